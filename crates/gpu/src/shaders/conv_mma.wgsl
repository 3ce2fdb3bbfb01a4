// 2-D convolution on the tensor cores: conv.wgsl's implicit GEMM (rows = output channels,
// columns = pixels, depth = Cin x taps) with the weight and im2col tiles staged in workgroup
// memory as f16 and multiplied by 16x16x16 cooperative matrices into f32 sums. Each 32-lane
// subgroup owns a (16 FM) x (16 FN) block of the BM x BN tile; the sums go through workgroup
// memory to the shared f32 epilogue. conv_io.wgsl and conv_epilogue.wgsl are appended (as to
// conv.wgsl), so the parameters, options and split-K partial sums are conv.wgsl's.
//
// Each thread's share of a depth step's tiles passes through registers. With PREFETCH the
// next step's share is fetched from global memory before this step's multiply-adds, so its
// latency hides behind them instead of stalling every step.
enable f16;
enable wgpu_cooperative_matrix;

const BM: u32 = {{BM}}u;
const BN: u32 = {{BN}}u;
const BK: u32 = {{BK}}u;
const FM: u32 = {{FM}}u;
const FN: u32 = {{FN}}u;
const WARPS_N: u32 = BN / (16u * FN);
const WARPS: u32 = (BM / (16u * FM)) * WARPS_N;
const THREADS: u32 = WARPS * 32u;
const PREFETCH: bool = {{PREFETCH}};
// Values of the weight and input tiles per thread and depth step.
const A_PER: u32 = (BM * BK + THREADS - 1u) / THREADS;
const B_PER: u32 = (BK * BN + THREADS - 1u) / THREADS;

var<private> ra: array<f16, A_PER>;
var<private> rb: array<f16, B_PER>;

// Weights [m][k] and inputs [k][n], row-major; one 16x16 block of sums per subgroup on its
// way to the epilogue.
var<workgroup> As: array<f16, BM * BK>;
var<workgroup> Bs: array<f16, BK * BN>;
var<workgroup> Cs: array<f32, WARPS * 256u>;

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
    fetch(m0, n0, k_lo, k_hi, t, b_y, b_x);
    for (var k0 = k_lo; k0 < k_hi; k0 = k0 + BK) {
        if (!PREFETCH && k0 != k_lo) {
            fetch(m0, n0, k0, k_hi, t, b_y, b_x);
        }
        for (var i = 0u; i < A_PER; i = i + 1u) {
            let e = t + i * THREADS;
            if (e < BM * BK) {
                As[e] = ra[i];
            }
        }
        for (var i = 0u; i < B_PER; i = i + 1u) {
            let e = t + i * THREADS;
            if (e < BK * BN) {
                Bs[e] = rb[i];
            }
        }
        workgroupBarrier();
        if (PREFETCH && k0 + BK < k_hi) {
            fetch(m0, n0, k0 + BK, k_hi, t, b_y, b_x);
        }
        for (var kk = 0u; kk < BK; kk = kk + 16u) {
{{MMA}}
        }
        workgroupBarrier();
    }
    // Each 16x16 block of sums in turn: stored to the subgroup's staging area, then through
    // the epilogue, 8 values a lane.
{{STORE}}
}

// This thread's share of the weight and input tiles at depth k0 into ra and rb (zeros past
// the layer's channels, the image and the depth end). Element e of a tile is t + i THREADS;
// where whole input columns fall to whole threads, the column's pixel (b_y, b_x) is this
// thread's alone.
fn fetch(m0: u32, n0: u32, k0: u32, k_hi: u32, t: u32, b_y: i32, b_x: i32) {
    let kdim = p.cin * TAPS;
    for (var i = 0u; i < A_PER; i = i + 1u) {
        let e = t + i * THREADS;
        let m = e / BK;
        let kk = e % BK;
        var v = 0.0;
        if (e < BM * BK && m0 + m < p.cout && k0 + kk < k_hi) {
            v = wt[(m0 + m) * kdim + k0 + kk];
        }
        ra[i] = f16(v);
    }
    for (var i = 0u; i < B_PER; i = i + 1u) {
        let e = t + i * THREADS;
        let kk = e / BN;
        let pix = n0 + e % BN;
        var v = 0.0;
        if (e < BK * BN) {
            if (THREADS % BN == 0u) {
                v = load_x(k0 + kk, k_hi, pix, b_y, b_x);
            } else {
                v = load_x(k0 + kk, k_hi, pix, i32(pix / p.w), i32(pix % p.w));
            }
        }
        rb[i] = f16(v);
    }
}
