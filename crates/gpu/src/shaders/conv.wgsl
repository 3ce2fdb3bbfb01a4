// 2-D convolution (1x1 or 3x3, stride 1, zero padding k/2) of one [Cin, H, W] image as an
// implicit GEMM: rows = output channels, columns = pixels, depth = Cin x taps. A workgroup
// computes a BM x BN output tile with (BM/TM) x (BN/TN) threads of TM x TN outputs each,
// staging BK-deep slices of the weights and of the (im2col) input in workgroup memory.
//
// Options (compile-time flags): per-input-channel scale of the input (a modulated conv's
// style), per-output-channel scale (its demodulation x gain), then
//   v = acc * out_scale + bias + noise_weight * noise; lrelu; + residual; * sft_scale +
//   sft_shift; sigmoid
// in the CPU path's order (`conv_epilogue.wgsl`, appended to this source). With split-K (SPLIT > 0) a workgroup covers only `SPLIT` of the
// depth and writes raw partial sums; `conv_finish.wgsl` adds them and applies the epilogue.

struct P {
    cin: u32,
    cout: u32,
    h: u32,
    w: u32,
    in_off: u32,
    out_off: u32,
    bias_off: u32,
    insc_off: u32,
    outsc_off: u32,
    aux_off: u32,
    sft_scale_off: u32,
    sft_shift_off: u32,
    noise_w: f32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

const KS: u32 = {{KSIZE}}u;
const TAPS: u32 = KS * KS;
const PAD: i32 = i32(KS / 2u);
const BM: u32 = {{BM}}u;
const BN: u32 = {{BN}}u;
const BK: u32 = {{BK}}u;
const TM: u32 = {{TM}}u;
const TN: u32 = {{TN}}u;
const THREADS: u32 = (BM / TM) * (BN / TN);
const SPLIT: u32 = {{SPLIT}}u;
const IN_SCALE: bool = {{IN_SCALE}};
const OUT_SCALE: bool = {{OUT_SCALE}};
const BIAS: bool = {{BIAS}};
const NOISE: bool = {{NOISE}};
const LRELU: bool = {{LRELU}};
const RESID: bool = {{RESID}};
const SFT: bool = {{SFT}};
const SIGMOID: bool = {{SIGMOID}};

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

var<workgroup> As: array<f32, BK * BM>;
var<workgroup> Bs: array<f32, BK * BN>;

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

@compute @workgroup_size(THREADS)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let hw = p.h * p.w;
    let n0 = wid.x * BN;
    let m0 = wid.y * BM;
    let tx = t % (BN / TN);
    let ty = t / (BN / TN);
    let kdim = p.cin * TAPS;
    var k_lo = 0u;
    var k_hi = kdim;
    if (SPLIT > 0u) {
        k_lo = wid.z * SPLIT;
        k_hi = min(kdim, k_lo + SPLIT);
    }
    let b_col = t % BN;
    let b_pix = n0 + b_col;
    let b_y = i32(b_pix / p.w);
    let b_x = i32(b_pix % p.w);
{{ACC_DECL}}
    for (var k0 = k_lo; k0 < k_hi; k0 = k0 + BK) {
        if (THREADS % BK == 0u) {
            // Each thread loads one depth column of the weight tile, rows a stride apart.
            let kk = t % BK;
            for (var m = t / BK; m < BM; m = m + THREADS / BK) {
                var v = 0.0;
                if (m0 + m < p.cout && k0 + kk < k_hi) {
                    v = wt[(m0 + m) * kdim + k0 + kk];
                }
                As[kk * BM + m] = v;
            }
        } else {
            for (var e = t; e < BM * BK; e = e + THREADS) {
                let m = e / BK;
                let kk = e % BK;
                var v = 0.0;
                if (m0 + m < p.cout && k0 + kk < k_hi) {
                    v = wt[(m0 + m) * kdim + k0 + kk];
                }
                As[kk * BM + m] = v;
            }
        }
        if (THREADS % BN == 0u) {
            // Each thread loads one pixel column of the input tile (its coordinates computed
            // once), depth rows a stride apart.
            for (var kk = t / BN; kk < BK; kk = kk + THREADS / BN) {
                Bs[kk * BN + b_col] = load_x(k0 + kk, k_hi, b_pix, b_y, b_x);
            }
        } else {
            for (var e = t; e < BN * BK; e = e + THREADS) {
                let kk = e / BN;
                let n = e % BN;
                let pix = n0 + n;
                Bs[kk * BN + n] = load_x(k0 + kk, k_hi, pix, i32(pix / p.w), i32(pix % p.w));
            }
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk = kk + 1u) {
            let ar = kk * BM + ty * TM;
            let br = kk * BN + tx * TN;
{{MICRO}}
        }
        workgroupBarrier();
    }
    let co0 = m0 + ty * TM;
    let pix0 = n0 + tx * TN;
{{EMIT}}
}
