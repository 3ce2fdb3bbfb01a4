// 2-D convolution on the tensor cores: conv.wgsl's implicit GEMM (rows = output channels,
// columns = pixels, depth = Cin x taps) with the weight and im2col tiles staged in workgroup
// memory as f16 and multiplied by 16x16x16 cooperative matrices into f32 sums. Each 32-lane
// subgroup owns a (16 FM) x (16 FN) block of the BM x BN tile; the sums go through workgroup
// memory to the shared f32 epilogue. conv_io.wgsl and conv_epilogue.wgsl are appended (as to
// conv.wgsl), so the parameters, options and split-K partial sums are conv.wgsl's.
//
// With PREFETCH each thread's share of the next depth step's tiles is read from global memory
// into registers before this step's multiply-adds, so its latency hides behind them. The
// registers are scalars written out per tile by conv.rs (REG_*): arrays indexed in loops were
// kept in slow local memory by the driver (25% slower on an H200).
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
    if (PREFETCH) {
{{REG_DECL}}
        var kf = k_lo;
{{REG_FETCH}}
        for (var k0 = k_lo; k0 < k_hi; k0 = k0 + BK) {
{{REG_STORE}}
            workgroupBarrier();
            if (k0 + BK < k_hi) {
                kf = k0 + BK;
{{REG_FETCH}}
            }
            for (var kk = 0u; kk < BK; kk = kk + 16u) {
{{MMA}}
            }
            workgroupBarrier();
        }
    } else {
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
    }
    // Each 16x16 block of sums in turn: stored to the subgroup's staging area, then through
    // the epilogue, 8 values a lane.
{{STORE}}
}

// Element e of the weight tile at depth k0 (zero past the layer's channels and the depth end).
fn fetch_a(e: u32, m0: u32, k0: u32, k_hi: u32) -> f16 {
    let m = e / BK;
    let kk = e % BK;
    var v = 0.0;
    if (e < BM * BK && m0 + m < p.cout && k0 + kk < k_hi) {
        v = wt[(m0 + m) * p.cin * TAPS + k0 + kk];
    }
    return f16(v);
}

// Element e of the input tile at depth k0; where whole columns fall to whole threads, the
// column's pixel (b_y, b_x) is the calling thread's.
fn fetch_b(e: u32, n0: u32, k0: u32, k_hi: u32, b_y: i32, b_x: i32) -> f16 {
    if (e >= BK * BN) {
        return f16(0.0);
    }
    let kk = e / BN;
    let pix = n0 + e % BN;
    if (THREADS % BN == 0u) {
        return f16(load_x(k0 + kk, k_hi, pix, b_y, b_x));
    }
    return f16(load_x(k0 + kk, k_hi, pix, i32(pix / p.w), i32(pix % p.w)));
}
