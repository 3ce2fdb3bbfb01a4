// Splatting backward, step 3: each Gaussian's gradient is the sum of its pairs' sums, in the
// order of its tiles (row by row): no atomics, the same result on every run. Threads past the
// Gaussians sum the background's gradient over the tiles.

struct P {
    n: u32,
    tiles: u32,
    bg_off: u32,
    _p0: u32,
}

const C: u32 = {{CHANNELS}}u;
// Per Gaussian: C feature gradients, then mean x, mean y, conic A, B, C, opacity.
const S: u32 = C + 6u;

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> info: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> pairs: array<f32>;
// [N, S], then the background's [C]
@group(0) @binding(3) var<storage, read_write> grads: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 64u);
    if (i < p.n) {
        let first = info[i].z;
        let count = info[i].w;
        for (var v = 0u; v < S; v = v + 1u) {
            var s = 0.0;
            for (var q = 0u; q < count; q = q + 1u) {
                s = s + pairs[(first + q) * S + v];
            }
            grads[i * S + v] = s;
        }
    } else if (i < p.n + C) {
        let c = i - p.n;
        var s = 0.0;
        for (var t = 0u; t < p.tiles; t = t + 1u) {
            s = s + pairs[p.bg_off + t * C + c];
        }
        grads[p.n * S + c] = s;
    }
}
