// The gradient of gaussians.wgsl's lifting branch (LIFT): from the gradients of one plane's
// activated Gaussians (Gaussian-major, at Gaussian `g0`; its means at float `means_off`) back
// to the generator's raw output [C + 9, M] (channel-major). Per raw value:
// - a colour: through the sigmoid where the release applies it (image columns 0..2), else 1;
// - opacity, scale (x SCALE_MAX), lifting distance: through the sigmoid, s (1 - s);
// - rotation r -> r / max(|r|, eps): (g - u (u . g)) / |r| with u = r / |r|, or g / eps where
//   the norm is clamped (its derivative is then 0);
// - distance d -> point + sign d dir: sign (dir . dmean).

const SCALE_MAX: f32 = 0.05;
const NORMALIZE_EPS: f32 = 1e-12;

struct P {
    m: u32,
    c: u32,
    side: u32,
    g0: u32,
    means_off: u32,
    out_off: u32,
    sign: f32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
// the plane's points [M, 3] then the view direction [3]
@group(0) @binding(2) var<storage, read> plane: array<f32>;
@group(0) @binding(3) var<storage, read> d_features: array<f32>;
@group(0) @binding(4) var<storage, read> d_opacities: array<f32>;
@group(0) @binding(5) var<storage, read> d_scales: array<f32>;
@group(0) @binding(6) var<storage, read> d_rotations: array<f32>;
@group(0) @binding(7) var<storage, read> d_means: array<f32>;
@group(0) @binding(8) var<storage, read_write> dx: array<f32>;

fn sigmoid(v: f32) -> f32 {
    return 1.0 / (1.0 + exp(-v));
}

fn raw(ch: u32, i: u32) -> f32 {
    return x[ch * p.m + i];
}

fn sig_grad(ch: u32, i: u32) -> f32 {
    let s = sigmoid(raw(ch, i));
    return s * (1.0 - s);
}

fn put(ch: u32, i: u32, v: f32) {
    dx[p.out_off + ch * p.m + i] = v;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.m) {
        return;
    }
    let g = p.g0 + i;
    let squash = i % p.side < 3u;
    for (var ch = 0u; ch < p.c; ch = ch + 1u) {
        var d = d_features[g * p.c + ch];
        if (squash) {
            d = d * sig_grad(ch, i);
        }
        put(ch, i, d);
    }
    put(p.c, i, d_opacities[g] * sig_grad(p.c, i));
    for (var k = 0u; k < 3u; k = k + 1u) {
        put(p.c + 1u + k, i, d_scales[g * 3u + k] * SCALE_MAX * sig_grad(p.c + 1u + k, i));
    }
    let r = vec4<f32>(
        raw(p.c + 4u, i),
        raw(p.c + 5u, i),
        raw(p.c + 6u, i),
        raw(p.c + 7u, i),
    );
    let gr = vec4<f32>(
        d_rotations[g * 4u],
        d_rotations[g * 4u + 1u],
        d_rotations[g * 4u + 2u],
        d_rotations[g * 4u + 3u],
    );
    let norm = sqrt(dot(r, r));
    var dr = gr / NORMALIZE_EPS;
    if (norm > NORMALIZE_EPS) {
        let u = r / norm;
        dr = (gr - u * dot(u, gr)) / norm;
    }
    put(p.c + 4u, i, dr.x);
    put(p.c + 5u, i, dr.y);
    put(p.c + 6u, i, dr.z);
    put(p.c + 7u, i, dr.w);
    let dir_at = 3u * p.m;
    var dd = 0.0;
    for (var k = 0u; k < 3u; k = k + 1u) {
        dd = dd + d_means[p.means_off + i * 3u + k] * plane[dir_at + k];
    }
    put(p.c + 8u, i, p.sign * dd * sig_grad(p.c + 8u, i));
}
