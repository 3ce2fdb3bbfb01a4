//! Per-tile alpha compositing (spec section 7) and its backward.
//!
//! Work is split by bands (one row of 16x16 tiles). Within a tile the loop runs over the tile's
//! Gaussians front to back and, for each, over only the pixels where its alpha can reach 1/255
//! (a conservative ellipse bounding box); the per-pixel arithmetic and its order are exactly the
//! release's, so results do not depend on the thread count.

use crate::binning::Bins;
use crate::project::{Projected, TILE};
use crate::real::Real;
use rayon::prelude::*;

/// Alpha is clamped to this value so a single Gaussian never makes a pixel fully opaque.
pub const MAX_ALPHA: f64 = 0.99;
/// Contributions with alpha below 1/255 are skipped.
pub const MIN_ALPHA: f64 = 1.0 / 255.0;
/// A pixel stops before a Gaussian would take its transmittance below this.
pub const MIN_TRANSMITTANCE: f64 = 1e-4;
/// Extra pixels around the analytic alpha >= 1/255 ellipse box, so that rounding can never
/// exclude a pixel the release would evaluate (extra pixels only cost time).
const BOX_MARGIN_PX: f64 = 1.0;
const BOX_MARGIN_REL: f64 = 1.02;
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

#[derive(Clone, Copy)]
struct G<T> {
    mx: T,
    my: T,
    ca: T,
    cb: T,
    cc: T,
    o: T,
}

impl<T: Real> G<T> {
    #[inline(always)]
    fn load(p: &Projected<T>, g: usize) -> Self {
        Self {
            mx: p.mx[g],
            my: p.my[g],
            ca: p.ca[g],
            cb: p.cb[g],
            cc: p.cc[g],
            o: p.opacity[g],
        }
    }

    /// (power, exp(power), alpha) at pixel centre (px, py), or None where the release skips.
    #[inline(always)]
    fn eval(&self, px: T, py: T) -> Option<(T, T, T, T, T)> {
        let dx = self.mx - px;
        let dy = self.my - py;
        let power = -T::lit(0.5) * (self.ca * dx * dx + self.cc * dy * dy) - self.cb * dx * dy;
        if power > T::ZERO {
            return None;
        }
        let gexp = power.exp();
        let alpha = (self.o * gexp).fmin(T::lit(MAX_ALPHA));
        if alpha < T::lit(MIN_ALPHA) {
            return None;
        }
        Some((dx, dy, gexp, alpha, power))
    }
}

/// Pixel box (inclusive, tile-local) where Gaussian `g` can reach alpha >= 1/255, or None.
#[inline(always)]
fn pixel_box<T: Real>(
    p: &Projected<T>,
    g: usize,
    x0: usize,
    y0: usize,
    tw: usize,
    th: usize,
) -> Option<(usize, usize, usize, usize)> {
    let o = p.opacity[g];
    if o < T::lit(MIN_ALPHA) {
        return None;
    }
    // alpha >= 1/255 needs 0.5 d^T Q d <= ln(255 o); that ellipse's half-extents are
    // sqrt(2 ln(255 o) cov_xx) and sqrt(2 ln(255 o) cov_yy).
    let tc = (255.0 * o.as_f64()).ln().max(0.0);
    let ex = (2.0 * tc * p.va[g].as_f64()).sqrt() * BOX_MARGIN_REL + BOX_MARGIN_PX;
    let ey = (2.0 * tc * p.vc[g].as_f64()).sqrt() * BOX_MARGIN_REL + BOX_MARGIN_PX;
    let (mx, my) = (p.mx[g].as_f64(), p.my[g].as_f64());
    let lo_x = (mx - ex - x0 as f64).ceil().max(0.0);
    let hi_x = (mx + ex - x0 as f64).floor().min(tw as f64 - 1.0);
    let lo_y = (my - ey - y0 as f64).ceil().max(0.0);
    let hi_y = (my + ey - y0 as f64).floor().min(th as f64 - 1.0);
    // NaN-safe: any comparison with NaN fails and skips.
    if lo_x <= hi_x && lo_y <= hi_y {
        Some((lo_x as usize, hi_x as usize, lo_y as usize, hi_y as usize))
    } else {
        None
    }
}

/// Splits `[C, H, W]` planes into per-band row slices so bands can be written in parallel.
fn band_slices<T>(data: &mut [T], planes: usize, height: usize, width: usize) -> Vec<Vec<&mut [T]>> {
    let bands = height.div_ceil(TILE);
    let mut out: Vec<Vec<&mut [T]>> = (0..bands).map(|_| Vec::with_capacity(planes)).collect();
    for plane in data.chunks_mut(height * width) {
        for (b, rows) in plane.chunks_mut(TILE * width).enumerate() {
            out[b].push(rows);
        }
    }
    out
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

/// Composites one image; returns `[C, H, W]` and the per-pixel state.
pub fn forward<T: Real>(f: &Frame<T>) -> (Vec<T>, PixelState<T>) {
    let (w, h, c) = (f.width, f.height, f.channels);
    let mut image = vec![T::ZERO; c * h * w];
    let mut final_t = vec![T::ZERO; h * w];
    let mut n_contrib = vec![0u32; h * w];
    let img_bands = band_slices(&mut image, c, h, w);
    let t_bands = final_t.chunks_mut(TILE * w);
    let n_bands = n_contrib.chunks_mut(TILE * w);
    img_bands
        .into_par_iter()
        .zip(t_bands.collect::<Vec<_>>())
        .zip(n_bands.collect::<Vec<_>>())
        .enumerate()
        .for_each(|(ty, ((mut img, tb), nb))| {
            let band = &f.bins.bands[ty];
            let y0 = ty * TILE;
            let th = TILE.min(h - y0);
            let mut acc = vec![T::ZERO; TILE * TILE * c];
            let mut tr = vec![T::ONE; TILE * TILE];
            let mut last = vec![0u32; TILE * TILE];
            let mut done = vec![false; TILE * TILE];
            for tx in 0..w.div_ceil(TILE) {
                let x0 = tx * TILE;
                let tw = TILE.min(w - x0);
                let npix = tw * th;
                acc[..npix * c].iter_mut().for_each(|v| *v = T::ZERO);
                tr[..npix].iter_mut().for_each(|v| *v = T::ONE);
                last[..npix].iter_mut().for_each(|v| *v = 0);
                done[..npix].iter_mut().for_each(|v| *v = false);
                let mut ndone = 0usize;
                for (k, &gi) in band.tile(tx).iter().enumerate() {
                    if ndone == npix {
                        break;
                    }
                    let g = gi as usize;
                    let Some((bx0, bx1, by0, by1)) = pixel_box(f.proj, g, x0, y0, tw, th) else {
                        continue;
                    };
                    let gs = G::load(f.proj, g);
                    let feat = &f.features[g * c..(g + 1) * c];
                    for ly in by0..=by1 {
                        let py = T::lit((y0 + ly) as f64);
                        for lx in bx0..=bx1 {
                            let p = ly * tw + lx;
                            if done[p] {
                                continue;
                            }
                            let px = T::lit((x0 + lx) as f64);
                            let Some((_, _, _, alpha, _)) = gs.eval(px, py) else {
                                continue;
                            };
                            let t = tr[p];
                            let test_t = t * (T::ONE - alpha);
                            if test_t < T::lit(MIN_TRANSMITTANCE) {
                                done[p] = true;
                                ndone += 1;
                                continue;
                            }
                            let wgt = alpha * t;
                            for (a, &fv) in acc[p * c..(p + 1) * c].iter_mut().zip(feat) {
                                *a += fv * wgt;
                            }
                            tr[p] = test_t;
                            last[p] = k as u32 + 1;
                        }
                    }
                }
                for ly in 0..th {
                    for lx in 0..tw {
                        let p = ly * tw + lx;
                        let o = ly * w + x0 + lx;
                        tb[o] = tr[p];
                        nb[o] = last[p];
                        for (ch, plane) in img.iter_mut().enumerate() {
                            plane[o] = acc[p * c + ch] + tr[p] * f.background[ch];
                        }
                    }
                }
            }
        });
    (image, PixelState { final_t, n_contrib })
}

/// Gradients of one image w.r.t. the per-Gaussian screen-space quantities.
pub struct Grads2D<T> {
    /// [N, C]
    pub features: Vec<T>,
    /// [N, 6]: mean x, mean y, conic A, B, C, opacity.
    pub screen: Vec<T>,
    /// [C]
    pub background: Vec<T>,
}

const SCREEN: usize = 6;

struct BandGrads<T> {
    ids: Vec<u32>,
    /// Per slot: [features (C) | screen (6)].
    vals: Vec<T>,
    background: Vec<T>,
}

/// Backward of [`forward`] given `grad` = dL/dimage `[C, H, W]`.
pub fn backward<T: Real>(f: &Frame<T>, state: &PixelState<T>, grad: &[T], n: usize) -> Grads2D<T> {
    let (w, h, c) = (f.width, f.height, f.channels);
    let stride = c + SCREEN;
    let plane = h * w;
    let band_grads: Vec<BandGrads<T>> = (0..f.bins.bands.len())
        .into_par_iter()
        .map_init(
            || vec![0u32; n],
            |slot, ty| {
                let band = &f.bins.bands[ty];
                let mut ids = band.ids.clone();
                ids.sort_unstable();
                ids.dedup();
                for (s, &g) in ids.iter().enumerate() {
                    slot[g as usize] = s as u32;
                }
                let mut vals = vec![T::ZERO; ids.len() * stride];
                let mut bg = vec![T::ZERO; c];
                let y0 = ty * TILE;
                let th = TILE.min(h - y0);
                let mut dpix = vec![T::ZERO; TILE * TILE * c];
                let mut rec = vec![T::ZERO; TILE * TILE * c];
                let mut tr = vec![T::ZERO; TILE * TILE];
                let mut bg_dot = vec![T::ZERO; TILE * TILE];
                let mut ncon = vec![0u32; TILE * TILE];
                let mut local = vec![T::ZERO; stride];
                for tx in 0..w.div_ceil(TILE) {
                    let x0 = tx * TILE;
                    let tw = TILE.min(w - x0);
                    let mut kmax = 0u32;
                    for ly in 0..th {
                        for lx in 0..tw {
                            let p = ly * tw + lx;
                            let o = (y0 + ly) * w + x0 + lx;
                            let mut dot = T::ZERO;
                            for ch in 0..c {
                                let d = grad[ch * plane + o];
                                dpix[p * c + ch] = d;
                                dot += d * f.background[ch];
                                bg[ch] += d * state.final_t[o];
                            }
                            bg_dot[p] = dot;
                            tr[p] = state.final_t[o];
                            ncon[p] = state.n_contrib[o];
                            kmax = kmax.max(ncon[p]);
                        }
                    }
                    rec[..tw * th * c].iter_mut().for_each(|v| *v = T::ZERO);
                    let list = band.tile(tx);
                    for k in (0..kmax as usize).rev() {
                        let g = list[k] as usize;
                        let Some((bx0, bx1, by0, by1)) = pixel_box(f.proj, g, x0, y0, tw, th)
                        else {
                            continue;
                        };
                        let gs = G::load(f.proj, g);
                        let feat = &f.features[g * c..(g + 1) * c];
                        local.iter_mut().for_each(|v| *v = T::ZERO);
                        let mut touched = false;
                        for ly in by0..=by1 {
                            let py = T::lit((y0 + ly) as f64);
                            for lx in bx0..=bx1 {
                                let p = ly * tw + lx;
                                if k as u32 >= ncon[p] {
                                    continue;
                                }
                                let px = T::lit((x0 + lx) as f64);
                                let Some((dx, dy, gexp, alpha, _)) = gs.eval(px, py) else {
                                    continue;
                                };
                                touched = true;
                                let one_m = T::ONE - alpha;
                                let t = tr[p] / one_m;
                                tr[p] = t;
                                let wgt = alpha * t;
                                let dp = &dpix[p * c..(p + 1) * c];
                                let rc = &mut rec[p * c..(p + 1) * c];
                                let mut dalpha = T::ZERO;
                                for ch in 0..c {
                                    local[ch] += wgt * dp[ch];
                                    dalpha += (feat[ch] - rc[ch]) * dp[ch];
                                    rc[ch] = alpha * feat[ch] + one_m * rc[ch];
                                }
                                let o_final = state.final_t[(y0 + ly) * w + x0 + lx];
                                dalpha = dalpha * t - o_final / one_m * bg_dot[p];
                                // alpha = min(0.99, o G): no gradient where the clamp is active.
                                if gs.o * gexp < T::lit(MAX_ALPHA) {
                                    let dg = gs.o * dalpha;
                                    local[c + 5] += gexp * dalpha;
                                    let dpow = gexp * dg;
                                    // power = -0.5 (A dx^2 + C dy^2) - B dx dy, d = mean - pixel
                                    local[c] -= dpow * (gs.ca * dx + gs.cb * dy);
                                    local[c + 1] -= dpow * (gs.cc * dy + gs.cb * dx);
                                    local[c + 2] -= T::lit(0.5) * dpow * dx * dx;
                                    local[c + 3] -= dpow * dx * dy;
                                    local[c + 4] -= T::lit(0.5) * dpow * dy * dy;
                                }
                            }
                        }
                        if touched {
                            let s = slot[g] as usize * stride;
                            for (v, l) in vals[s..s + stride].iter_mut().zip(&local) {
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
            },
        )
        .collect();

    // Deterministic reduction: each Gaussian sums its band contributions in band order.
    let mut features = vec![T::ZERO; n * c];
    let mut screen = vec![T::ZERO; n * SCREEN];
    features
        .par_chunks_mut(REDUCE_CHUNK * c.max(1))
        .zip(screen.par_chunks_mut(REDUCE_CHUNK * SCREEN))
        .enumerate()
        .for_each(|(chunk, (fo, so))| {
            let lo = (chunk * REDUCE_CHUNK) as u32;
            let hi = lo + (so.len() / SCREEN) as u32;
            for bg in &band_grads {
                let start = bg.ids.partition_point(|&g| g < lo);
                let end = bg.ids.partition_point(|&g| g < hi);
                for (s, &g) in bg.ids[start..end].iter().enumerate() {
                    let s = (start + s) * stride;
                    let l = (g - lo) as usize;
                    for ch in 0..c {
                        fo[l * c + ch] += bg.vals[s + ch];
                    }
                    for q in 0..SCREEN {
                        so[l * SCREEN + q] += bg.vals[s + c + q];
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
