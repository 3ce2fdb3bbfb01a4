// LayerNorm over the channels of each token of a channel-major [C, stride] activation (the
// ViT keeps tokens as columns so that its linear layers are 1x1 convolutions). One thread per
// token; the mean first, then the variance of the centred values (the CPU path's two passes).

struct P {
    c: u32,
    n: u32,
    in_off: u32,
    in_stride: u32,
    out_off: u32,
    out_stride: u32,
    w_off: u32,
    b_off: u32,
    eps: f32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
// gamma at w_off, beta at b_off
@group(0) @binding(2) var<storage, read> vecs: array<f32>;
@group(0) @binding(3) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x;
    if (t >= p.n) {
        return;
    }
    var sum = 0.0;
    for (var ch = 0u; ch < p.c; ch = ch + 1u) {
        sum = sum + x[p.in_off + ch * p.in_stride + t];
    }
    let mean = sum / f32(p.c);
    var sq = 0.0;
    for (var ch = 0u; ch < p.c; ch = ch + 1u) {
        let d = x[p.in_off + ch * p.in_stride + t] - mean;
        sq = fma(d, d, sq);
    }
    let inv = 1.0 / sqrt(sq / f32(p.c) + p.eps);
    for (var ch = 0u; ch < p.c; ch = ch + 1u) {
        let d = x[p.in_off + ch * p.in_stride + t] - mean;
        y[p.out_off + ch * p.out_stride + t] = d * inv * vecs[p.w_off + ch] + vecs[p.b_off + ch];
    }
}
