//! Per-tile alpha compositing (spec section 7) and its backward.
//!
//! Work is split by bands (one row of 16x16 tiles). Both passes put the 16 pixels of a 4x4 block
//! in the 16 lanes of a vector ([`crate::lanes`]) and only visit the blocks a Gaussian can reach
//! (the bounding box of a slightly inflated ellipse): on small splats that is about a third
//! fewer Gaussian-block visits than Gaussian-row visits with 16x1 rows, and the same lanes. The
//! forward composites block by block: every Gaussian reaching the block takes its turn on all 16
//! pixels at once, then the weighted features are summed with the sums in registers. The
//! backward goes Gaussian by Gaussian, back to front. Per pixel, the
//! decisions (skip, stop) and the forward's accumulation order are exactly the release's, and
//! no result depends on the thread count or on the instruction set the kernels run with.

use crate::binning::Bins;
#[cfg(target_arch = "x86_64")]
use crate::lanes::Z16;
use crate::lanes::{simd_disabled, Lanes, Mask, ALL, P16, WIDTH};
use crate::project::{Projected, Splat2D, TILE};
use crate::real::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;

pub use crate::params::{MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, SCREEN};
/// Gaussian slots per reduction chunk in the backward.
const REDUCE_CHUNK: usize = 4096;

/// Per-pixel results of the forward that the backward and callers need.
#[derive(Debug, Clone, Default)]
pub struct PixelState<T> {
    /// Final transmittance per pixel, [H*W].
    pub final_t: Vec<T>,
    /// One past the tile-list position of the last Gaussian added to each pixel, [H*W].
    pub n_contrib: Vec<u32>,
}

pub struct Frame<'a, T> {
    pub proj: &'a Projected<T>,
    pub bins: &'a Bins,
    pub features: &'a [T],
    pub channels: usize,
    pub background: &'a [T],
    pub width: usize,
    pub height: usize,
}

/// Tile-local inclusive range of pixel rows (`centre = my`, `half = ey`) or columns (`mx`,
/// `ex`), out of `n`, where the Gaussian can reach alpha >= 1/255 (a bound: the region behind
/// it is inflated far beyond what rounding here can move); `None` for a negative `half`.
#[inline(always)]
fn reach<T: Real>(centre: T, half: T, o: usize, n: usize) -> Option<(usize, usize)> {
    if !(half >= T::ZERO) {
        return None;
    }
    let m = centre - T::lit(o as f64);
    let lo = (m - half).ceil().fmax(T::ZERO);
    let hi = (m + half).floor().fmin(T::lit(n as f64 - 1.0));
    (lo <= hi).then(|| (lo.as_f64() as usize, hi.as_f64() as usize))
}

/// Side of the square pixel blocks whose 16 pixels share a vector (row-major in the lanes).
pub const BLOCK: usize = 4;
/// Blocks per tile side.
const BLOCKS: usize = TILE / BLOCK;
/// Blocks per tile.
const NBLK: usize = BLOCKS * BLOCKS;
const _: () = assert!(BLOCK * BLOCK == WIDTH && BLOCKS * BLOCK == TILE);

/// Inclusive ranges of block rows and block columns of the tile at `(x0, y0)` (`tw x th`
/// pixels) where the Gaussian can reach alpha >= 1/255; `None` where it reaches no pixel.
#[inline(always)]
pub(crate) fn block_range<T: Real>(
    s: &Splat2D<T>,
    x0: usize,
    y0: usize,
    tw: usize,
    th: usize,
) -> Option<[(usize, usize); 2]> {
    let (r0, r1) = reach(s.my, s.ey, y0, th)?;
    let (c0, c1) = reach(s.mx, s.ex, x0, tw)?;
    Some([(r0 / BLOCK, r1 / BLOCK), (c0 / BLOCK, c1 / BLOCK)])
}

/// Where block `b` of a `tw x th` tile lies: its tile-local origin, its pixel rows and columns
/// inside the image, the mask of those lanes and its pixel coordinates per lane.
struct BlockAt<T> {
    ox: usize,
    oy: usize,
    rows: usize,
    cols: usize,
    valid: Mask,
    px: [T; WIDTH],
    py: [T; WIDTH],
}

impl<T: Real> BlockAt<T> {
    /// `None` when the block lies wholly outside the image.
    #[inline(always)]
    fn new(b: usize, x0: usize, y0: usize, tw: usize, th: usize) -> Option<Self> {
        let (ox, oy) = ((b % BLOCKS) * BLOCK, (b / BLOCKS) * BLOCK);
        if ox >= tw || oy >= th {
            return None;
        }
        let (cols, rows) = (BLOCK.min(tw - ox), BLOCK.min(th - oy));
        let mut valid: Mask = 0;
        let mut px = [T::ZERO; WIDTH];
        let mut py = [T::ZERO; WIDTH];
        for l in 0..WIDTH {
            let (r, c) = (l / BLOCK, l % BLOCK);
            valid |= ((r < rows && c < cols) as Mask) << l;
            px[l] = T::lit((x0 + ox + c) as f64);
            py[l] = T::lit((y0 + oy + r) as f64);
        }
        Some(Self {
            ox,
            oy,
            rows,
            cols,
            valid,
            px,
            py,
        })
    }

    /// Writes the block's lanes into a row-major plane of width `w` whose row 0 is tile row 0
    /// (of output not yet initialised: see [`forward`]). (Whole block rows are copied with a
    /// constant length: a variable one is a memmove call.)
    #[inline(always)]
    fn put<V: Copy>(&self, lanes: &[V; WIDTH], plane: &mut [MaybeUninit<V>], w: usize, x0: usize) {
        let lanes = lanes.map(MaybeUninit::new);
        for r in 0..self.rows {
            let o = (self.oy + r) * w + x0 + self.ox;
            if self.cols == BLOCK {
                plane[o..o + BLOCK].copy_from_slice(&lanes[r * BLOCK..(r + 1) * BLOCK]);
            } else {
                for c in 0..self.cols {
                    plane[o + c] = lanes[r * BLOCK + c];
                }
            }
        }
    }

    /// Reads the block's lanes from such a plane (zeros outside the image).
    #[inline(always)]
    fn get<V: Copy>(&self, plane: &[V], w: usize, x0: usize, zero: V) -> [V; WIDTH] {
        let mut lanes = [zero; WIDTH];
        for r in 0..self.rows {
            let o = (self.oy + r) * w + x0 + self.ox;
            if self.cols == BLOCK {
                lanes[r * BLOCK..(r + 1) * BLOCK].copy_from_slice(&plane[o..o + BLOCK]);
            } else {
                for c in 0..self.cols {
                    lanes[r * BLOCK + c] = plane[o + c];
                }
            }
        }
        lanes
    }
}

/// `n` copies of `zero`, written rather than calloc'ed. Reading a calloc'ed page maps the
/// shared zero page, and the first write after that is a copy-on-write fault that flushes the
/// TLB of every core (an IPI each time): in the backward, whose buffers are read-modify-written,
/// that was 15% of the time.
pub(crate) fn zeros<T: Copy>(n: usize, zero: T) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    v.resize(n, zero);
    v
}

/// Gaussians whose alphas on a block are computed side by side in the forward.
const GROUP: usize = 8;

/// How many tile-list entries ahead a Gaussian's data is requested.
const PREFETCH_AHEAD: usize = 8;

/// Asks the cache for `data[start..start + len]` ahead of use. Tile lists are in depth order,
/// so consecutive Gaussians sit far apart in memory and each would otherwise stall on a miss
/// (the main cost of small splats). A hint only: it never faults and changes no result.
#[inline(always)]
fn prefetch<T>(data: &[T], start: usize, len: usize) {
    #[cfg(target_arch = "x86_64")]
    if start + len <= data.len() && len > 0 {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let first = data[start..].as_ptr() as *const i8;
        let bytes = len * std::mem::size_of::<T>();
        let mut off = 0;
        while off < bytes {
            // SAFETY: prefetch is a hint that never dereferences; the address is in bounds.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(first.wrapping_add(off)) };
            off += 64;
        }
        // SAFETY: as above (the last byte, in case the range straddles one more line).
        unsafe { _mm_prefetch::<_MM_HINT_T0>(first.wrapping_add(bytes - 1)) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, start, len);
}

/// Splits `[C, H, W]` planes into per-band row slices so bands can be written in parallel.
fn band_slices<T>(
    data: &mut [T],
    planes: usize,
    height: usize,
    width: usize,
) -> Vec<Vec<&mut [T]>> {
    let bands = height.div_ceil(TILE);
    let mut out: Vec<Vec<&mut [T]>> = (0..bands).map(|_| Vec::with_capacity(planes)).collect();
    if height * width == 0 {
        return out;
    }
    for plane in data.chunks_mut(height * width) {
        for (b, rows) in plane.chunks_mut(TILE * width).enumerate() {
            out[b].push(rows);
        }
    }
    out
}

/// Which compilation of the band kernels runs.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Path {
    /// f32 in AVX-512 registers ([`Z16`]).
    Avx512,
    /// Plain arrays, compiled with AVX2 enabled.
    Avx2,
    /// Plain arrays, baseline instructions.
    Portable,
}

fn path<T: Real>() -> Path {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        // Bit counts and scans in single instructions (the block lists count bits).
        let vec2 = has!("avx2") && has!("fma") && has!("popcnt") && has!("bmi1") && has!("bmi2");
        let f32 = std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>();
        if f32 && vec2 && has!("avx512f") && !simd_disabled() {
            return Path::Avx512;
        }
        if vec2 {
            return Path::Avx2;
        }
    }
    Path::Portable
}

/// The frame as `Frame<f32>` when `T` is `f32`.
fn as_f32<'a, 'b, T: Real>(f: &'b Frame<'a, T>) -> Option<&'b Frame<'a, f32>> {
    (std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>())
        // SAFETY: T and f32 are the same type, so the two are the same struct.
        .then(|| unsafe { &*(f as *const Frame<'a, T>).cast::<Frame<'a, f32>>() })
}

/// Features and background with the channel count rounded up to whole 16-lane blocks (zeros
/// after the real channels); borrowed when it already is.
struct Padded<'a, T: Clone> {
    features: std::borrow::Cow<'a, [T]>,
    background: std::borrow::Cow<'a, [T]>,
    cpad: usize,
}

impl<'a, T: Real> Padded<'a, T> {
    fn new(f: &Frame<'a, T>) -> Self {
        let c = f.channels;
        let cpad = c.div_ceil(WIDTH) * WIDTH;
        if cpad == c {
            return Self {
                features: f.features.into(),
                background: f.background.into(),
                cpad,
            };
        }
        let n = f.features.len() / c.max(1);
        let mut features = zeros(n * cpad, T::ZERO);
        for (dst, src) in features.chunks_mut(cpad).zip(f.features.chunks(c)) {
            dst[..c].copy_from_slice(src);
        }
        let mut background = vec![T::ZERO; cpad];
        background[..c].copy_from_slice(f.background);
        Self {
            features: features.into(),
            background: background.into(),
            cpad,
        }
    }
}

/// Alphas and exp(power) of `N` Gaussians on one pixel block (`px`, `py`: the pixel
/// coordinates per lane) and the masks of lanes the release would not skip (`power <= 0` and
/// `alpha >= 1/255`), computed step by step side by side so the long exp chains overlap.
#[inline(always)]
fn eval_n<T: Real, L: Lanes<T>, const N: usize>(
    ss: [&Splat2D<T>; N],
    px: L,
    py: L,
) -> ([L; N], [L; N], [Mask; N]) {
    let zero = L::zero();
    let mut power = [zero; N];
    for i in 0..N {
        // power = -0.5 (A dx^2 + C dy^2) - B dx dy = dx (-A/2 dx - B dy) + (-C/2 dy) dy, with
        // d = mean - pixel (the halved, negated conic is stored).
        let s = ss[i];
        let dy = L::splat(s.my).sub(py);
        let dx = L::splat(s.mx).sub(px);
        let inner = L::splat(s.qa).mul_add(dx, L::splat(s.qb).mul(dy));
        let cdy = L::splat(s.qc).mul(dy).mul(dy);
        power[i] = dx.mul_add(inner, cdy);
    }
    let g = L::exp_n(power);
    let mut alpha = [zero; N];
    let mut keep = [0; N];
    for i in 0..N {
        alpha[i] = L::splat(ss[i].opacity)
            .mul(g[i])
            .min(L::splat(T::lit(MAX_ALPHA)));
        keep[i] = power[i].le(zero) & alpha[i].ge(L::splat(T::lit(MIN_ALPHA)));
    }
    (alpha, g, keep)
}

/// The 16-bit mask of the tile's pixel blocks a Gaussian can reach (bit `4 * row + column`).
#[inline(always)]
fn block_mask(range: Option<[(usize, usize); 2]>) -> u32 {
    let Some([(r0, r1), (c0, c1)]) = range else {
        return 0;
    };
    let cols = (2u32 << c1) - (1u32 << c0);
    // 16^r0 + ... + 16^r1: one bit per block row, at the row's first block.
    let rows = ((1u32 << (BLOCKS * (r1 + 1))) - (1u32 << (BLOCKS * r0))) / 15;
    cols * rows
}

/// [`block_mask`] of every Gaussian of a tile list. (A plain loop: a closure would not inherit
/// the kernel's target features, and floor/ceil would become library calls.)
#[inline(always)]
fn block_masks<T: Real>(
    g: &[Splat2D<T>],
    list: &[u32],
    (x0, y0, tw, th): (usize, usize, usize, usize),
    masks: &mut Vec<u32>,
) {
    masks.clear();
    for (k, &gi) in list.iter().enumerate() {
        if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
            prefetch(g, ahead as usize, 1);
        }
        masks.push(block_mask(block_range(&g[gi as usize], x0, y0, tw, th)));
    }
}

/// How a kernel's lanes fill a tile's block masks: [`block_masks`], or for the AVX-512 lanes
/// [`block_masks_avx512`] (the same masks).
trait TileMasks<T: Real>: Lanes<T> {
    #[inline(always)]
    fn tile_masks(
        g: &[Splat2D<T>],
        list: &[u32],
        tile: (usize, usize, usize, usize),
        masks: &mut Vec<u32>,
    ) {
        block_masks(g, list, tile, masks)
    }
}

impl<T: Real> TileMasks<T> for P16<T> {}

#[cfg(target_arch = "x86_64")]
impl TileMasks<f32> for Z16 {
    #[inline(always)]
    fn tile_masks(
        g: &[Splat2D<f32>],
        list: &[u32],
        tile: (usize, usize, usize, usize),
        masks: &mut Vec<u32>,
    ) {
        // SAFETY: Z16 is only used inside kernels that run after AVX-512F was detected (see
        // the lanes module).
        unsafe { block_masks_avx512(g, list, tile, masks) }
    }
}

/// [`block_masks`] sixteen list entries at a time in AVX-512 registers, gathering the
/// Gaussians' centres and reaches: the same masks, without a scalar chain of rounding, clamps
/// and shifts per entry.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn block_masks_avx512(
    g: &[Splat2D<f32>],
    list: &[u32],
    (x0, y0, tw, th): (usize, usize, usize, usize),
    masks: &mut Vec<u32>,
) {
    use std::arch::x86_64::*;
    // The gathers below read g[list[k]]: every entry must be in bounds, and 8 * entry must
    // fit an i32 offset.
    assert!(g.len() <= i32::MAX as usize / 8);
    assert!(list.iter().all(|&i| (i as usize) < g.len()));
    const _: () = assert!(std::mem::size_of::<Splat2D<f32>>() == 32);
    masks.clear();
    masks.reserve(list.len() + WIDTH);
    let base = g.as_ptr() as *const f32;
    // Field offsets (in floats) of mx, my, ey, ex in the #[repr(C)] Splat2D.
    const MX: usize = 0;
    const MY: usize = 1;
    const EY: usize = 6;
    const EX: usize = 7;
    // Inclusive block range along one axis, as `reach` computes its pixel range, and whether
    // it is non-empty.
    #[inline(always)]
    unsafe fn axis(centre: __m512, half: __m512, o: usize, n: usize) -> (__m512i, __m512i, u16) {
        let zero = _mm512_setzero_ps();
        let m = _mm512_sub_ps(centre, _mm512_set1_ps(o as f32));
        let lo = _mm512_roundscale_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(
            _mm512_sub_ps(m, half),
        );
        let lo = _mm512_max_ps(lo, zero);
        let hi = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(
            _mm512_add_ps(m, half),
        );
        let hi = _mm512_min_ps(hi, _mm512_set1_ps(n as f32 - 1.0));
        let ok =
            _mm512_cmp_ps_mask::<_CMP_GE_OQ>(half, zero) & _mm512_cmp_ps_mask::<_CMP_LE_OQ>(lo, hi);
        // Block indices (pixel / 4); lanes not in `ok` are masked off by the caller.
        let lo = _mm512_srli_epi32::<2>(_mm512_cvttps_epi32(lo));
        let hi = _mm512_srli_epi32::<2>(_mm512_cvttps_epi32(hi));
        (lo, hi, ok)
    }
    let one = _mm512_set1_epi32(1);
    let mut k = 0;
    while k < list.len() {
        let lanes = crate::lanes::first(list.len() - k);
        let idx = _mm512_maskz_loadu_epi32(lanes, list.as_ptr().add(k) as *const i32);
        let off = _mm512_slli_epi32::<3>(idx);
        #[inline(always)]
        unsafe fn field(lanes: u16, off: __m512i, at: *const f32) -> __m512 {
            _mm512_mask_i32gather_ps::<4>(_mm512_setzero_ps(), lanes, off, at)
        }
        let (mx, my) = (
            field(lanes, off, base.add(MX)),
            field(lanes, off, base.add(MY)),
        );
        let (ey, ex) = (
            field(lanes, off, base.add(EY)),
            field(lanes, off, base.add(EX)),
        );
        let (r0, r1, okr) = axis(my, ey, y0, th);
        let (c0, c1, okc) = axis(mx, ex, x0, tw);
        // Columns c0..=c1 of a block row, and the rows' first bits (4 r for r0..=r1).
        let cols = _mm512_sub_epi32(
            _mm512_sllv_epi32(_mm512_set1_epi32(2), c1),
            _mm512_sllv_epi32(one, c0),
        );
        let below_r1 = _mm512_sub_epi32(
            _mm512_sllv_epi32(_mm512_set1_epi32(2), _mm512_slli_epi32::<2>(r1)),
            one,
        );
        let below_r0 = _mm512_sub_epi32(_mm512_sllv_epi32(one, _mm512_slli_epi32::<2>(r0)), one);
        let rows = _mm512_andnot_si512(
            below_r0,
            _mm512_and_si512(below_r1, _mm512_set1_epi32(0x1111)),
        );
        let mask = _mm512_maskz_mov_epi32(okr & okc, _mm512_mullo_epi32(cols, rows));
        // Sixteen lanes are stored (the capacity allows it); only the first len count.
        _mm512_storeu_si512(masks.as_mut_ptr().add(k) as *mut _, mask);
        k += WIDTH;
    }
    masks.set_len(list.len());
}

pub(crate) struct BandOut<'a, T> {
    image: Vec<&'a mut [MaybeUninit<T>]>,
    final_t: &'a mut [MaybeUninit<T>],
    n_contrib: &'a mut [MaybeUninit<u32>],
}

/// Forward scratch reused across the tiles of a band.
struct FwdScratch<L> {
    /// Per Gaussian of the tile list: the blocks it can reach ([`block_mask`]).
    masks: Vec<u32>,
    /// Tile-list positions of the Gaussians that can reach the current block.
    blk: Vec<u32>,
    /// Per Gaussian taken on the current block: its 16 weights (0 where not taken) ...
    weights: Vec<L>,
    /// ... and the offset of its (padded) features.
    feat_at: Vec<usize>,
}

impl<L> FwdScratch<L> {
    fn new() -> Self {
        Self {
            masks: Vec::new(),
            blk: Vec::new(),
            weights: Vec::new(),
            feat_at: Vec::new(),
        }
    }
}

/// Composites one image; returns `[C, H, W]` and the per-pixel state.
pub fn forward<T: Real>(f: &Frame<T>) -> (Vec<T>, PixelState<T>) {
    let (w, h, c) = (f.width, f.height, f.channels);
    // The outputs are written once, block by block, and never read here, so they start
    // uninitialised: zeroing first would be one more pass over 32 MB (and the blocks' writes
    // then fetch the zeroed lines back).
    let mut image: Vec<T> = Vec::with_capacity(c * h * w);
    let mut final_t: Vec<T> = Vec::with_capacity(h * w);
    let mut n_contrib: Vec<u32> = Vec::with_capacity(h * w);
    let outs: Vec<BandOut<T>> = band_slices(&mut image.spare_capacity_mut()[..c * h * w], c, h, w)
        .into_iter()
        .zip(final_t.spare_capacity_mut()[..h * w].chunks_mut(TILE * w))
        .zip(n_contrib.spare_capacity_mut()[..h * w].chunks_mut(TILE * w))
        .map(|((image, final_t), n_contrib)| BandOut {
            image,
            final_t,
            n_contrib,
        })
        .collect();
    let bands = outs.len();
    let pad = Padded::new(f);
    let cost = |ty: usize| f.bins.bands[ty].ids.len();
    match (path::<T>(), as_f32(f)) {
        #[cfg(target_arch = "x86_64")]
        (Path::Avx512, Some(f32f)) => {
            // SAFETY: T is f32 (as_f32), so Padded<T> is Padded<f32>.
            let pad32 = unsafe { &*(&pad as *const Padded<T>).cast::<Padded<f32>>() };
            heaviest_first(outs, cost, FwdScratch::new, |sc, ty, out| {
                // SAFETY: T is f32 (as_f32), so BandOut<T> is BandOut<f32>; the CPU has
                // AVX-512F, AVX2, FMA, POPCNT, BMI1 and BMI2 (path).
                unsafe {
                    let out = std::mem::transmute::<BandOut<T>, BandOut<f32>>(out);
                    forward_band_avx512(f32f, pad32, ty, out, sc)
                }
            })
        }
        #[cfg(target_arch = "x86_64")]
        (Path::Avx2, _) => heaviest_first(outs, cost, FwdScratch::new, |sc, ty, out| {
            // SAFETY: the CPU has AVX2, FMA, POPCNT, BMI1 and BMI2 (path).
            unsafe { forward_band_avx2(f, &pad, ty, out, sc) }
        }),
        _ => heaviest_first(outs, cost, FwdScratch::new, |sc, ty, out| {
            forward_band::<T, P16<T>>(f, &pad, ty, out, sc)
        }),
    }
    assert_eq!(bands, h.div_ceil(TILE));
    // SAFETY: every band ran (`heaviest_first` hands out every item), and each band wrote
    // every element of its rows: all its tiles, all their blocks inside the image, all rows
    // and columns of each block inside the image, and every channel (`forward_band`).
    unsafe {
        image.set_len(c * h * w);
        final_t.set_len(h * w);
        n_contrib.set_len(h * w);
    }
    (image, PixelState { final_t, n_contrib })
}

/// Runs `work(scratch, i, items[i])` for every item on every thread of the current pool,
/// each thread taking the costliest item left next (a thread's `scratch` comes from `init`).
/// Bands differ in cost by an order of magnitude (the head sits in the middle of the image),
/// and a costly band started last leaves the other threads idle until it ends.
fn heaviest_first<I: Send, S>(
    items: Vec<I>,
    cost: impl Fn(usize) -> usize,
    init: impl Fn() -> S + Sync,
    work: impl Fn(&mut S, usize, I) + Sync,
) {
    let mut order: Vec<usize> = (0..items.len()).collect();
    order.sort_by_key(|&i| std::cmp::Reverse(cost(i)));
    let slots: Vec<std::sync::Mutex<Option<I>>> = items
        .into_iter()
        .map(|i| std::sync::Mutex::new(Some(i)))
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    rayon::broadcast(|_| {
        let mut scratch = None;
        loop {
            let k = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let Some(&i) = order.get(k) else {
                break;
            };
            // Each index is handed out once, so the slot is full; a poisoned lock (a panic
            // elsewhere, which reaches the caller anyway) still holds the item.
            let item = match slots[i].lock() {
                Ok(mut g) => g.take(),
                Err(p) => p.into_inner().take(),
            };
            if let Some(item) = item {
                work(scratch.get_or_insert_with(&init), i, item);
            }
        }
    });
    debug_assert!(slots
        .iter()
        .all(|s| s.lock().map(|g| g.is_none()).unwrap_or(true)));
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma,popcnt,bmi1,bmi2")]
unsafe fn forward_band_avx512(
    f: &Frame<f32>,
    pad: &Padded<f32>,
    ty: usize,
    out: BandOut<f32>,
    sc: &mut FwdScratch<Z16>,
) {
    forward_band::<f32, Z16>(f, pad, ty, out, sc)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,popcnt,bmi1,bmi2")]
unsafe fn forward_band_avx2<T: Real>(
    f: &Frame<T>,
    pad: &Padded<T>,
    ty: usize,
    out: BandOut<T>,
    sc: &mut FwdScratch<P16<T>>,
) {
    forward_band::<T, P16<T>>(f, pad, ty, out, sc)
}

/// Composites one band (a row of tiles), 4x4 block by block: first every Gaussian that can
/// reach the block takes its turn on all 16 pixels at once (alphas, the transmittance step and
/// the weights alpha*T, 0 where a pixel skips it or has stopped), then the weighted features
/// are summed with a 16-channel x 16-pixel block of sums held in registers.
///
/// Each pixel receives exactly the release's operations in the release's order: a zero weight
/// adds an exact zero (features are finite, and a sum that starts at +0 never becomes -0).
#[inline(always)]
fn forward_band<T: Real, L: TileMasks<T>>(
    f: &Frame<T>,
    pad: &Padded<T>,
    ty: usize,
    out: BandOut<T>,
    sc: &mut FwdScratch<L>,
) {
    let BandOut {
        mut image,
        final_t,
        n_contrib,
    } = out;
    let band = &f.bins.bands[ty];
    let (w, h, c) = (f.width, f.height, f.channels);
    let (feats, bg, cpad) = (&*pad.features, &*pad.background, pad.cpad);
    let y0 = ty * TILE;
    let th = TILE.min(h - y0);
    let one = L::splat(T::ONE);
    let zero = L::zero();
    let min_t = L::splat(T::lit(MIN_TRANSMITTANCE));
    for tx in 0..w.div_ceil(TILE) {
        let x0 = tx * TILE;
        let tw = TILE.min(w - x0);
        let list = band.tile(tx);
        L::tile_masks(&f.proj.g, list, (x0, y0, tw, th), &mut sc.masks);
        if sc.blk.len() < list.len() + WIDTH {
            sc.blk.resize(list.len() + WIDTH, 0);
        }
        for bi in 0..NBLK {
            let Some(at) = BlockAt::<T>::new(bi, x0, y0, tw, th) else {
                continue;
            };
            let (px, py) = (L::from_array(at.px), L::from_array(at.py));
            let nb = L::positions_with(&sc.masks, 1 << bi, &mut sc.blk);
            let blk = &sc.blk[..nb];
            if sc.weights.len() < blk.len() {
                sc.weights.resize(blk.len(), L::zero());
                sc.feat_at.resize(blk.len(), 0);
            }
            // A pixel that has stopped holds t = 0 from then on (its test below is 0, so it
            // never takes another Gaussian) and its transmittance is kept in `t_stop`. No
            // per-pixel "done" mask sits in the loop-carried dependency through `t`.
            // Lanes outside the image start stopped.
            let mut t = L::select(at.valid, one, zero);
            let mut t_stop = zero;
            let mut stopped: Mask = !at.valid;
            let mut last = L::idx_zero();
            let mut ne = 0;
            for chunk in blk.chunks(GROUP) {
                if stopped == ALL {
                    break;
                }
                // The chunk's alphas first, side by side: they do not depend on the
                // transmittance, and their long exp chains overlap only when interleaved.
                let n = chunk.len();
                let mut gs = [0usize; GROUP];
                for i in 0..GROUP {
                    gs[i] = list[chunk[i.min(n - 1)] as usize] as usize;
                    prefetch(feats, gs[i] * cpad, cpad);
                }
                let (alphas, _, keeps) = eval_n::<T, L, GROUP>(gs.map(|g| &f.proj.g[g]), px, py);
                for i in 0..n {
                    let (k, g, keep) = (chunk[i], gs[i], keeps[i]);
                    // Alpha 0 where the pixel skips the Gaussian: its test is then t itself,
                    // so only the transmittance test decides whether t changes and the chain
                    // through t never leaves the vector unit.
                    let alpha = L::select(keep, alphas[i], zero);
                    let test = t.mul(one.sub(alpha));
                    let go = test.ge(min_t);
                    let added = keep & go;
                    let stop = keep & !go & t.gt(zero);
                    // Written whether or not the Gaussian was taken (no branch to mispredict);
                    // `ne` only moves past it if it was.
                    sc.weights[ne] = L::select(go, alpha.mul(t), zero);
                    sc.feat_at[ne] = g * cpad;
                    ne += (added != 0) as usize;
                    t_stop = L::select(stop, t, t_stop);
                    stopped |= stop;
                    t = L::select(go, test, zero);
                    last = L::idx_set(added, k + 1, last);
                }
            }
            let t = L::select(stopped, t_stop, t);
            at.put(&t.to_array(), final_t, w, x0);
            let mut nc = [0u32; WIDTH];
            L::idx_store_masked(last, &mut nc, ALL);
            at.put(&nc, n_contrib, w, x0);
            for cb in (0..c).step_by(WIDTH) {
                let mut acc = [L::zero(); WIDTH];
                for (wv, &fo) in sc.weights[..ne].iter().zip(&sc.feat_at[..ne]) {
                    let fp = &feats[fo + cb..fo + cb + WIDTH];
                    for j in 0..WIDTH {
                        acc[j] = acc[j].add(wv.mul(L::splat(fp[j])));
                    }
                }
                for j in 0..WIDTH.min(c - cb) {
                    let ch = cb + j;
                    let v = acc[j].add(t.mul(L::splat(bg[ch])));
                    at.put(&v.to_array(), image[ch], w, x0);
                }
            }
        }
    }
}

/// Gradients of one image w.r.t. the per-Gaussian screen-space quantities.
pub struct Grads2D<T> {
    /// [N, C]
    pub features: Vec<T>,
    /// [N, SCREEN]: mean x, mean y, conic A, B, C, opacity.
    pub screen: Vec<T>,
    /// [C]
    pub background: Vec<T>,
}

struct BandGrads<T> {
    ids: Vec<u32>,
    /// Per slot: [features (C) | screen (SCREEN)].
    vals: Vec<T>,
    background: Vec<T>,
}

/// A Gaussian's feature-gradient sums, one vector per 16-channel block: a fixed-size array
/// (kept in registers) for the usual channel counts, a vector otherwise.
trait Blocks<L>: Sized {
    fn zeroed(nb: usize, zero: L) -> Self;
    fn blocks(&mut self) -> &mut [L];
}

impl<L: Copy, const N: usize> Blocks<L> for [L; N] {
    #[inline(always)]
    fn zeroed(_: usize, zero: L) -> Self {
        [zero; N]
    }
    #[inline(always)]
    fn blocks(&mut self) -> &mut [L] {
        self
    }
}

impl<L: Copy> Blocks<L> for Vec<L> {
    #[inline(always)]
    fn zeroed(nb: usize, zero: L) -> Self {
        vec![zero; nb]
    }
    #[inline(always)]
    fn blocks(&mut self) -> &mut [L] {
        self
    }
}

/// Backward scratch reused across the tiles of a band.
struct BwdScratch<L> {
    /// dL/dpixel per pixel block and channel, pixels in lanes: `[block][cpad]`.
    dpc: Vec<L>,
    /// The same, channels in lanes: `[block][pixel][channel block]`.
    dpp: Vec<L>,
    /// Gaussian slots of this band.
    slot: Vec<u32>,
}

/// Backward of [`forward`] given `grad` = dL/dimage `[C, H, W]`.
///
/// Each band accumulates into its own compact buffer (one slot per Gaussian it touches), and
/// the buffers are summed per Gaussian in band order, so gradients are bit-identical for any
/// thread count.
pub fn backward<T: Real>(f: &Frame<T>, state: &PixelState<T>, grad: &[T], n: usize) -> Grads2D<T> {
    let c = f.channels;
    let stride = c + SCREEN;
    let pad = Padded::new(f);
    let nb = pad.cpad / WIDTH;
    let bands = 0..f.bins.bands.len();
    let band_grads: Vec<BandGrads<T>> = match (path::<T>(), as_f32(f)) {
        #[cfg(target_arch = "x86_64")]
        (Path::Avx512, Some(f32f)) => {
            // SAFETY: T is f32 (as_f32), so Padded<T> is Padded<f32>.
            let pad32 = unsafe { &*(&pad as *const Padded<T>).cast::<Padded<f32>>() };
            // SAFETY: T is f32 (as_f32), so the slices and results have the same types.
            let (st32, grad32) = unsafe {
                (
                    &*(state as *const PixelState<T>).cast::<PixelState<f32>>(),
                    std::slice::from_raw_parts(grad.as_ptr().cast::<f32>(), grad.len()),
                )
            };
            let run = |sc: &mut BwdScratch<Z16>, ty: usize| -> BandGrads<f32> {
                // SAFETY: the CPU has AVX-512F, AVX2, FMA, POPCNT, BMI1 and BMI2 (path).
                unsafe {
                    match nb {
                        1 => backward_band_avx512::<[Z16; 1]>(f32f, pad32, st32, grad32, ty, sc),
                        2 => backward_band_avx512::<[Z16; 2]>(f32f, pad32, st32, grad32, ty, sc),
                        3 => backward_band_avx512::<[Z16; 3]>(f32f, pad32, st32, grad32, ty, sc),
                        4 => backward_band_avx512::<[Z16; 4]>(f32f, pad32, st32, grad32, ty, sc),
                        _ => backward_band_avx512::<Vec<Z16>>(f32f, pad32, st32, grad32, ty, sc),
                    }
                }
            };
            let out: Vec<BandGrads<f32>> = bands
                .into_par_iter()
                .map_init(|| BwdScratch::new(n), run)
                .collect();
            // SAFETY: T is f32.
            unsafe { std::mem::transmute::<Vec<BandGrads<f32>>, Vec<BandGrads<T>>>(out) }
        }
        #[cfg(target_arch = "x86_64")]
        (Path::Avx2, _) => bands
            .into_par_iter()
            .map_init(
                || BwdScratch::new(n),
                |sc, ty| {
                    // SAFETY: the CPU has AVX2, FMA, POPCNT, BMI1 and BMI2 (path).
                    unsafe { backward_band_avx2(f, &pad, state, grad, ty, sc) }
                },
            )
            .collect(),
        _ => bands
            .into_par_iter()
            .map_init(
                || BwdScratch::new(n),
                |sc, ty| backward_band::<T, P16<T>, Vec<P16<T>>>(f, &pad, state, grad, ty, sc),
            )
            .collect(),
    };
    let mut features = zeros(n * c, T::ZERO);
    let mut screen = zeros(n * SCREEN, T::ZERO);
    features
        .par_chunks_mut(REDUCE_CHUNK * c)
        .zip(screen.par_chunks_mut(REDUCE_CHUNK * SCREEN))
        .enumerate()
        .for_each(|(chunk, (fo, so))| {
            let lo = (chunk * REDUCE_CHUNK) as u32;
            let hi = lo + (so.len() / SCREEN) as u32;
            for bg in &band_grads {
                let start = bg.ids.partition_point(|&g| g < lo);
                let end = bg.ids.partition_point(|&g| g < hi);
                for (i, &g) in bg.ids[start..end].iter().enumerate() {
                    let s = (start + i) * stride;
                    let l = (g - lo) as usize;
                    for (o, v) in fo[l * c..(l + 1) * c].iter_mut().zip(&bg.vals[s..s + c]) {
                        *o += *v;
                    }
                    for (o, v) in so[l * SCREEN..(l + 1) * SCREEN]
                        .iter_mut()
                        .zip(&bg.vals[s + c..s + stride])
                    {
                        *o += *v;
                    }
                }
            }
        });
    let mut background = vec![T::ZERO; c];
    for bg in &band_grads {
        for (a, b) in background.iter_mut().zip(&bg.background) {
            *a += *b;
        }
    }
    Grads2D {
        features,
        screen,
        background,
    }
}

impl<L> BwdScratch<L> {
    fn new(n: usize) -> Self {
        Self {
            dpc: Vec::new(),
            dpp: Vec::new(),
            slot: vec![0; n],
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma,popcnt,bmi1,bmi2")]
unsafe fn backward_band_avx512<D: Blocks<Z16>>(
    f: &Frame<f32>,
    pad: &Padded<f32>,
    state: &PixelState<f32>,
    grad: &[f32],
    ty: usize,
    sc: &mut BwdScratch<Z16>,
) -> BandGrads<f32> {
    backward_band::<f32, Z16, D>(f, pad, state, grad, ty, sc)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,popcnt,bmi1,bmi2")]
unsafe fn backward_band_avx2<T: Real>(
    f: &Frame<T>,
    pad: &Padded<T>,
    state: &PixelState<T>,
    grad: &[T],
    ty: usize,
    sc: &mut BwdScratch<P16<T>>,
) -> BandGrads<T> {
    backward_band::<T, P16<T>, Vec<P16<T>>>(f, pad, state, grad, ty, sc)
}

/// The backward of one band, Gaussian by Gaussian from back to front and, for each, block by
/// block with the block's 16 pixels in lanes. The transmittance in front of each Gaussian
/// is recovered by division, and what lies behind it enters through one running sum per pixel,
/// `s = sum over the Gaussians behind of w_i (dL/dpixel . f_i)`:
/// `dL/dalpha = T (dL/dpixel . f) - (s + T_final (dL/dpixel . background)) / (1 - alpha)`.
/// The Gaussian's own sums (features, screen-space quantities) stay in registers across its
/// blocks.
#[inline(always)]
fn backward_band<T: Real, L: Lanes<T>, D: Blocks<L>>(
    f: &Frame<T>,
    pad: &Padded<T>,
    state: &PixelState<T>,
    grad: &[T],
    ty: usize,
    sc: &mut BwdScratch<L>,
) -> BandGrads<T> {
    let (w, h, c) = (f.width, f.height, f.channels);
    let (feats, bgp, cpad) = (&*pad.features, &*pad.background, pad.cpad);
    let nb = cpad / WIDTH;
    let stride = c + SCREEN;
    let plane = h * w;
    let band = &f.bins.bands[ty];
    let mut ids = band.ids.clone();
    ids.sort_unstable();
    ids.dedup();
    let slot = &mut sc.slot;
    for (s, &g) in ids.iter().enumerate() {
        slot[g as usize] = s as u32;
    }
    let mut vals = zeros(ids.len() * stride, T::ZERO);
    let mut bg_acc = vec![L::zero(); nb];
    let y0 = ty * TILE;
    let th = TILE.min(h - y0);
    sc.dpc.clear();
    sc.dpc.resize(NBLK * cpad, L::zero());
    sc.dpp.clear();
    sc.dpp.resize(NBLK * WIDTH * nb, L::zero());
    let (dpc, dpp) = (&mut sc.dpc, &mut sc.dpp);
    let one = L::splat(T::ONE);
    let half = L::splat(T::lit(0.5));
    let max_alpha = L::splat(T::lit(MAX_ALPHA));
    let mut dfeat_store = D::zeroed(nb, L::zero());
    debug_assert_eq!(dfeat_store.blocks().len(), nb);
    // Per pixel block: transmittance in front of the Gaussian being visited, final
    // transmittance, running sum of what lies behind, dL/dpixel . background, contributor
    // counts, pixel coordinates and which lanes are pixels of the image.
    let mut tb = [L::zero(); NBLK];
    let mut tfin = [L::zero(); NBLK];
    let mut sb = [L::zero(); NBLK];
    let mut bgdot = [L::zero(); NBLK];
    let mut ncon = [L::idx_zero(); NBLK];
    let mut pxy = [(L::zero(), L::zero()); NBLK];
    let mut valid = [0 as Mask; NBLK];
    for tx in 0..w.div_ceil(TILE) {
        let x0 = tx * TILE;
        let tw = TILE.min(w - x0);
        let mut blk_max = [0u32; NBLK];
        let mut kmax = 0;
        for bi in 0..NBLK {
            valid[bi] = 0;
            let Some(at) = BlockAt::<T>::new(bi, x0, y0, tw, th) else {
                continue;
            };
            valid[bi] = at.valid;
            pxy[bi] = (L::from_array(at.px), L::from_array(at.py));
            // The incoming gradient of every channel on this block.
            for ch in 0..c {
                let g = &grad[ch * plane + y0 * w..];
                dpc[bi * cpad + ch] = L::from_array(at.get(g, w, x0, T::ZERO));
            }
            for j in 0..nb {
                // To channels in lanes.
                let mut rows = [L::zero(); WIDTH];
                rows.copy_from_slice(&dpc[bi * cpad + j * WIDTH..bi * cpad + (j + 1) * WIDTH]);
                let cols = L::transpose(rows);
                for (l, col) in cols.iter().enumerate() {
                    dpp[(bi * WIDTH + l) * nb + j] = *col;
                }
            }
            let mut dot = L::zero();
            for ch in 0..c {
                dot = dot.add(dpc[bi * cpad + ch].mul(L::splat(bgp[ch])));
            }
            bgdot[bi] = dot;
            let ft = at.get(&state.final_t[y0 * w..], w, x0, T::ZERO);
            tfin[bi] = L::from_array(ft);
            tb[bi] = tfin[bi];
            sb[bi] = L::zero();
            let nc = at.get(&state.n_contrib[y0 * w..], w, x0, 0);
            ncon[bi] = L::idx_load_first(&nc);
            blk_max[bi] = nc.iter().copied().max().unwrap_or(0);
            kmax = kmax.max(blk_max[bi]);
            for (l, &t) in ft.iter().enumerate() {
                for j in 0..nb {
                    bg_acc[j] = bg_acc[j].add(dpp[(bi * WIDTH + l) * nb + j].mul(L::splat(t)));
                }
            }
        }
        let list = band.tile(tx);
        for k in (0..kmax as usize).rev() {
            if let Some(ahead) = k.checked_sub(PREFETCH_AHEAD) {
                let ahead = list[ahead] as usize;
                prefetch(&f.proj.g, ahead, 1);
                prefetch(feats, ahead * cpad, c);
                prefetch(&vals, slot[ahead] as usize * stride, stride);
            }
            let g = list[k] as usize;
            let s = &f.proj.g[g];
            let Some([(r0, r1), (c0, c1)]) = block_range(s, x0, y0, tw, th) else {
                continue;
            };
            let fp = &feats[g * cpad..g * cpad + c];
            let (ca, cb, cc) = s.conic();
            let (ca, cb, cc) = (L::splat(ca), L::splat(cb), L::splat(cc));
            let dfeat = dfeat_store.blocks();
            for d in dfeat.iter_mut() {
                *d = L::zero();
            }
            let mut geo = [L::zero(); SCREEN];
            let mut touched = false;
            for by in r0..=r1 {
                for bi in by * BLOCKS + c0..=by * BLOCKS + c1 {
                    if k as u32 >= blk_max[bi] {
                        continue;
                    }
                    let (px, py) = pxy[bi];
                    let ([alpha], [gexp], [keep]) = eval_n::<T, L, 1>([s], px, py);
                    let m = keep & valid[bi] & L::idx_gt(ncon[bi], k as u32);
                    if m == 0 {
                        continue;
                    }
                    touched = true;
                    let one_m = one.sub(alpha);
                    // Transmittance in front of this Gaussian, recovered back to front.
                    let t = tb[bi].div(one_m);
                    tb[bi] = L::select(m, t, tb[bi]);
                    let wgt = L::select(m, alpha.mul(t), L::zero());
                    let dpr = &dpc[bi * cpad..bi * cpad + c];
                    let mut dot = L::zero();
                    for (d, &fv) in dpr.iter().zip(fp) {
                        dot = dot.add(d.mul(L::splat(fv)));
                    }
                    let behind = sb[bi].add(tfin[bi].mul(bgdot[bi])).div(one_m);
                    let dalpha = dot.mul(t).sub(behind);
                    sb[bi] = L::select(m, sb[bi].add(wgt.mul(dot)), sb[bi]);
                    // dL/dfeatures = sum over pixels of w dL/dpixel; lanes outside m add exact
                    // zeros, so only the span of m is visited.
                    let wa = wgt.to_array();
                    let (lo, hi) = (m.trailing_zeros() as usize, 15 - m.leading_zeros() as usize);
                    for l in lo..=hi {
                        let wl = L::splat(wa[l]);
                        let at = (bi * WIDTH + l) * nb;
                        for j in 0..dfeat.len() {
                            dfeat[j] = dfeat[j].add(dpp[at + j].mul(wl));
                        }
                    }
                    // alpha = min(0.99, o G): no gradient where the clamp is active.
                    let cm = m & L::splat(s.opacity).mul(gexp).lt(max_alpha);
                    let dal = L::select(cm, dalpha, L::zero());
                    geo[5] = geo[5].add(gexp.mul(dal));
                    let dpow = gexp.mul(L::splat(s.opacity)).mul(dal);
                    // power = -0.5 (A dx^2 + C dy^2) - B dx dy, with d = mean - pixel.
                    let dx = L::splat(s.mx).sub(px);
                    let dy = L::splat(s.my).sub(py);
                    geo[0] = geo[0].sub(dpow.mul(ca.mul(dx).add(cb.mul(dy))));
                    geo[1] = geo[1].sub(dpow.mul(cc.mul(dy).add(cb.mul(dx))));
                    geo[2] = geo[2].sub(half.mul(dpow).mul(dx).mul(dx));
                    geo[3] = geo[3].sub(dpow.mul(dx).mul(dy));
                    geo[4] = geo[4].sub(half.mul(dpow).mul(dy).mul(dy));
                }
            }
            if touched {
                let at = slot[g] as usize * stride;
                let out = &mut vals[at..at + stride];
                for (j, d) in dfeat.iter().enumerate() {
                    let a = d.to_array();
                    let n = WIDTH.min(c - j * WIDTH);
                    for (o, v) in out[j * WIDTH..j * WIDTH + n].iter_mut().zip(&a) {
                        *o += *v;
                    }
                }
                for (o, q) in out[c..].iter_mut().zip(&geo) {
                    *o += q.hsum();
                }
            }
        }
    }
    let mut background = Vec::with_capacity(c);
    for b in &bg_acc {
        background.extend_from_slice(&b.to_array());
    }
    background.truncate(c);
    BandGrads {
        ids,
        vals,
        background,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::binning::bin;
    use crate::project::{project, CamK, GEOM};
    use crate::testscene::{avatar_scene, Regime};

    /// The AVX-512 block masks equal the scalar ones, on tiles inside and at the edge of the
    /// image (partial tiles), for splats inside, straddling and outside the tile, and ones
    /// that reach nothing.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx512_block_masks_equal_scalar_ones() {
        if !gagavatar_testkit::avx512_or_skip("avx512_block_masks_equal_scalar_ones") {
            return;
        }
        let mut rng = crate::rng::Rng::new(21);
        let g: Vec<Splat2D<f32>> = (0..3000)
            .map(|i| {
                let half = |rng: &mut crate::rng::Rng| match i % 9 {
                    0 => -1.0,
                    1 => 0.0,
                    _ => rng.range(0.0, 12.0) as f32,
                };
                Splat2D {
                    mx: rng.range(-20.0, 60.0) as f32,
                    my: rng.range(-20.0, 60.0) as f32,
                    ey: half(&mut rng),
                    ex: half(&mut rng),
                    ..Default::default()
                }
            })
            .collect();
        for (x0, y0, tw, th) in [
            (16, 16, 16, 16),
            (0, 32, 16, 8),
            (32, 0, 8, 16),
            (32, 32, 8, 8),
        ] {
            for len in [0usize, 1, 15, 16, 17, 3000] {
                let list: Vec<u32> = (0..len as u32).rev().collect();
                let (mut want, mut got) = (Vec::new(), Vec::new());
                block_masks(&g, &list, (x0, y0, tw, th), &mut want);
                // SAFETY: the CPU has AVX-512F.
                unsafe { block_masks_avx512(&g, &list, (x0, y0, tw, th), &mut got) };
                for (k, (w, gv)) in want.iter().zip(&got).enumerate() {
                    assert_eq!(
                        gv, w,
                        "tile at ({x0}, {y0}) {tw}x{th}, entry {k}: expected {w:#x}, got {gv:#x}"
                    );
                }
                assert_eq!(got.len(), want.len());
                assert!(len < 3000 || want.iter().filter(|&&m| m != 0).count() > 100);
            }
        }
    }

    /// The mask of a block range has exactly the blocks of the range.
    #[test]
    fn block_mask_is_the_range() {
        assert_eq!(block_mask(None), 0);
        for (r0, r1, c0, c1) in (0..BLOCKS).flat_map(|r0| {
            (r0..BLOCKS).flat_map(move |r1| {
                (0..BLOCKS).flat_map(move |c0| (c0..BLOCKS).map(move |c1| (r0, r1, c0, c1)))
            })
        }) {
            let want: u32 = (0..NBLK)
                .filter(|b| (r0..=r1).contains(&(b / BLOCKS)) && (c0..=c1).contains(&(b % BLOCKS)))
                .map(|b| 1 << b)
                .sum();
            let got = block_mask(Some([(r0, r1), (c0, c1)]));
            assert_eq!(got, want, "rows {r0}..={r1}, columns {c0}..={c1}");
        }
    }

    /// Every pixel a Gaussian reaches (alpha >= 1/255, power <= 0, evaluated in f64 from the
    /// f32 screen-space values) lies in a block of its block range, on scenes with very
    /// anisotropic and tiny-quaternion Gaussians in both size regimes.
    #[test]
    fn block_ranges_cover_every_reached_pixel() {
        for regime in [Regime::Small, Regime::Large] {
            let (s, cam) = avatar_scene(60, 800, 3, regime, 7);
            let mut geom = Vec::with_capacity(s.len() * GEOM);
            for block in [&s.means, &s.opacities, &s.scales, &s.rotations] {
                geom.extend_from_slice(block);
            }
            let k = CamK::<f32>::new(&cam);
            let proj = project(&k, &geom);
            let bins = bin(&proj, k.grid_x, k.grid_y);
            let (mut reached, mut listed) = (0usize, 0usize);
            for (ty, band) in bins.bands.iter().enumerate() {
                let (y0, th) = (ty * TILE, TILE.min(cam.height - ty * TILE));
                for tx in 0..cam.width.div_ceil(TILE) {
                    let (x0, tw) = (tx * TILE, TILE.min(cam.width - tx * TILE));
                    for &gi in band.tile(tx) {
                        let g = &proj.g[gi as usize];
                        let range = block_range(g, x0, y0, tw, th);
                        if let Some([(r0, r1), (c0, c1)]) = range {
                            listed += (r1 - r0 + 1) * (c1 - c0 + 1);
                        }
                        for ly in 0..th {
                            for lx in 0..tw {
                                let dx = g.mx as f64 - (x0 + lx) as f64;
                                let dy = g.my as f64 - (y0 + ly) as f64;
                                let (a, b, c) = g.conic();
                                let (a, b, c) = (a as f64, b as f64, c as f64);
                                let power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy;
                                let alpha = (g.opacity as f64 * power.exp()).min(MAX_ALPHA);
                                if power > 0.0 || alpha < MIN_ALPHA {
                                    continue;
                                }
                                reached += 1;
                                let inside = range.is_some_and(|[(r0, r1), (c0, c1)]| {
                                    (r0..=r1).contains(&(ly / BLOCK))
                                        && (c0..=c1).contains(&(lx / BLOCK))
                                });
                                assert!(
                                    inside,
                                    "{regime:?}: Gaussian {gi} reaches pixel ({}, {}) with \
                                     alpha {alpha} but its block range is {range:?}",
                                    x0 + lx,
                                    y0 + ly
                                );
                            }
                        }
                    }
                }
            }
            assert!(
                reached > 10_000 && listed > 0,
                "{regime:?}: {reached} reached pixels"
            );
        }
    }
}
