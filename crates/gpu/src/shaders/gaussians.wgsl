// A generator's raw output [C + 8 (+ 1), M] (channel-major, M Gaussians) activated into the
// splatting's Gaussian-major buffers at Gaussian `g0` (spec 5: colours sigmoid on their first
// three, opacity sigmoid, scales sigmoid x SCALE_MAX). The lifting generators (LIFT) also
// L2-normalise each rotation, move each plane point along the view direction by its sigmoid
// distance (l0 forward, l1 backward) and, as the release does, apply the colour sigmoid to the
// first three image columns rather than the first three channels. The expression generator's
// rotations are normalised across the Gaussians (the release's dim-1 quirk), by
// rotations_across.wgsl.

const LIFT: bool = {{LIFT}};
const SCALE_MAX: f32 = 0.05;
const NORMALIZE_EPS: f32 = 1e-12;

struct P {
    m: u32,
    c: u32,
    side: u32,
    g0: u32,
    in_off: u32,
    means_off: u32,
    sign: f32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
// the plane's points [M, 3] then the view direction [3]
@group(0) @binding(2) var<storage, read> plane: array<f32>;
@group(0) @binding(3) var<storage, read_write> features: array<f32>;
@group(0) @binding(4) var<storage, read_write> opacities: array<f32>;
@group(0) @binding(5) var<storage, read_write> scales: array<f32>;
@group(0) @binding(6) var<storage, read_write> rotations: array<f32>;
@group(0) @binding(7) var<storage, read_write> means: array<f32>;

fn sigmoid(v: f32) -> f32 {
    return 1.0 / (1.0 + exp(-v));
}

fn raw(ch: u32, i: u32) -> f32 {
    return x[p.in_off + ch * p.m + i];
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.m) {
        return;
    }
    let g = p.g0 + i;
    for (var ch = 0u; ch < p.c; ch = ch + 1u) {
        var v = raw(ch, i);
        var squash = ch < 3u;
        if (LIFT) {
            squash = i % p.side < 3u;
        }
        if (squash) {
            v = sigmoid(v);
        }
        features[g * p.c + ch] = v;
    }
    opacities[g] = sigmoid(raw(p.c, i));
    for (var k = 0u; k < 3u; k = k + 1u) {
        scales[g * 3u + k] = sigmoid(raw(p.c + 1u + k, i)) * SCALE_MAX;
    }
    if (LIFT) {
        let r = vec4<f32>(
            raw(p.c + 4u, i),
            raw(p.c + 5u, i),
            raw(p.c + 6u, i),
            raw(p.c + 7u, i),
        );
        let norm = max(sqrt(dot(r, r)), NORMALIZE_EPS);
        let u = r / norm;
        rotations[g * 4u] = u.x;
        rotations[g * 4u + 1u] = u.y;
        rotations[g * 4u + 2u] = u.z;
        rotations[g * 4u + 3u] = u.w;
        let dist = sigmoid(raw(p.c + 8u, i));
        let dir_at = 3u * p.m;
        for (var k = 0u; k < 3u; k = k + 1u) {
            means[p.means_off + i * 3u + k] = plane[i * 3u + k] + p.sign * dist * plane[dir_at + k];
        }
    }
}
