// Max-pooling `k x k`, stride `s`, no padding, floor mode, of `[c, h, w]` into `[c, oh, ow]`.
// One thread per output value.

struct P {
    c: u32,
    h: u32,
    w: u32,
    k: u32,
    s: u32,
    oh: u32,
    ow: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.c * p.oh * p.ow) {
        return;
    }
    let c = i / (p.oh * p.ow);
    let oy = (i / p.ow) % p.oh;
    let ox = i % p.ow;
    let base = c * p.h * p.w;
    var best = x[base + oy * p.s * p.w + ox * p.s];
    for (var dy = 0u; dy < p.k; dy++) {
        for (var dx = 0u; dx < p.k; dx++) {
            best = max(best, x[base + (oy * p.s + dy) * p.w + ox * p.s + dx]);
        }
    }
    y[i] = best;
}
