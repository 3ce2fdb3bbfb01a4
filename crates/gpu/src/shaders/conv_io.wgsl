// What conv.wgsl and conv_mma.wgsl share (appended to both, with conv_epilogue.wgsl, which holds
// the parameters and epilogue flags): the input options and buffers of one convolution, the
// im2col read and the output write.

const KS: u32 = {{KSIZE}}u;
const TAPS: u32 = KS * KS;
const PAD: i32 = i32(KS / 2u);
const SPLIT: u32 = {{SPLIT}}u;
const IN_SCALE: bool = {{IN_SCALE}};
// ReLU on the input as it is read (DPT's pre-activation residual units).
const IN_RELU: bool = {{IN_RELU}};

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
// [cout, cin * taps]
@group(0) @binding(2) var<storage, read> wt: array<f32>;
// biases, styles and demodulation factors of every layer, at the offsets in P
@group(0) @binding(3) var<storage, read> vecs: array<f32>;
// the residual [cout, H, W] or the noise [H, W]
@group(0) @binding(4) var<storage, read> aux: array<f32>;
// SFT scale and shift maps [cout, H, W]
@group(0) @binding(5) var<storage, read> sft: array<f32>;
@group(0) @binding(6) var<storage, read_write> y: array<f32>;

// The im2col value at depth `kidx` (input channel, tap) for output pixel `pix` at (py, px),
// zero outside the image and past the depth end.
fn load_x(kidx: u32, k_hi: u32, pix: u32, py: i32, px: i32) -> f32 {
    let hw = p.h * p.w;
    if (kidx >= k_hi || pix >= hw) {
        return 0.0;
    }
    let ci = kidx / TAPS;
    let tap = kidx % TAPS;
    let yy = py + i32(tap / KS) - PAD;
    let xx = px + i32(tap % KS) - PAD;
    if (yy < 0 || yy >= i32(p.h) || xx < 0 || xx >= i32(p.w)) {
        return 0.0;
    }
    var v = x[p.in_off + ci * hw + u32(yy) * p.w + u32(xx)];
    if (IN_SCALE) {
        v = v * vecs[p.insc_off + ci];
    }
    if (IN_RELU) {
        v = max(v, 0.0);
    }
    return v;
}

// Stores one output value (or, with split-K, one partial sum) after the epilogue.
fn emit(co: u32, pix: u32, acc: f32, slice: u32) {
    let hw = p.h * p.w;
    if (co >= p.cout || pix >= hw) {
        return;
    }
    if (SPLIT > 0u) {
        y[(slice * p.cout + co) * hw + pix] = acc;
        return;
    }
    y[p.out_off + co * hw + pix] = epilogue(acc, co, pix, hw);
}
