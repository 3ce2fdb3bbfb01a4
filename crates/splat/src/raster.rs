//! Per-tile alpha compositing (spec section 7) and its backward.
//!
//! Work is split by bands (one row of 16x16 tiles). Within a tile the loop runs over the tile's
//! Gaussians front to back and, for each, over only the pixel rows and column spans where its
//! alpha can reach 1/255 (a slightly inflated ellipse, solved per row). Each row's powers and
//! alphas are computed for all 16 lanes at once, branch-free so the compiler vectorises them;
//! the per-pixel decisions and the accumulation order are exactly the release's, so results
//! do not depend on the thread count or on the SIMD path taken.

use crate::binning::Bins;
use crate::project::{Projected, Splat2D, TILE};
use crate::real::Real;
use rayon::prelude::*;

/// Alpha is clamped to this value so a single Gaussian never makes a pixel fully opaque.
pub const MAX_ALPHA: f64 = 0.99;
/// Contributions with alpha below 1/255 are skipped.
pub const MIN_ALPHA: f64 = 1.0 / 255.0;
/// A pixel stops before a Gaussian would take its transmittance below this.
pub const MIN_TRANSMITTANCE: f64 = 1e-4;
/// Bit mask of a whole row of tile pixels.
const FULL_ROW: u32 = (1 << TILE) - 1;
/// Gaussian slots per reduction chunk in the backward.
const REDUCE_CHUNK: usize = 4096;
/// Screen-space gradient entries per Gaussian: mean x, mean y, conic A, B, C, opacity.
pub const SCREEN: usize = 6;

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

/// Tile-local inclusive row range where the Gaussian can reach alpha >= 1/255.
#[inline(always)]
fn row_range<T: Real>(s: &Splat2D<T>, y0: usize, th: usize) -> Option<(usize, usize)> {
    let cut = s.cut.as_f64();
    if !(cut > 0.0) {
        return None;
    }
    // The ellipse d^T Q d <= cut reaches sqrt(cut * cov_yy) above and below its centre.
    let ey = (cut * s.vc.as_f64()).sqrt();
    let my = s.my.as_f64() - y0 as f64;
    let lo = (my - ey).ceil().max(0.0);
    let hi = (my + ey).floor().min(th as f64 - 1.0);
    (lo <= hi).then_some((lo as usize, hi as usize))
}

/// Power, exp(power) and alpha of one Gaussian for the 16 pixels of a tile row.
struct Lanes<T> {
    power: [T; TILE],
    gexp: [T; TILE],
    alpha: [T; TILE],
}

/// 0, 1, ..., 15 as floats: pixel x = tile origin + lane offset (exact for integers).
#[inline(always)]
fn lane_offsets<T: Real>() -> [T; TILE] {
    std::array::from_fn(|i| T::lit(i as f64))
}

/// Fills `out` for one row and returns the bit mask of lanes the release would not skip
/// (`power <= 0` and `alpha >= 1/255`).
#[inline(always)]
fn eval_row<T: Real>(
    s: &Splat2D<T>,
    lane_x: &[T; TILE],
    x0: usize,
    py: T,
    out: &mut Lanes<T>,
) -> u32 {
    let dy = s.my - py;
    let cdy = s.cc * dy * dy;
    let bdy = s.cb * dy;
    let base = T::lit(x0 as f64);
    let half = T::lit(0.5);
    let max_alpha = T::lit(MAX_ALPHA);
    for i in 0..TILE {
        let dx = s.mx - (base + lane_x[i]);
        let power = -(half * (s.ca * dx * dx + cdy)) - bdy * dx;
        let g = power.fexp();
        out.power[i] = power;
        out.gexp[i] = g;
        out.alpha[i] = (s.opacity * g).fmin(max_alpha);
    }
    T::lane_mask(&out.power, &out.alpha, T::lit(MIN_ALPHA))
}

/// One Gaussian's alphas and exp(power) on one tile row (all 16 lanes) and the bit mask of
/// lanes the release would not skip (`power <= 0` and `alpha >= 1/255`).
#[inline(always)]
pub(crate) fn row_eval<T: Real>(
    s: &Splat2D<T>,
    x0: usize,
    py: T,
    alpha: &mut [T; TILE],
    gexp: &mut [T; TILE],
) -> u32 {
    let mut lanes = Lanes {
        power: [T::ZERO; TILE],
        gexp: [T::ZERO; TILE],
        alpha: [T::ZERO; TILE],
    };
    let mask = eval_row(s, &lane_offsets(), x0, py, &mut lanes);
    *alpha = lanes.alpha;
    *gexp = lanes.gexp;
    mask
}

/// Advances the transmittance of the lanes in `valid` exactly as the release does per pixel.
/// Returns the bit masks of lanes that took the Gaussian (their weight alpha*T is in `w`) and
/// of lanes that stopped before it (T would have dropped below 1e-4).
#[inline(always)]
pub(crate) fn row_take<T: Real>(
    alpha: &[T; TILE],
    valid: u32,
    trow: &mut [T; TILE],
    w: &mut [T; TILE],
) -> (u32, u32) {
    let min_t = T::lit(MIN_TRANSMITTANCE);
    let (mut added, mut stopped) = (0u32, 0u32);
    let mut mask = valid;
    while mask != 0 {
        let lx = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        let t = trow[lx];
        let test_t = t * (T::ONE - alpha[lx]);
        if test_t < min_t {
            stopped |= 1 << lx;
            continue;
        }
        w[lx] = alpha[lx] * t;
        trow[lx] = test_t;
        added |= 1 << lx;
    }
    (added, stopped)
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

/// True when the band kernels can run compiled for AVX2 (wider vectors for the lane loops and
/// the channel accumulation). Rust never contracts a*b+c into an FMA, so both paths round
/// identically and results are bit-identical either way.
#[inline]
fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn forward_band_avx2<T: Real>(f: &Frame<T>, ty: usize, out: BandOut<T>) {
    forward_band::<T, false>(f, ty, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
unsafe fn forward_band_avx512<T: Real>(f: &Frame<T>, ty: usize, out: BandOut<T>) {
    forward_band::<T, true>(f, ty, out)
}

/// Whether the 16-lane AVX-512 row kernel can run (it is bit-identical to the portable one).
#[inline]
fn has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f") && !simd_disabled()
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `GAGAVATAR_NO_AVX512=1` forces the portable row kernel (to compare paths or debug).
fn simd_disabled() -> bool {
    std::env::var_os("GAGAVATAR_NO_AVX512").is_some_and(|v| v != "0")
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn backward_band_avx2<T: Real>(
    f: &Frame<T>,
    state: &PixelState<T>,
    grad: &[T],
    ty: usize,
    slot: &mut [u32],
) -> BandGrads<T> {
    backward_band::<T, true, false>(f, state, grad, ty, slot)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
unsafe fn backward_band_avx512<T: Real>(
    f: &Frame<T>,
    state: &PixelState<T>,
    grad: &[T],
    ty: usize,
    slot: &mut [u32],
) -> BandGrads<T> {
    backward_band::<T, true, true>(f, state, grad, ty, slot)
}

struct BandOut<'a, T> {
    image: Vec<&'a mut [T]>,
    final_t: &'a mut [T],
    n_contrib: &'a mut [u32],
}

/// Composites one image; returns `[C, H, W]` and the per-pixel state.
pub fn forward<T: Real>(f: &Frame<T>) -> (Vec<T>, PixelState<T>) {
    let (w, h, c) = (f.width, f.height, f.channels);
    // Only ever written, so calloc'ed memory costs nothing extra here (see [`zeros`]).
    let mut image = vec![T::ZERO; c * h * w];
    let mut final_t = vec![T::ZERO; h * w];
    let mut n_contrib = vec![0u32; h * w];
    let outs: Vec<BandOut<T>> = band_slices(&mut image, c, h, w)
        .into_iter()
        .zip(final_t.chunks_mut(TILE * w))
        .zip(n_contrib.chunks_mut(TILE * w))
        .map(|((image, final_t), n_contrib)| BandOut {
            image,
            final_t,
            n_contrib,
        })
        .collect();
    let avx2 = has_avx2();
    let avx512 = avx2 && has_avx512();
    outs.into_par_iter().enumerate().for_each(|(ty, out)| {
        #[cfg(target_arch = "x86_64")]
        if avx512 {
            // SAFETY: the CPU supports AVX-512F and AVX2 (checked above).
            return unsafe { forward_band_avx512(f, ty, out) };
        }
        #[cfg(target_arch = "x86_64")]
        if avx2 {
            // SAFETY: the CPU supports AVX2 (checked by has_avx2).
            return unsafe { forward_band_avx2(f, ty, out) };
        }
        forward_band::<T, false>(f, ty, out)
    });
    (image, PixelState { final_t, n_contrib })
}

#[inline(always)]
fn forward_band<T: Real, const AVX512: bool>(f: &Frame<T>, ty: usize, mut out: BandOut<T>) {
    let band = &f.bins.bands[ty];
    let mut wrow = [T::ZERO; TILE];
    let (w, h, c) = (f.width, f.height, f.channels);
    let y0 = ty * TILE;
    let th = TILE.min(h - y0);
    // Channel sums per tile pixel, [TILE * TILE][C]. Each pixel receives its Gaussians front to
    // back, so the rounding is that of compositing the pixel on its own.
    let mut acc = vec![T::ZERO; TILE * TILE * c];
    let mut alpha = [[T::ZERO; TILE]; TILE];
    let mut gexp = [T::ZERO; TILE];
    let mut valid = [0u32; TILE];
    for tx in 0..w.div_ceil(TILE) {
        let x0 = tx * TILE;
        let tw = TILE.min(w - x0);
        let npix = TILE * th;
        acc.iter_mut().for_each(|v| *v = T::ZERO);
        let mut tr = [T::ONE; TILE * TILE];
        let mut last = [0u32; TILE * TILE];
        // Columns beyond the image edge count as done from the start.
        let edge_mask: u32 = !((1u32 << tw) - 1) & FULL_ROW;
        let mut row_done = [edge_mask; TILE];
        let mut ndone = (TILE - tw) * th;
        let list = band.tile(tx);
        for (k, &gi) in list.iter().enumerate() {
            if ndone == npix {
                break;
            }
            if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
                prefetch(&f.proj.g, ahead as usize, 1);
                prefetch(f.features, ahead as usize * c, c);
            }
            let g = gi as usize;
            let s = &f.proj.g[g];
            let Some((ry0, ry1)) = row_range(s, y0, th) else {
                continue;
            };
            let feat = &f.features[g * c..(g + 1) * c];
            // All rows' alphas first: they do not depend on the transmittance, so these
            // iterations overlap instead of waiting on each other's exp.
            for ly in ry0..=ry1 {
                valid[ly] = if row_done[ly] == FULL_ROW {
                    0
                } else {
                    let py = T::lit((y0 + ly) as f64);
                    let a = if AVX512 {
                        // SAFETY: AVX512 = true only in the AVX-512 kernel, entered after the check.
                        unsafe { T::row_eval_avx512(s, x0, py, &mut alpha[ly], &mut gexp) }
                    } else {
                        row_eval(s, x0, py, &mut alpha[ly], &mut gexp)
                    };
                    a & !row_done[ly] & FULL_ROW
                };
            }
            for ly in ry0..=ry1 {
                if valid[ly] == 0 {
                    continue;
                }
                let trow: &mut [T; TILE] = (&mut tr[ly * TILE..(ly + 1) * TILE])
                    .try_into()
                    .expect("a tile row has TILE pixels");
                let (mut added, stopped) = if AVX512 {
                    // SAFETY: as above.
                    unsafe { T::row_take_avx512(&alpha[ly], valid[ly], trow, &mut wrow) }
                } else {
                    row_take(&alpha[ly], valid[ly], trow, &mut wrow)
                };
                row_done[ly] |= stopped;
                ndone += stopped.count_ones() as usize;
                while added != 0 {
                    let lx = added.trailing_zeros() as usize;
                    added &= added - 1;
                    let p = ly * TILE + lx;
                    T::accumulate(&mut acc[p * c..(p + 1) * c], feat, wrow[lx]);
                    last[p] = k as u32 + 1;
                }
            }
        }
        for ly in 0..th {
            let o = ly * w + x0;
            out.final_t[o..o + tw].copy_from_slice(&tr[ly * TILE..ly * TILE + tw]);
            out.n_contrib[o..o + tw].copy_from_slice(&last[ly * TILE..ly * TILE + tw]);
        }
        // Plane by plane and row by row: contiguous stores (32 planes per pixel would touch 32
        // pages at once).
        for (ch, plane) in out.image.iter_mut().enumerate() {
            let bg = f.background[ch];
            for ly in 0..th {
                let o = ly * w + x0;
                for (lx, v) in plane[o..o + tw].iter_mut().enumerate() {
                    let p = ly * TILE + lx;
                    *v = acc[p * c + ch] + tr[p] * bg;
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

/// Backward of [`forward`] given `grad` = dL/dimage `[C, H, W]`.
///
/// Each band accumulates into its own compact buffer (one slot per Gaussian it touches), and
/// the buffers are summed per Gaussian in band order, so gradients are bit-identical for any
/// thread count.
pub fn backward<T: Real>(f: &Frame<T>, state: &PixelState<T>, grad: &[T], n: usize) -> Grads2D<T> {
    let c = f.channels;
    let stride = c + SCREEN;
    let avx2 = has_avx2();
    let avx512 = avx2 && has_avx512();
    let band_grads: Vec<BandGrads<T>> = (0..f.bins.bands.len())
        .into_par_iter()
        .map_init(
            || vec![0u32; n],
            |slot, ty| {
                #[cfg(target_arch = "x86_64")]
                if avx512 {
                    // SAFETY: the CPU supports AVX-512F and AVX2 (checked above).
                    return unsafe { backward_band_avx512(f, state, grad, ty, slot) };
                }
                #[cfg(target_arch = "x86_64")]
                if avx2 {
                    // SAFETY: the CPU supports AVX2 (checked by has_avx2).
                    return unsafe { backward_band_avx2(f, state, grad, ty, slot) };
                }
                backward_band::<T, false, false>(f, state, grad, ty, slot)
            },
        )
        .collect();
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

#[inline(always)]
fn backward_band<T: Real, const AVX2: bool, const AVX512: bool>(
    f: &Frame<T>,
    state: &PixelState<T>,
    grad: &[T],
    ty: usize,
    slot: &mut [u32],
) -> BandGrads<T> {
    let (w, h, c) = (f.width, f.height, f.channels);
    let stride = c + SCREEN;
    let plane = h * w;
    let band = &f.bins.bands[ty];
    let mut ids = band.ids.clone();
    ids.sort_unstable();
    ids.dedup();
    for (s, &g) in ids.iter().enumerate() {
        slot[g as usize] = s as u32;
    }
    let mut vals = zeros(ids.len() * stride, T::ZERO);
    let mut bg = vec![T::ZERO; c];
    let y0 = ty * TILE;
    let th = TILE.min(h - y0);
    let mut dpix = vec![T::ZERO; TILE * TILE * c];
    let mut rec = vec![T::ZERO; TILE * TILE * c];
    let mut tr = [T::ZERO; TILE * TILE];
    let mut t_final = [T::ZERO; TILE * TILE];
    let mut bg_dot = [T::ZERO; TILE * TILE];
    let mut local = vec![T::ZERO; stride];
    let mut ralpha = [[T::ZERO; TILE]; TILE];
    let mut rgexp = [[T::ZERO; TILE]; TILE];
    let mut rmask = [0u32; TILE];
    let max_alpha = T::lit(MAX_ALPHA);
    let half = T::lit(0.5);
    for tx in 0..w.div_ceil(TILE) {
        let x0 = tx * TILE;
        let tw = TILE.min(w - x0);
        let cols: u32 = (1u32 << tw) - 1;
        let mut kmax = 0u32;
        let mut ncon = [0u32; TILE * TILE];
        let mut row_max = [0u32; TILE];
        // The incoming gradient plane by plane, row by row (contiguous reads; 32 planes per
        // pixel would touch 32 pages at once).
        for ch in 0..c {
            for ly in 0..th {
                let o = ch * plane + (y0 + ly) * w + x0;
                for (lx, &d) in grad[o..o + tw].iter().enumerate() {
                    dpix[(ly * TILE + lx) * c + ch] = d;
                }
            }
        }
        for ly in 0..th {
            for lx in 0..tw {
                let p = ly * TILE + lx;
                let o = (y0 + ly) * w + x0 + lx;
                let mut dot = T::ZERO;
                for ch in 0..c {
                    let d = dpix[p * c + ch];
                    dot += d * f.background[ch];
                    bg[ch] += d * state.final_t[o];
                }
                bg_dot[p] = dot;
                tr[p] = state.final_t[o];
                t_final[p] = state.final_t[o];
                ncon[p] = state.n_contrib[o];
                row_max[ly] = row_max[ly].max(ncon[p]);
                kmax = kmax.max(ncon[p]);
            }
        }
        rec.iter_mut().for_each(|v| *v = T::ZERO);
        let list = band.tile(tx);
        for k in (0..kmax as usize).rev() {
            if let Some(ahead) = k.checked_sub(PREFETCH_AHEAD) {
                let ahead = list[ahead] as usize;
                prefetch(&f.proj.g, ahead, 1);
                prefetch(f.features, ahead * c, c);
                prefetch(&vals, slot[ahead] as usize * stride, stride);
            }
            let g = list[k] as usize;
            let s = &f.proj.g[g];
            let Some((ry0, ry1)) = row_range(s, y0, th) else {
                continue;
            };
            let feat = &f.features[g * c..(g + 1) * c];
            local.iter_mut().for_each(|v| *v = T::ZERO);
            let mut touched = false;
            // All rows' alphas first (independent of each other, so they overlap), then the
            // per-pixel work.
            for ly in ry0..=ry1 {
                rmask[ly] = if k as u32 >= row_max[ly] {
                    0
                } else {
                    let py = T::lit((y0 + ly) as f64);
                    let m = if AVX512 {
                        // SAFETY: AVX512 = true only in the AVX-512 kernel, entered after the check.
                        unsafe { T::row_eval_avx512(s, x0, py, &mut ralpha[ly], &mut rgexp[ly]) }
                    } else {
                        row_eval(s, x0, py, &mut ralpha[ly], &mut rgexp[ly])
                    };
                    m & cols
                };
            }
            for ly in ry0..=ry1 {
                let mut mask = rmask[ly];
                if mask == 0 {
                    continue;
                }
                let py = T::lit((y0 + ly) as f64);
                let dy = s.my - py;
                while mask != 0 {
                    let lx = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    let p = ly * TILE + lx;
                    if k as u32 >= ncon[p] {
                        continue;
                    }
                    let alpha = ralpha[ly][lx];
                    touched = true;
                    let gexp = rgexp[ly][lx];
                    let dx = s.mx - T::lit((x0 + lx) as f64);
                    let one_m = T::ONE - alpha;
                    // Transmittance in front of this Gaussian, recovered back to front.
                    let t = tr[p] / one_m;
                    tr[p] = t;
                    let wgt = alpha * t;
                    let dp = &dpix[p * c..(p + 1) * c];
                    let rc = &mut rec[p * c..(p + 1) * c];
                    // rec = colour composited behind this Gaussian, per unit transmittance.
                    let mut dalpha = if AVX2 {
                        // SAFETY: AVX2 = true only in the AVX2 kernel, entered after the check.
                        unsafe {
                            T::blend_back_avx2(&mut local[..c], dp, feat, rc, wgt, alpha, one_m)
                        }
                    } else {
                        T::blend_back(&mut local[..c], dp, feat, rc, wgt, alpha, one_m)
                    };
                    dalpha = dalpha * t - t_final[p] / one_m * bg_dot[p];
                    // alpha = min(0.99, o G): no gradient where the clamp is active.
                    if s.opacity * gexp < max_alpha {
                        local[c + 5] += gexp * dalpha;
                        let dpow = gexp * s.opacity * dalpha;
                        // power = -0.5 (A dx^2 + C dy^2) - B dx dy, with d = mean - pixel.
                        local[c] -= dpow * (s.ca * dx + s.cb * dy);
                        local[c + 1] -= dpow * (s.cc * dy + s.cb * dx);
                        local[c + 2] -= half * dpow * dx * dx;
                        local[c + 3] -= dpow * dx * dy;
                        local[c + 4] -= half * dpow * dy * dy;
                    }
                }
            }
            if touched {
                let at = slot[g] as usize * stride;
                for (v, l) in vals[at..at + stride].iter_mut().zip(&local) {
                    *v += *l;
                }
            }
        }
    }
    BandGrads {
        ids,
        vals,
        background: bg,
    }
}
