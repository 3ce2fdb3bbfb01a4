// LayerNorm over the channels of each token of a channel-major [C, stride] activation (the
// ViT keeps tokens as columns so that its linear layers are 1x1 convolutions). SLICES threads
// share a token, each summing every SLICES-th channel, so a workgroup of 256 threads covers
// 256 / SLICES tokens: a few thousand tokens still fill a large GPU, where one thread per token
// walked all 768 channels alone. The mean first, then the variance of the centred values (the
// CPU path's two passes).

const SLICES: u32 = {{SLICES}}u;
const TOK: u32 = 256u / SLICES;

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

var<workgroup> part: array<f32, 256>;

// The sum over the slices of this thread's token (every thread of the token gets it).
fn token_sum(li: u32, tl: u32, v: f32) -> f32 {
    part[li] = v;
    workgroupBarrier();
    var s = 0.0;
    for (var k = 0u; k < SLICES; k = k + 1u) {
        s = s + part[k * TOK + tl];
    }
    workgroupBarrier();
    return s;
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    // Consecutive threads take consecutive tokens, so each channel row is read in runs.
    let tl = li % TOK;
    let sl = li / TOK;
    let t = wid.x * TOK + tl;
    // Threads past the last token still reach every barrier.
    let live = t < p.n;
    var sum = 0.0;
    if (live) {
        for (var ch = sl; ch < p.c; ch = ch + SLICES) {
            sum = sum + x[p.in_off + ch * p.in_stride + t];
        }
    }
    let mean = token_sum(li, tl, sum) / f32(p.c);
    var sq = 0.0;
    if (live) {
        for (var ch = sl; ch < p.c; ch = ch + SLICES) {
            let d = x[p.in_off + ch * p.in_stride + t] - mean;
            sq = fma(d, d, sq);
        }
    }
    let inv = 1.0 / sqrt(token_sum(li, tl, sq) / f32(p.c) + p.eps);
    if (live) {
        for (var ch = sl; ch < p.c; ch = ch + SLICES) {
            let d = x[p.in_off + ch * p.in_stride + t] - mean;
            y[p.out_off + ch * p.out_stride + t] = d * inv * vecs[p.w_off + ch] + vecs[p.b_off + ch];
        }
    }
}
