// 2-D convolution on the tensor cores: conv.wgsl's implicit GEMM (rows = output channels,
// columns = pixels, depth = Cin x taps) with the weight and im2col tiles staged in workgroup
// memory as f16 and multiplied by 16x16x16 cooperative matrices into f32 sums. Each 32-lane
// subgroup owns a (16 FM) x (16 FN) block of the BM x BN tile; the sums go through workgroup
// memory to the shared f32 epilogue (conv_epilogue.wgsl, appended), so the options and the
// split-K partial sums are conv.wgsl's.
enable f16;
enable wgpu_cooperative_matrix;

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
const FM: u32 = {{FM}}u;
const FN: u32 = {{FN}}u;
const WARPS_N: u32 = BN / (16u * FN);
const WARPS: u32 = (BM / (16u * FM)) * WARPS_N;
const THREADS: u32 = WARPS * 32u;
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
@group(0) @binding(3) var<storage, read> vecs: array<f32>;
@group(0) @binding(4) var<storage, read> aux: array<f32>;
@group(0) @binding(5) var<storage, read> sft: array<f32>;
@group(0) @binding(6) var<storage, read_write> y: array<f32>;

// Weights [m][k] and inputs [k][n], row-major; one 16x16 block of sums per subgroup on its
// way to the epilogue.
var<workgroup> As: array<f16, BM * BK>;
var<workgroup> Bs: array<f16, BK * BN>;
var<workgroup> Cs: array<f32, WARPS * 256u>;

// The im2col value at depth `kidx` for output pixel `pix` at (py, px), zero outside the image
// and past the depth end.
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
    let n0 = wid.x * BN;
    let m0 = wid.y * BM;
    let warp = t / 32u;
    let lane = t % 32u;
    // This subgroup's block of the tile, and its 16x16 staging area.
    let wm = (warp / WARPS_N) * 16u * FM;
    let wn = (warp % WARPS_N) * 16u * FN;
    let cs = warp * 256u;
    let kdim = p.cin * TAPS;
    var k_lo = 0u;
    var k_hi = kdim;
    if (SPLIT > 0u) {
        k_lo = wid.z * SPLIT;
        k_hi = min(kdim, k_lo + SPLIT);
    }
    // This thread's input column (when whole columns fall to whole threads).
    let b_col = t % BN;
    let b_pix = n0 + b_col;
    let b_y = i32(b_pix / p.w);
    let b_x = i32(b_pix % p.w);
    // The accumulators start from zeros loaded out of workgroup memory.
    for (var e = lane; e < 256u; e = e + 32u) {
        Cs[cs + e] = 0.0;
    }
    workgroupBarrier();
{{ACC_DECL}}
    for (var k0 = k_lo; k0 < k_hi; k0 = k0 + BK) {
        for (var e = t; e < BM * BK; e = e + THREADS) {
            let m = e / BK;
            let kk = e % BK;
            var v = 0.0;
            if (m0 + m < p.cout && k0 + kk < k_hi) {
                v = wt[(m0 + m) * kdim + k0 + kk];
            }
            As[e] = f16(v);
        }
        if (THREADS % BN == 0u) {
            for (var kk = t / BN; kk < BK; kk = kk + THREADS / BN) {
                Bs[kk * BN + b_col] = f16(load_x(k0 + kk, k_hi, b_pix, b_y, b_x));
            }
        } else {
            for (var e = t; e < BK * BN; e = e + THREADS) {
                let kk = e / BN;
                let pix = n0 + e % BN;
                Bs[e] = f16(load_x(k0 + kk, k_hi, pix, i32(pix / p.w), i32(pix % p.w)));
            }
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk = kk + 16u) {
{{MMA}}
        }
        workgroupBarrier();
    }
    // Each 16x16 block of sums in turn: stored to the subgroup's staging area, then through
    // the epilogue, 8 values a lane.
{{STORE}}
}
