//! Winograd F(4x4, 3x3) for 3x3 stride-1 convolutions (Lavin & Gray 2016): each 4x4 output
//! tile costs 36 multiplies per input/output channel pair instead of 144. Per task (a band of
//! tile rows of one image): transform the 6x6 input tiles (`V = B^T d B`), run 36 GEMMs
//! `M[xi] = U[xi] V[xi]` over channels, transform back (`Y = A^T M A`) into the output.
//! The weight gradient uses the same tiles (Winograd's transposition principle). The points are
//! 0, +-1, +-2 (and infinity), the usual choice; in f32 the results differ from a direct sum by
//! up to ~4e-6 of `conv(|x|, |w|)`, about 10x the rounding of the GEMM path (tests/conv.rs).

// The transforms index several small arrays with the same tile coordinates; ranges read
// closer to the matrix formulas than zipped iterators.
#![allow(clippy::needless_range_loop)]

use super::elem::{alloc_output, balanced_chunk, gemm, multiversion, Elem, Mat, SendPtr};
use super::geom::Geom;
use candle_core::TensorId;
use rayon::prelude::*;
use std::sync::{Arc, Mutex};

/// Tiles transformed side by side in local arrays, so the transforms vectorise across tiles.
const LANES: usize = 16;
/// Tiles per task: enough for the GEMMs (`m` = tiles) to run their wide micro-kernels, while
/// `V` and `M` (36 x channels x tiles each) stay small (64..160 measured within 10% of each
/// other on the benchmark shapes).
const TILES_PER_TASK: usize = 96;

pub(crate) fn eligible(g: &Geom) -> bool {
    g.kh == 3 && g.kw == 3 && g.stride == 1 && g.ph == g.pw
}

/// `G g` for one kernel column/row `g` (3 -> 6).
#[inline(always)]
fn g6<T: Elem>(g0: T, g1: T, g2: T) -> [T; 6] {
    let (q, s, t) = (T::c(0.25), T::c(1.0 / 6.0), T::c(1.0 / 12.0));
    let (e, f) = (T::c(1.0 / 24.0), g0 + g2);
    [
        g0 * q,
        T::ZERO - (f + g1) * s,
        (g1 - f) * s,
        g0 * e + g1 * t + g2 * s,
        g0 * e - g1 * t + g2 * s,
        g2,
    ]
}

/// `B^T d` for one column of 6 input samples.
#[inline(always)]
fn bt6<T: Elem>(a: [T; 6]) -> [T; 6] {
    let (two, four, five) = (T::c(2.0), T::c(4.0), T::c(5.0));
    let s42 = a[4] - a[2];
    let d31 = (a[3] - a[1]) * two;
    [
        a[0] * four - a[2] * five + a[4],
        (a[3] + a[4]) - (a[1] + a[2]) * four,
        (a[4] - a[3]) + (a[1] - a[2]) * four,
        s42 + d31,
        s42 - d31,
        a[1] * four - a[3] * five + a[5],
    ]
}

/// `A^T m` for one column of 6 transformed products (6 -> 4).
#[inline(always)]
fn at4<T: Elem>(m: [T; 6]) -> [T; 4] {
    let (two, four, eight) = (T::c(2.0), T::c(4.0), T::c(8.0));
    let (p12, m12) = (m[1] + m[2], m[1] - m[2]);
    let (p34, m34) = (m[3] + m[4], m[3] - m[4]);
    [
        m[0] + p12 + p34,
        m12 + m34 * two,
        p12 + p34 * four,
        m12 + m34 * eight + m[5],
    ]
}

/// Filters transformed per task in [`transform_weights`].
const WEIGHT_BLOCK: usize = 128;

/// `U[xi][co][ci] = (G g G^T)[xi]` for every filter `g = w[co][ci]`.
///
/// Blocked and parallel: filter by filter, each of the 36 outputs lands one `cout * cin` slab
/// apart, and with 256 channels that stride is a power of two, so the 36 write streams fall in
/// the same cache sets and evict each other (10 ms of a 21 ms 256->256 layer). A block of
/// filters is transformed first, then written as 36 short contiguous runs.
pub(crate) fn transform_weights<T: Elem>(w: &[T], cout: usize, cin: usize) -> Vec<T> {
    let slab = cout * cin;
    let mut u = alloc_output::<T>(36 * slab);
    // Each block owns its run of every one of the 36 slabs.
    let mut blocks: Vec<Vec<&mut [T]>> = (0..slab.div_ceil(WEIGHT_BLOCK))
        .map(|_| Vec::with_capacity(36))
        .collect();
    for row in u.chunks_exact_mut(slab.max(1)) {
        for (block, run) in blocks.iter_mut().zip(row.chunks_mut(WEIGHT_BLOCK)) {
            block.push(run);
        }
    }
    blocks
        .into_par_iter()
        .enumerate()
        .for_each(|(b, mut runs)| {
            let first = b * WEIGHT_BLOCK;
            let n = runs[0].len();
            let mut local = [[T::ZERO; 36]; WEIGHT_BLOCK];
            for (p, out) in local[..n].iter_mut().enumerate() {
                let g = &w[(first + p) * 9..][..9];
                let cols: [[T; 6]; 3] = std::array::from_fn(|c| g6(g[c], g[3 + c], g[6 + c]));
                for i in 0..6 {
                    let row = g6(cols[0][i], cols[1][i], cols[2][i]);
                    out[i * 6..][..6].copy_from_slice(&row);
                }
            }
            for (k, run) in runs.iter_mut().enumerate() {
                for (d, l) in run.iter_mut().zip(&local[..n]) {
                    *d = l[k];
                }
            }
        });
    u
}

/// The Winograd transform of one fixed 3x3 weight, made by the layer's first Winograd call
/// and reused by every later one: transforming a 256x256 filter bank costs about a tenth of
/// running the layer at 74x74. It holds the transform of the last weight it was given (a layer
/// whose weight tensor is replaced transforms the new one), and only ever grows by the
/// layers that run Winograd (4x their weight's size).
#[derive(Debug, Clone, Default)]
pub struct WinogradCache(Arc<Mutex<Option<CachedTransform>>>);

#[derive(Debug)]
struct CachedTransform {
    weight: TensorId,
    u: Arc<Vec<f32>>,
}

impl WinogradCache {
    pub(super) fn transform(&self, id: TensorId, w: &[f32], g: &Geom) -> Arc<Vec<f32>> {
        // A poisoned lock only means another thread panicked while holding it: go on.
        let held = {
            let slot = self.0.lock().unwrap_or_else(|e| e.into_inner());
            match &*slot {
                Some(c) if c.weight == id && c.u.len() == 36 * g.cout * g.cin => Some(c.u.clone()),
                _ => None,
            }
        };
        if let Some(u) = held {
            return u;
        }
        // Transformed without the lock: the transform runs rayon tasks, and a worker waiting on
        // them may pick up another call of this same layer (e.g. LPIPS inside a parallel
        // evaluation), which would then wait on a lock its own thread holds. Two first calls
        // at once both transform; either result is the same.
        let u = Arc::new(transform_weights(w, g.cout, g.cin));
        let mut slot = self.0.lock().unwrap_or_else(|e| e.into_inner());
        *slot = Some(CachedTransform {
            weight: id,
            u: u.clone(),
        });
        u
    }

    /// Whether a transform is held (tests).
    pub fn is_filled(&self) -> bool {
        self.0.lock().map(|s| s.is_some()).unwrap_or(false)
    }
}

/// Length of a zero-padded input row: every 16-tile block reads `4*LANES + 2` samples.
fn padded_len(tw: usize) -> usize {
    4 * tw.div_ceil(LANES) * LANES + 2 + SLACK
}

/// Room for the AVX-512 kernel's loads past the last block.
#[cfg(target_arch = "x86_64")]
const SLACK: usize = super::wino_x86::ROW_SLACK;
#[cfg(not(target_arch = "x86_64"))]
const SLACK: usize = 0;

fn avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        super::elem::simd_level() == super::elem::SimdLevel::Avx512
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// [`input_tiles`], by the AVX-512 f32 kernel when it applies.
fn input_tiles_any<T: Elem>(
    rows: &[T],
    rowlen: usize,
    tw: usize,
    v: &mut [T],
    slab: usize,
    off: usize,
) {
    #[cfg(target_arch = "x86_64")]
    if avx512() {
        if let (Some(r), Some(v)) = (T::as_f32(rows), T::as_f32_mut(v)) {
            // SAFETY: AVX-512F detected; sizes are asserted inside.
            unsafe { super::wino_x86::input_tiles(r, rowlen, tw, v, slab, off) };
            return;
        }
    }
    input_tiles(rows, rowlen, tw, v, slab, off)
}

/// [`output_tiles`], by the AVX-512 f32 kernel when it applies.
#[allow(clippy::too_many_arguments)]
pub(super) fn output_tiles_any<T: Elem>(
    m: &[T],
    slab: usize,
    off: usize,
    tw: usize,
    bias: T,
    band: &mut [T],
    ow: usize,
    row0: usize,
    nrows: usize,
) {
    #[cfg(target_arch = "x86_64")]
    if avx512() {
        if let (Some(m), Some(b)) = (T::as_f32(m), T::as_f32_mut(band)) {
            // SAFETY: AVX-512F detected; sizes are asserted inside.
            unsafe {
                super::wino_x86::output_tiles(m, slab, off, tw, bias.to_f32(), b, ow, row0, nrows)
            };
            return;
        }
    }
    output_tiles(m, slab, off, tw, bias, band, ow, row0, nrows)
}

/// Zero-padded copy of an input row (`None`: all padding): `dst[j] = x[iy][j - pad]`.
fn pad_row<T: Elem>(row: Option<&[T]>, pad: usize, dst: &mut [T]) {
    let Some(src) = row else {
        dst.fill(T::ZERO);
        return;
    };
    let lo = pad.min(dst.len());
    let hi = (pad + src.len()).min(dst.len());
    dst[..lo].fill(T::ZERO);
    dst[lo..hi].copy_from_slice(&src[..hi - lo]);
    dst[hi..].fill(T::ZERO);
}

multiversion! {
    /// Transforms the tiles of one tile row of one channel: `rows` holds the 6 zero-padded
    /// input rows (each `rowlen`), and `V[xi*slab + off + tx]` receives the 36 coefficients.
    fn input_tiles<T: Elem>(rows: &[T], rowlen: usize, tw: usize, v: &mut [T], slab: usize, off: usize) {
        for tx0 in (0..tw).step_by(LANES) {
            let cnt = LANES.min(tw - tx0);
            // a[r][c][l]: row r, column c of tile tx0 + l.
            let mut a = [[[T::ZERO; LANES]; 6]; 6];
            for (r, ar) in a.iter_mut().enumerate() {
                let src = &rows[r * rowlen + 4 * tx0..][..4 * LANES + 2];
                for l in 0..LANES {
                    for c in 0..6 {
                        ar[c][l] = src[4 * l + c];
                    }
                }
            }
            let mut b = [[[T::ZERO; LANES]; 6]; 6]; // b[i][c][l] = (B^T d)[i][c]
            for c in 0..6 {
                for l in 0..LANES {
                    let o = bt6([a[0][c][l], a[1][c][l], a[2][c][l], a[3][c][l], a[4][c][l], a[5][c][l]]);
                    for i in 0..6 {
                        b[i][c][l] = o[i];
                    }
                }
            }
            for (i, bi) in b.iter().enumerate() {
                let mut o6 = [[T::ZERO; LANES]; 6];
                for l in 0..LANES {
                    let o = bt6([bi[0][l], bi[1][l], bi[2][l], bi[3][l], bi[4][l], bi[5][l]]);
                    for j in 0..6 {
                        o6[j][l] = o[j];
                    }
                }
                for (j, oj) in o6.iter().enumerate() {
                    let at = (i * 6 + j) * slab + off + tx0;
                    if cnt == LANES {
                        v[at..at + LANES].copy_from_slice(oj);
                    } else {
                        for (d, s) in v[at..at + cnt].iter_mut().zip(oj) {
                            *d = *s;
                        }
                    }
                }
            }
        }
    }
}

multiversion! {
    /// Inverse-transforms one tile row of one output channel from `M[xi*slab + off + tx]` into
    /// rows `row0 .. row0 + nrows` of `band` (rows of width `ow`), adding `bias`.
    fn output_tiles<T: Elem>(
        m: &[T],
        slab: usize,
        off: usize,
        tw: usize,
        bias: T,
        band: &mut [T],
        ow: usize,
        row0: usize,
        nrows: usize,
    ) {
        for tx0 in (0..tw).step_by(LANES) {
            let cnt = LANES.min(tw - tx0);
            let mut a = [[T::ZERO; LANES]; 36];
            for (xi, ax) in a.iter_mut().enumerate() {
                let at = xi * slab + off + tx0;
                if cnt == LANES {
                    ax.copy_from_slice(&m[at..at + LANES]);
                } else {
                    for (d, s) in ax.iter_mut().zip(&m[at..at + cnt]) {
                        *d = *s;
                    }
                }
            }
            // s[j][r][l]: column j after the horizontal pass, for transform row r.
            let mut s = [[[T::ZERO; LANES]; 6]; 4];
            for r in 0..6 {
                for l in 0..LANES {
                    let o = at4([a[r * 6][l], a[r * 6 + 1][l], a[r * 6 + 2][l], a[r * 6 + 3][l], a[r * 6 + 4][l], a[r * 6 + 5][l]]);
                    for j in 0..4 {
                        s[j][r][l] = o[j];
                    }
                }
            }
            let mut o = [[[T::ZERO; LANES]; 4]; 4]; // o[i][j][l]
            for j in 0..4 {
                for l in 0..LANES {
                    let sj = &s[j];
                    let v = at4([sj[0][l], sj[1][l], sj[2][l], sj[3][l], sj[4][l], sj[5][l]]);
                    for i in 0..4 {
                        o[i][j][l] = v[i] + bias;
                    }
                }
            }
            let x0 = 4 * tx0;
            for (i, oi) in o.iter().enumerate().take(nrows) {
                let row = &mut band[(row0 + i) * ow..(row0 + i + 1) * ow];
                if x0 + 4 * LANES <= ow {
                    let dst = &mut row[x0..x0 + 4 * LANES];
                    for l in 0..LANES {
                        for j in 0..4 {
                            dst[4 * l + j] = oi[j][l];
                        }
                    }
                } else {
                    for (q, d) in row[x0..].iter_mut().enumerate() {
                        *d = oi[q % 4][q / 4];
                    }
                }
            }
        }
    }
}

/// How the tile rows of a call are split into tasks.
pub(super) struct Partition {
    pub th: usize,
    pub tw: usize,
    rows_per_task: usize,
    nbands: usize,
    tasks: usize,
    /// Threads each GEMM may use: 1 when there are enough tasks to go round.
    pub inner: usize,
}

impl Partition {
    pub(super) fn new(g: &Geom) -> Self {
        let (th, tw) = (g.oh.div_ceil(4), g.ow.div_ceil(4));
        let threads = rayon::current_num_threads();
        let rows_per_task = balanced_chunk(th, TILES_PER_TASK.div_ceil(tw), g.b, threads, 1);
        let nbands = th.div_ceil(rows_per_task);
        let tasks = g.b * nbands;
        let inner = if tasks >= threads { 1 } else { threads };
        Self {
            th,
            tw,
            rows_per_task,
            nbands,
            tasks,
            inner,
        }
    }

    /// Image and tile rows `[ty0, ty1)` of a task.
    pub(super) fn task(&self, task: usize) -> (usize, usize, usize) {
        let (bi, band) = (task / self.nbands, task % self.nbands);
        let ty0 = band * self.rows_per_task;
        (bi, ty0, (ty0 + self.rows_per_task).min(self.th))
    }

    /// Runs `run(scratch, task)` for every task, in parallel when there are enough.
    pub(super) fn run<S: Default + Send, F: Fn(&mut S, usize) + Sync + Send>(&self, run: F) {
        if self.inner == 1 {
            (0..self.tasks)
                .into_par_iter()
                .for_each_init(S::default, run);
        } else {
            let mut s = S::default();
            (0..self.tasks).for_each(|t| run(&mut s, t));
        }
    }
}

/// Per-thread buffers, reused across tasks.
#[derive(Default)]
struct Scratch<T> {
    rows: Vec<T>,
    v: Vec<T>,
    m: Vec<T>,
}

/// `V[xi][ci][t]` for the tiles of tile rows `[ty0, ty1)` of image `xb`.
pub(super) fn transform_input_band<T: Elem>(
    xb: &[T],
    g: &Geom,
    tw: usize,
    ty0: usize,
    ty1: usize,
    rows: &mut Vec<T>,
    v: &mut Vec<T>,
) {
    let nt = (ty1 - ty0) * tw;
    let rowlen = padded_len(tw);
    let plane_in = g.h * g.w;
    rows.resize(6 * rowlen, T::ZERO);
    v.resize(36 * g.cin * nt, T::ZERO);
    for ci in 0..g.cin {
        let plane = &xb[ci * plane_in..(ci + 1) * plane_in];
        for ty in ty0..ty1 {
            for r in 0..6 {
                let iy = (4 * ty + r).checked_sub(g.ph).filter(|&iy| iy < g.h);
                let src = iy.map(|iy| &plane[iy * g.w..(iy + 1) * g.w]);
                pad_row(src, g.pw, &mut rows[r * rowlen..(r + 1) * rowlen]);
            }
            input_tiles_any(rows, rowlen, tw, v, g.cin * nt, ci * nt + (ty - ty0) * tw);
        }
    }
}

/// `y = conv3x3(x, w) [+ bias]`, stride 1, any padding; `u` from [`transform_weights`].
pub(crate) fn forward<T: Elem>(x: &[T], u: &[T], bias: Option<&[T]>, g: &Geom, y: &mut [T]) {
    let p = Partition::new(g);
    let tw = p.tw;
    let (plane_in, plane_out) = (g.h * g.w, g.oh * g.ow);
    let yp = SendPtr(y.as_mut_ptr());
    p.run(|s: &mut Scratch<T>, task| {
        let (bi, ty0, ty1) = p.task(task);
        let nt = (ty1 - ty0) * tw;
        let xb = &x[bi * g.cin * plane_in..(bi + 1) * g.cin * plane_in];
        transform_input_band(xb, g, tw, ty0, ty1, &mut s.rows, &mut s.v);
        s.m.resize(36 * g.cout * nt, T::ZERO);
        for xi in 0..36 {
            let lhs = Mat {
                ptr: u[xi * g.cout * g.cin..].as_ptr(),
                rs: g.cin as isize,
                cs: 1,
            };
            let rhs = Mat {
                ptr: s.v[xi * g.cin * nt..].as_ptr(),
                rs: nt as isize,
                cs: 1,
            };
            let dst = s.m[xi * g.cout * nt..].as_mut_ptr();
            // SAFETY: u is [36, cout, cin], v [36, cin, nt], m [36, cout, nt].
            unsafe {
                gemm(
                    g.cout,
                    nt,
                    g.cin,
                    dst,
                    nt as isize,
                    1,
                    false,
                    lhs,
                    rhs,
                    p.inner,
                )
            };
        }
        let row_lo = 4 * ty0;
        let row_hi = (4 * ty1).min(g.oh);
        for co in 0..g.cout {
            // SAFETY: this task alone writes rows [row_lo, row_hi) of image bi's channels.
            let band = unsafe {
                let at = (bi * g.cout + co) * plane_out + row_lo * g.ow;
                std::slice::from_raw_parts_mut(yp.get().add(at), (row_hi - row_lo) * g.ow)
            };
            let bv = bias.map_or(T::ZERO, |b| b[co]);
            for ty in ty0..ty1 {
                let row0 = 4 * ty;
                let nrows = (row_hi - row0).min(4);
                let off = co * nt + (ty - ty0) * tw;
                output_tiles_any(
                    &s.m,
                    g.cout * nt,
                    off,
                    tw,
                    bv,
                    band,
                    g.ow,
                    row0 - row_lo,
                    nrows,
                );
            }
        }
    });
}

/// `A e` for 4 output-gradient samples (4 -> 6): the transpose of the output transform, which
/// turns a gradient tile into the Winograd domain (Winograd's transposition principle:
/// `dw = G^T [(A E A^T) . (B^T D B)] G` summed over tiles).
#[inline(always)]
fn a6<T: Elem>(e: [T; 4]) -> [T; 6] {
    let (two, four, eight) = (T::c(2.0), T::c(4.0), T::c(8.0));
    let (p02, p13) = (e[0] + e[2] * four, e[1] * two + e[3] * eight);
    [
        e[0],
        e[0] + e[1] + e[2] + e[3],
        e[0] - e[1] + e[2] - e[3],
        p02 + p13,
        p02 - p13,
        e[3],
    ]
}

multiversion! {
    /// Transforms the output-gradient tiles of one tile row of one channel: `rows` holds its 4
    /// zero-padded rows (each `rowlen`), and `E[xi*slab + off + tx]` receives the 36 values.
    fn grad_tiles<T: Elem>(rows: &[T], rowlen: usize, tw: usize, e: &mut [T], slab: usize, off: usize) {
        for tx0 in (0..tw).step_by(LANES) {
            let cnt = LANES.min(tw - tx0);
            let mut a = [[[T::ZERO; LANES]; 4]; 4]; // a[r][c][l]
            for (r, ar) in a.iter_mut().enumerate() {
                let src = &rows[r * rowlen + 4 * tx0..][..4 * LANES];
                for l in 0..LANES {
                    for c in 0..4 {
                        ar[c][l] = src[4 * l + c];
                    }
                }
            }
            let mut b = [[[T::ZERO; LANES]; 4]; 6]; // b[i][c][l]
            for c in 0..4 {
                for l in 0..LANES {
                    let o = a6([a[0][c][l], a[1][c][l], a[2][c][l], a[3][c][l]]);
                    for i in 0..6 {
                        b[i][c][l] = o[i];
                    }
                }
            }
            for (i, bi) in b.iter().enumerate() {
                for l in 0..cnt {
                    let o = a6([bi[0][l], bi[1][l], bi[2][l], bi[3][l]]);
                    for j in 0..6 {
                        e[(i * 6 + j) * slab + off + tx0 + l] = o[j];
                    }
                }
            }
        }
    }
}

/// [`grad_tiles`], by the AVX-512 f32 kernel when it applies.
fn grad_tiles_any<T: Elem>(
    rows: &[T],
    rowlen: usize,
    tw: usize,
    e: &mut [T],
    slab: usize,
    off: usize,
) {
    #[cfg(target_arch = "x86_64")]
    if avx512() {
        if let (Some(r), Some(e)) = (T::as_f32(rows), T::as_f32_mut(e)) {
            // SAFETY: AVX-512F detected; sizes are asserted inside.
            unsafe { super::wino_x86::grad_tiles(r, rowlen, tw, e, slab, off) };
            return;
        }
    }
    grad_tiles(rows, rowlen, tw, e, slab, off)
}

#[derive(Default)]
struct GradScratch<T> {
    rows: Vec<T>,
    v: Vec<T>,
    e: Vec<T>,
    /// Per-thread `S[xi][co][ci]`, the Winograd-domain weight gradient.
    acc: Vec<T>,
}

/// `dL/dw [cout, cin, 3, 3]` of a Winograd-eligible convolution: per tile, the products of the
/// transformed input and output-gradient tiles, summed over tiles by 36 GEMMs per task
/// (`S[xi] += E[xi] V[xi]^T`), then `dw = G^T S G`. A quarter of the multiplies of im2col.
pub(crate) fn grad_weight<T: Elem>(x: &[T], gy: &[T], g: &Geom) -> Vec<T> {
    let p = Partition::new(g);
    let tw = p.tw;
    let (plane_in, plane_out) = (g.h * g.w, g.oh * g.ow);
    let slab = g.cout * g.cin;
    let run = |s: &mut GradScratch<T>, task: usize| {
        let (bi, ty0, ty1) = p.task(task);
        let nt = (ty1 - ty0) * tw;
        let xb = &x[bi * g.cin * plane_in..(bi + 1) * g.cin * plane_in];
        transform_input_band(xb, g, tw, ty0, ty1, &mut s.rows, &mut s.v);
        let rowlen = padded_len(tw);
        s.e.resize(36 * g.cout * nt, T::ZERO);
        s.acc.resize(36 * slab, T::ZERO);
        for co in 0..g.cout {
            let plane = &gy[(bi * g.cout + co) * plane_out..(bi * g.cout + co + 1) * plane_out];
            for ty in ty0..ty1 {
                for r in 0..4 {
                    let oy = Some(4 * ty + r).filter(|&oy| oy < g.oh);
                    let src = oy.map(|oy| &plane[oy * g.ow..(oy + 1) * g.ow]);
                    pad_row(src, 0, &mut s.rows[r * rowlen..(r + 1) * rowlen]);
                }
                grad_tiles_any(
                    &s.rows,
                    rowlen,
                    tw,
                    &mut s.e,
                    g.cout * nt,
                    co * nt + (ty - ty0) * tw,
                );
            }
        }
        for xi in 0..36 {
            let lhs = Mat {
                ptr: s.e[xi * g.cout * nt..].as_ptr(),
                rs: nt as isize,
                cs: 1,
            };
            let rhs = Mat {
                ptr: s.v[xi * g.cin * nt..].as_ptr(),
                rs: 1,
                cs: nt as isize,
            };
            let dst = s.acc[xi * slab..].as_mut_ptr();
            // SAFETY: e is [36, cout, nt], v [36, cin, nt], acc [36, cout, cin].
            unsafe {
                gemm(
                    g.cout,
                    g.cin,
                    nt,
                    dst,
                    g.cin as isize,
                    1,
                    true,
                    lhs,
                    rhs,
                    p.inner,
                )
            };
        }
    };
    let s = if p.inner == 1 {
        (0..p.tasks)
            .into_par_iter()
            .fold(GradScratch::default, |mut s, t| {
                run(&mut s, t);
                s
            })
            .map(|s| s.acc)
            .reduce_with(|mut a, b| {
                if a.len() < b.len() {
                    return b;
                }
                a.iter_mut().zip(&b).for_each(|(a, b)| *a += *b);
                a
            })
            .unwrap_or_default()
    } else {
        let mut s = GradScratch::default();
        (0..p.tasks).for_each(|t| run(&mut s, t));
        s.acc
    };
    let mut gw = vec![T::ZERO; slab * 9];
    if s.len() != 36 * slab {
        return gw;
    }
    // gw = G^T S G per channel pair; G^T's rows are the coefficients below.
    let gt: [[T; 6]; 3] = [
        [0.25, -1.0 / 6.0, -1.0 / 6.0, 1.0 / 24.0, 1.0 / 24.0, 0.0].map(T::c),
        [0.0, -1.0 / 6.0, 1.0 / 6.0, 1.0 / 12.0, -1.0 / 12.0, 0.0].map(T::c),
        [0.0, -1.0 / 6.0, -1.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0, 1.0].map(T::c),
    ];
    for (pair, out) in gw.chunks_exact_mut(9).enumerate() {
        let sv: [T; 36] = std::array::from_fn(|xi| s[xi * slab + pair]);
        // t[i][kx] = sum_j S[i][j] G[j][kx]
        let t: [[T; 3]; 6] = std::array::from_fn(|i| {
            std::array::from_fn(|kx| {
                let mut a = T::ZERO;
                for j in 0..6 {
                    a += sv[i * 6 + j] * gt[kx][j];
                }
                a
            })
        });
        for ky in 0..3 {
            for kx in 0..3 {
                let mut a = T::ZERO;
                for i in 0..6 {
                    a += gt[ky][i] * t[i][kx];
                }
                out[ky * 3 + kx] = a;
            }
        }
    }
    gw
}
