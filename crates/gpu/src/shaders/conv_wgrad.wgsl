// Weight gradient of a stride-1 convolution (1x1 or 3x3, zero padding k/2) of one [Cin, H, W]
// image: dW[co, ci * taps + tap] = sum over pixels of dZ[co, pix] * X[ci, pix shifted by tap],
// a GEMM with rows = output channels, columns = (input channel, tap) and depth = pixels.
// A workgroup computes a BM x BN tile of dW over the pixels of slice `wid.z` (SLICE pixels each)
// with (BM/TM) x (BN/TN) threads of TM x TN sums, staging BK pixels of dZ and of the im2col'd
// input in workgroup memory. Each slice writes its partial sums to `part`; `conv_wgrad_sum.wgsl`
// adds the slices in a fixed order, so the result does not depend on scheduling.

const BM: u32 = {{BM}}u;
const BN: u32 = {{BN}}u;
const BK: u32 = {{BK}}u;
const TM: u32 = {{TM}}u;
const TN: u32 = {{TN}}u;
const THREADS: u32 = (BM / TM) * (BN / TN);
const KS: u32 = {{KSIZE}}u;
const TAPS: u32 = KS * KS;
const PAD: i32 = i32(KS / 2u);

struct P {
    cin: u32,
    cout: u32,
    h: u32,
    w: u32,
    x_off: u32,
    dz_off: u32,
    // pixels per slice (a multiple of BK)
    slice: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read> dz: array<f32>;
// [slices, cout, cin * taps]
@group(0) @binding(3) var<storage, read_write> part: array<f32>;

var<workgroup> As: array<f32, BK * BM>;
var<workgroup> Bs: array<f32, BK * BN>;

fn load_x(j: u32, pix: u32, hw: u32) -> f32 {
    if (j >= p.cin * TAPS || pix >= hw) {
        return 0.0;
    }
    let ci = j / TAPS;
    let tap = j % TAPS;
    let yy = i32(pix / p.w) + i32(tap / KS) - PAD;
    let xx = i32(pix % p.w) + i32(tap % KS) - PAD;
    if (yy < 0 || yy >= i32(p.h) || xx < 0 || xx >= i32(p.w)) {
        return 0.0;
    }
    return x[p.x_off + ci * hw + u32(yy) * p.w + u32(xx)];
}

fn emit(co: u32, j: u32, acc: f32, slice: u32) {
    let cols = p.cin * TAPS;
    if (co >= p.cout || j >= cols) {
        return;
    }
    part[(slice * p.cout + co) * cols + j] = acc;
}

@compute @workgroup_size(THREADS)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let hw = p.h * p.w;
    let n0 = wid.x * BN;
    let m0 = wid.y * BM;
    let tx = t % (BN / TN);
    let ty = t / (BN / TN);
    let k_lo = wid.z * p.slice;
    let k_hi = min(hw, k_lo + p.slice);
{{ACC_DECL}}
    for (var k0 = k_lo; k0 < k_hi; k0 = k0 + BK) {
        // Pixels vary fastest across threads: neighbouring threads read neighbouring values.
        for (var e = t; e < BM * BK; e = e + THREADS) {
            let m = e / BK;
            let kk = e % BK;
            var v = 0.0;
            if (m0 + m < p.cout && k0 + kk < k_hi) {
                v = dz[p.dz_off + (m0 + m) * hw + k0 + kk];
            }
            As[kk * BM + m] = v;
        }
        for (var e = t; e < BN * BK; e = e + THREADS) {
            let n = e / BK;
            let kk = e % BK;
            var v = 0.0;
            if (k0 + kk < k_hi) {
                v = load_x(n0 + n, k0 + kk, hw);
            }
            Bs[kk * BN + n] = v;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk = kk + 1u) {
            let ar = kk * BM + ty * TM;
            let br = kk * BN + tx * TN;
{{MICRO}}
        }
        workgroupBarrier();
    }
    // The micro-tile's rows are output channels and its columns (input channel, tap) pairs.
    let co0 = m0 + ty * TM;
    let pix0 = n0 + tx * TN;
{{EMIT}}
}
