// FLAME per frame, part 2: blendshapes (expression + pose correctives) on the identity's
// shaped template, then linear blend skinning and the x5 scale. One thread per vertex.

struct P {
    n_vertices: u32,
    n_coeffs: u32,
    scale: f32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
// [V * 3] template + shape blendshapes of the identity
@group(0) @binding(1) var<storage, read> v_shaped: array<f32>;
// [n_coeffs, V * 3]: expression blendshapes, then pose correctives
@group(0) @binding(2) var<storage, read> dirs: array<f32>;
@group(0) @binding(3) var<storage, read> coeffs: array<f32>;
// [V, 5]
@group(0) @binding(4) var<storage, read> weights: array<f32>;
// [5, 12]
@group(0) @binding(5) var<storage, read> transforms: array<f32>;
// out: [V * 3]
@group(0) @binding(6) var<storage, read_write> vertices: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let v = gid.x;
    if (v >= p.n_vertices) {
        return;
    }
    let v3 = 3u * p.n_vertices;
    var x = 0.0;
    var y = 0.0;
    var z = 0.0;
    for (var k = 0u; k < p.n_coeffs; k = k + 1u) {
        let c = coeffs[k];
        let o = k * v3 + 3u * v;
        x = x + c * dirs[o];
        y = y + c * dirs[o + 1u];
        z = z + c * dirs[o + 2u];
    }
    x = x + v_shaped[3u * v];
    y = y + v_shaped[3u * v + 1u];
    z = z + v_shaped[3u * v + 2u];
    var m: array<f32, 12>;
    for (var i = 0u; i < 12u; i = i + 1u) {
        m[i] = 0.0;
    }
    for (var j = 0u; j < 5u; j = j + 1u) {
        let w = weights[v * 5u + j];
        for (var i = 0u; i < 12u; i = i + 1u) {
            m[i] = m[i] + w * transforms[j * 12u + i];
        }
    }
    for (var r = 0u; r < 3u; r = r + 1u) {
        vertices[3u * v + r] = (m[4u * r] * x + m[4u * r + 1u] * y + m[4u * r + 2u] * z + m[4u * r + 3u]) * p.scale;
    }
}
