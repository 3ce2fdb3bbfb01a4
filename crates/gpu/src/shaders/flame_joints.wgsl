// FLAME per frame, part 1 (spec section 9): the posed joints' skinning transforms and the
// blendshape coefficients (expression, then the 36 pose-corrective features), from the codes.
// One workgroup: 15 threads regress the rest joints, then thread 0 runs the 5-joint chain.

struct P {
    n_exp: u32,
    parent1: u32,
    parent2: u32,
    parent3: u32,
    parent4: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
// [n_exp expression | 6 pose (global, jaw) | 6 eye]
@group(0) @binding(1) var<storage, read> codes: array<f32>;
// [15] the identity's rest joints
@group(0) @binding(2) var<storage, read> j_rest: array<f32>;
// [n_exp, 15] joint regressor applied to each expression blendshape
@group(0) @binding(3) var<storage, read> j_exp: array<f32>;
// out: [n_exp + 36] blendshape coefficients
@group(0) @binding(4) var<storage, read_write> coeffs: array<f32>;
// out: [5, 12] row-major [R | t] per joint
@group(0) @binding(5) var<storage, read_write> transforms: array<f32>;

var<workgroup> joints: array<f32, 15>;

fn rodrigues(r: vec3<f32>) -> mat3x3<f32> {
    let e = r + vec3<f32>(1e-8);
    let angle = sqrt(e.x * e.x + e.y * e.y + e.z * e.z);
    let d = r / angle;
    let sc = sin_cos(angle);
    let s = sc.x;
    let omc = sc.y * -1.0 + 1.0;
    let x = d.x;
    let y = d.y;
    let z = d.z;
    // Columns of R = I + sin K + (1 - cos) K^2, entries as the CPU path builds them.
    let r00 = ((y * y + z * z) * omc) * -1.0 + 1.0;
    let r01 = (x * y) * omc + (z * s) * -1.0;
    let r02 = (x * z) * omc + (y * s);
    let r10 = (x * y) * omc + (z * s);
    let r11 = ((x * x + z * z) * omc) * -1.0 + 1.0;
    let r12 = (y * z) * omc + (x * s) * -1.0;
    let r20 = (x * z) * omc + (y * s) * -1.0;
    let r21 = (y * z) * omc + (x * s);
    let r22 = ((x * x + y * y) * omc) * -1.0 + 1.0;
    return mat3x3<f32>(vec3<f32>(r00, r10, r20), vec3<f32>(r01, r11, r21), vec3<f32>(r02, r12, r22));
}

fn parent(i: u32) -> u32 {
    switch i {
        case 1u: { return p.parent1; }
        case 2u: { return p.parent2; }
        case 3u: { return p.parent3; }
        default: { return p.parent4; }
    }
}

@compute @workgroup_size(64)
fn main(@builtin(local_invocation_index) t: u32) {
    let ne = p.n_exp;
    if (t < 15u) {
        var acc = 0.0;
        for (var e = 0u; e < ne; e = e + 1u) {
            acc = acc + codes[e] * j_exp[e * 15u + t];
        }
        joints[t] = acc + j_rest[t];
    }
    for (var e = t; e < ne; e = e + 64u) {
        coeffs[e] = codes[e];
    }
    workgroupBarrier();
    if (t != 0u) {
        return;
    }
    // Full pose: [global = pose 0..3, neck = 0, jaw = pose 3..6, eye 0..3, eye 3..6].
    var rot: array<mat3x3<f32>, 5>;
    let c = ne;
    rot[0] = rodrigues(vec3<f32>(codes[c], codes[c + 1u], codes[c + 2u]));
    rot[1] = rodrigues(vec3<f32>(0.0, 0.0, 0.0));
    rot[2] = rodrigues(vec3<f32>(codes[c + 3u], codes[c + 4u], codes[c + 5u]));
    rot[3] = rodrigues(vec3<f32>(codes[c + 6u], codes[c + 7u], codes[c + 8u]));
    rot[4] = rodrigues(vec3<f32>(codes[c + 9u], codes[c + 10u], codes[c + 11u]));
    // Pose feature: joints 1..4, (R - I) row-major.
    for (var j = 1u; j < 5u; j = j + 1u) {
        for (var row = 0u; row < 3u; row = row + 1u) {
            for (var col = 0u; col < 3u; col = col + 1u) {
                var v = rot[j][col][row];
                if (row == col) {
                    v = v - 1.0;
                }
                coeffs[ne + (j - 1u) * 9u + row * 3u + col] = v;
            }
        }
    }
    var world_r: array<mat3x3<f32>, 5>;
    var world_t: array<vec3<f32>, 5>;
    for (var i = 0u; i < 5u; i = i + 1u) {
        let ji = vec3<f32>(joints[3u * i], joints[3u * i + 1u], joints[3u * i + 2u]);
        var rw: mat3x3<f32>;
        var tw: vec3<f32>;
        if (i == 0u) {
            rw = rot[0];
            tw = ji;
        } else {
            let par = parent(i);
            let jp = vec3<f32>(joints[3u * par], joints[3u * par + 1u], joints[3u * par + 2u]);
            rw = world_r[par] * rot[i];
            tw = world_r[par] * (ji - jp) + world_t[par];
        }
        world_r[i] = rw;
        world_t[i] = tw;
        let tr = tw - rw * ji;
        for (var row = 0u; row < 3u; row = row + 1u) {
            transforms[i * 12u + row * 4u] = rw[0][row];
            transforms[i * 12u + row * 4u + 1u] = rw[1][row];
            transforms[i * 12u + row * 4u + 2u] = rw[2][row];
            transforms[i * 12u + row * 4u + 3u] = tr[row];
        }
    }
}
