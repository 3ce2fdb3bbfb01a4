// 2-D convolution (1x1 or 3x3, stride 1, zero padding k/2) of one [Cin, H, W] image as an
// implicit GEMM: rows = output channels, columns = pixels, depth = Cin x taps. A workgroup
// computes a BM x BN output tile with (BM/TM) x (BN/TN) threads of TM x TN outputs each,
// staging BK-deep slices of the weights and of the (im2col) input in workgroup memory.
//
// Options (compile-time flags): per-input-channel scale of the input (a modulated conv's
// style) and ReLU of the input, per-output-channel scale (its demodulation x gain), then
//   v = acc * out_scale + bias + noise_weight * noise; activation (leaky ReLU, ReLU or GELU);
//   + residual; * sft_scale + sft_shift; sigmoid
// in the CPU path's order (`conv_epilogue.wgsl`, appended to this source with `conv_io.wgsl`:
// the parameters, buffers, im2col read and output write conv_mma.wgsl shares). With split-K
// (SPLIT > 0) a workgroup covers only `SPLIT` of the depth and writes raw partial sums;
// `conv_finish.wgsl` adds them and applies the epilogue.

const BM: u32 = {{BM}}u;
const BN: u32 = {{BN}}u;
const BK: u32 = {{BK}}u;
const TM: u32 = {{TM}}u;
const TN: u32 = {{TN}}u;
const THREADS: u32 = (BM / TM) * (BN / TN);

var<workgroup> As: array<f32, BK * BM>;
var<workgroup> Bs: array<f32, BK * BN>;

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
