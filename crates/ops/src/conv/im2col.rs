//! General convolution as implicit im2col + GEMM: a band of output rows at a time, so the patch
//! matrix of the band stays in cache instead of materialising one for the whole image (candle's
//! approach, which streams hundreds of MB at 512x512). Handles any kernel size, stride and
//! padding; also provides the weight gradient (all cases) and the input gradient as col2im
//! (for strided convolutions; stride 1 reuses the forward with flipped weights).

use super::elem::{balanced_chunk, gemm, Elem, Mat, SendPtr};
use super::geom::Geom;
use rayon::prelude::*;

/// Patch-matrix budget per band in elements (~1 MiB of f32): big enough that the GEMM's
/// per-call packing is amortised, small enough to stay in the core's L2 for the packing read.
pub(super) const COL_ELEMS: usize = 256 * 1024;
/// Fewer output pixels per GEMM than this make its micro-kernels run mostly on edges.
const MIN_BAND_PX: usize = 256;

/// Rows of output per band: about `col_elems` patch-matrix entries each, balanced over threads.
pub(super) fn band_rows(g: &Geom, k: usize, col_elems: usize, threads: usize) -> usize {
    let px = (col_elems / k.max(1)).max(MIN_BAND_PX);
    let min_rows = MIN_BAND_PX.div_ceil(2 * g.ow).max(1);
    balanced_chunk(g.oh, px.div_ceil(g.ow), g.b, threads, min_rows)
}

/// Valid output columns `[lo, hi)` for kernel column `kx`: those whose input column
/// `ow*s + kx - pw` lies in `[0, w)`.
#[inline]
fn valid_cols(g: &Geom, kx: usize) -> (usize, usize) {
    let s = g.stride;
    let lo = g.pw.saturating_sub(kx).div_ceil(s).min(g.ow);
    // ow*s + kx - pw <= w - 1  <=>  ow <= (w - 1 + pw - kx) / s
    let hi = if g.w + g.pw > kx {
        ((g.w - 1 + g.pw - kx) / s + 1).min(g.ow)
    } else {
        0
    };
    (lo, hi.max(lo))
}

/// Input row of output row `r` and kernel row `ky`, if inside the image.
#[inline]
fn in_row(g: &Geom, r: usize, ky: usize) -> Option<usize> {
    let iy = (r * g.stride + ky).checked_sub(g.ph)?;
    (iy < g.h).then_some(iy)
}

/// Patch matrix `[c*kh*kw, (r1-r0)*ow]` of output rows `[r0, r1)` of the `c` channel planes
/// in `xb` (all of an image's, or a range of them).
pub(super) fn im2col_band<T: Elem>(xb: &[T], g: &Geom, r0: usize, r1: usize, col: &mut [T]) {
    let nb = (r1 - r0) * g.ow;
    let (s, w) = (g.stride, g.w);
    let mut kk = 0;
    for ci in 0..xb.len() / (g.h * w) {
        let plane = &xb[ci * g.h * w..(ci + 1) * g.h * w];
        for ky in 0..g.kh {
            for kx in 0..g.kw {
                let (lo, hi) = valid_cols(g, kx);
                let dst = &mut col[kk * nb..(kk + 1) * nb];
                for (r, d) in (r0..r1).zip(dst.chunks_exact_mut(g.ow)) {
                    let Some(iy) = in_row(g, r, ky) else {
                        d.fill(T::ZERO);
                        continue;
                    };
                    let src = &plane[iy * w..(iy + 1) * w];
                    d[..lo].fill(T::ZERO);
                    d[hi..].fill(T::ZERO);
                    if lo < hi {
                        let first = lo * s + kx - g.pw;
                        if s == 1 {
                            d[lo..hi].copy_from_slice(&src[first..first + hi - lo]);
                        } else {
                            for (o, v) in d[lo..hi].iter_mut().zip(src[first..].iter().step_by(s)) {
                                *o = *v;
                            }
                        }
                    }
                }
                kk += 1;
            }
        }
    }
}

/// Adds the patch-matrix rows of channels `[c0, c1)` (band `[r0, r1)`) back onto the image
/// gradient `gxb` (channels `c0..c1` only; index 0 is channel `c0`).
fn col2im_band<T: Elem>(
    col: &[T],
    g: &Geom,
    c0: usize,
    c1: usize,
    r0: usize,
    r1: usize,
    gxb: &mut [T],
) {
    let nb = (r1 - r0) * g.ow;
    let (s, w) = (g.stride, g.w);
    let mut kk = 0;
    for ci in 0..c1 - c0 {
        let plane = &mut gxb[ci * g.h * w..(ci + 1) * g.h * w];
        for ky in 0..g.kh {
            for kx in 0..g.kw {
                let (lo, hi) = valid_cols(g, kx);
                let src = &col[kk * nb..(kk + 1) * nb];
                for (r, c) in (r0..r1).zip(src.chunks_exact(g.ow)) {
                    let Some(iy) = in_row(g, r, ky) else { continue };
                    if lo >= hi {
                        continue;
                    }
                    let row = &mut plane[iy * w..(iy + 1) * w];
                    let first = lo * s + kx - g.pw;
                    for (d, v) in row[first..].iter_mut().step_by(s).zip(&c[lo..hi]) {
                        *d += *v;
                    }
                }
                kk += 1;
            }
        }
    }
}

/// A 1x1 stride-1 unpadded convolution needs no patch matrix: the input is the matrix.
pub(super) fn is_pointwise(g: &Geom) -> bool {
    g.kh == 1 && g.kw == 1 && g.stride == 1 && g.ph == 0 && g.pw == 0
}

/// Images up to this many output pixels with at least `SPLIT_K_MIN` patch rows split the
/// reduction over input channels instead of the pixels over bands: with few pixels per band,
/// every band task would repack the whole (large) weight matrix.
const SPLIT_K_MAX_PIXELS: usize = 1024;
const SPLIT_K_MIN: usize = 2048;

/// `y = conv(x, w) [+ bias]`; `y` is fully overwritten.
pub(crate) fn forward<T: Elem>(x: &[T], w: &[T], bias: Option<&[T]>, g: &Geom, y: &mut [T]) {
    let threads = rayon::current_num_threads();
    if threads > 1 && g.oh * g.ow <= SPLIT_K_MAX_PIXELS && g.k() >= SPLIT_K_MIN && g.cin >= threads
    {
        return forward_split_k(x, w, bias, g, y, threads);
    }
    let k = g.k();
    let (plane_in, plane_out) = (g.h * g.w, g.oh * g.ow);
    let threads = rayon::current_num_threads();
    let rows = band_rows(g, k, COL_ELEMS, threads);
    let nbands = g.oh.div_ceil(rows);
    let tasks = g.b * nbands;
    let inner = if tasks >= threads { 1 } else { threads };
    let pointwise = is_pointwise(g);
    let yp = SendPtr(y.as_mut_ptr());
    let run = |col: &mut Vec<T>, task: usize| {
        let (bi, band) = (task / nbands, task % nbands);
        let (r0, r1) = (band * rows, ((band + 1) * rows).min(g.oh));
        let nb = (r1 - r0) * g.ow;
        let xb = &x[bi * g.cin * plane_in..(bi + 1) * g.cin * plane_in];
        let rhs = if pointwise {
            Mat {
                ptr: xb[r0 * g.ow..].as_ptr(),
                rs: plane_in as isize,
                cs: 1,
            }
        } else {
            col.resize(k * nb, T::ZERO);
            im2col_band(xb, g, r0, r1, col);
            Mat {
                ptr: col.as_ptr(),
                rs: nb as isize,
                cs: 1,
            }
        };
        // SAFETY: this task alone writes rows [r0, r1) of every channel of image bi.
        let dst = unsafe { yp.get().add(bi * g.cout * plane_out + r0 * g.ow) };
        if let Some(b) = bias {
            for (co, &bv) in b.iter().enumerate() {
                // SAFETY: inside this task's region (see above).
                let d = unsafe { std::slice::from_raw_parts_mut(dst.add(co * plane_out), nb) };
                d.fill(bv);
            }
        }
        let lhs = Mat {
            ptr: w.as_ptr(),
            rs: k as isize,
            cs: 1,
        };
        // SAFETY: operands are in-bounds slices; dst rows are this task's region.
        unsafe {
            gemm(
                g.cout,
                nb,
                k,
                dst,
                plane_out as isize,
                1,
                bias.is_some(),
                lhs,
                rhs,
                inner,
            )
        };
    };
    if inner == 1 {
        (0..tasks).into_par_iter().for_each_init(Vec::new, run);
    } else {
        let mut col = Vec::new();
        (0..tasks).for_each(|t| run(&mut col, t));
    }
}

/// [`forward`] for small images: `chunks` tasks per image each take a range of input
/// channels (their patch rows and weight columns) over the whole image into a partial output;
/// the partials are then added in chunk order (so results do not depend on the batch size).
fn forward_split_k<T: Elem>(
    x: &[T],
    w: &[T],
    bias: Option<&[T]>,
    g: &Geom,
    y: &mut [T],
    chunks: usize,
) {
    let (k, khw) = (g.k(), g.kh * g.kw);
    let (plane_in, plane_out) = (g.h * g.w, g.oh * g.ow);
    let per = g.cin.div_ceil(chunks);
    let chunks = g.cin.div_ceil(per);
    let partials: Vec<Vec<T>> = (0..g.b * chunks)
        .into_par_iter()
        .map(|task| {
            let (bi, c) = (task / chunks, task % chunks);
            let (c0, c1) = (c * per, ((c + 1) * per).min(g.cin));
            let xb = &x[(bi * g.cin + c0) * plane_in..(bi * g.cin + c1) * plane_in];
            let rows = (c1 - c0) * khw;
            let mut col = vec![T::ZERO; rows * plane_out];
            im2col_band(xb, g, 0, g.oh, &mut col);
            let mut part = vec![T::ZERO; g.cout * plane_out];
            let lhs = Mat {
                ptr: w[c0 * khw..].as_ptr(),
                rs: k as isize,
                cs: 1,
            };
            let rhs = Mat {
                ptr: col.as_ptr(),
                rs: plane_out as isize,
                cs: 1,
            };
            // SAFETY: w columns [c0*khw, c1*khw) of every row, col [rows, plane_out], part [cout, plane_out].
            unsafe {
                gemm(
                    g.cout,
                    plane_out,
                    rows,
                    part.as_mut_ptr(),
                    plane_out as isize,
                    1,
                    false,
                    lhs,
                    rhs,
                    1,
                )
            };
            part
        })
        .collect();
    y.par_chunks_mut(plane_out).enumerate().for_each(|(i, yr)| {
        let (bi, co) = (i / g.cout, i % g.cout);
        yr.fill(bias.map_or(T::ZERO, |b| b[co]));
        for p in &partials[bi * chunks..(bi + 1) * chunks] {
            for (a, v) in yr.iter_mut().zip(&p[co * plane_out..(co + 1) * plane_out]) {
                *a += *v;
            }
        }
    });
}

/// `dL/dw [cout, cin*kh*kw] = sum over images and pixels of gy x patches`.
pub(crate) fn grad_weight<T: Elem>(x: &[T], gy: &[T], g: &Geom) -> Vec<T> {
    let k = g.k();
    let (plane_in, plane_out) = (g.h * g.w, g.oh * g.ow);
    let threads = rayon::current_num_threads();
    // The reduction runs over the band's pixels, so longer bands mean fewer passes over dw.
    let rows = band_rows(g, k, 4 * COL_ELEMS, threads);
    let nbands = g.oh.div_ceil(rows);
    let tasks = g.b * nbands;
    let inner = if tasks >= threads { 1 } else { threads };
    let pointwise = is_pointwise(g);
    let run = |col: &mut Vec<T>, acc: &mut [T], task: usize| {
        let (bi, band) = (task / nbands, task % nbands);
        let (r0, r1) = (band * rows, ((band + 1) * rows).min(g.oh));
        let nb = (r1 - r0) * g.ow;
        let xb = &x[bi * g.cin * plane_in..(bi + 1) * g.cin * plane_in];
        // rhs = patches^T: element (pixel p, row kk) = col[kk*nb + p].
        let rhs = if pointwise {
            Mat {
                ptr: xb[r0 * g.ow..].as_ptr(),
                rs: 1,
                cs: plane_in as isize,
            }
        } else {
            col.resize(k * nb, T::ZERO);
            im2col_band(xb, g, r0, r1, col);
            Mat {
                ptr: col.as_ptr(),
                rs: 1,
                cs: nb as isize,
            }
        };
        let gyb = &gy[bi * g.cout * plane_out + r0 * g.ow..];
        let lhs = Mat {
            ptr: gyb.as_ptr(),
            rs: plane_out as isize,
            cs: 1,
        };
        // SAFETY: acc is [cout, k]; operands are in-bounds slices.
        unsafe {
            gemm(
                g.cout,
                k,
                nb,
                acc.as_mut_ptr(),
                k as isize,
                1,
                true,
                lhs,
                rhs,
                inner,
            )
        };
    };
    if inner == 1 {
        (0..tasks)
            .into_par_iter()
            .fold(
                || (Vec::new(), vec![T::ZERO; g.cout * k]),
                |(mut col, mut acc), t| {
                    run(&mut col, &mut acc, t);
                    (col, acc)
                },
            )
            .map(|(_, acc)| acc)
            .reduce_with(|mut a, b| {
                a.iter_mut().zip(&b).for_each(|(a, b)| *a += *b);
                a
            })
            .unwrap_or_else(|| vec![T::ZERO; g.cout * k])
    } else {
        let (mut col, mut acc) = (Vec::new(), vec![T::ZERO; g.cout * k]);
        (0..tasks).for_each(|t| run(&mut col, &mut acc, t));
        acc
    }
}

/// `dL/dx` by col2im: patches-gradient `w^T gy` per band, scattered back onto the input.
/// `gx` must be zero on entry. Tasks own whole input channels, so scatters never collide.
pub(crate) fn grad_input_col2im<T: Elem>(gy: &[T], w: &[T], g: &Geom, gx: &mut [T]) {
    let k = g.k();
    let khw = g.kh * g.kw;
    let (plane_in, plane_out) = (g.h * g.w, g.oh * g.ow);
    let threads = rayon::current_num_threads();
    let chunks = (2 * threads).div_ceil(g.b).clamp(1, g.cin);
    let per = g.cin.div_ceil(chunks);
    let chunks = g.cin.div_ceil(per);
    let rows = band_rows(g, per * khw, COL_ELEMS, 1);
    let tasks = g.b * chunks;
    let gxp = SendPtr(gx.as_mut_ptr());
    (0..tasks)
        .into_par_iter()
        .for_each_init(Vec::new, |col: &mut Vec<T>, task| {
            let (bi, chunk) = (task / chunks, task % chunks);
            let (c0, c1) = (chunk * per, ((chunk + 1) * per).min(g.cin));
            let m = (c1 - c0) * khw;
            // SAFETY: this task alone touches channels [c0, c1) of image bi.
            let gxb = unsafe {
                std::slice::from_raw_parts_mut(
                    gxp.get().add((bi * g.cin + c0) * plane_in),
                    (c1 - c0) * plane_in,
                )
            };
            // lhs = w^T rows of these channels: element (kk, co) = w[co*k + c0*khw + kk].
            let lhs = Mat {
                ptr: w[c0 * khw..].as_ptr(),
                rs: 1,
                cs: k as isize,
            };
            for r0 in (0..g.oh).step_by(rows) {
                let r1 = (r0 + rows).min(g.oh);
                let nb = (r1 - r0) * g.ow;
                col.resize(m * nb, T::ZERO);
                let gyb = &gy[bi * g.cout * plane_out + r0 * g.ow..];
                let rhs = Mat {
                    ptr: gyb.as_ptr(),
                    rs: plane_out as isize,
                    cs: 1,
                };
                // SAFETY: col is [m, nb]; operands are in-bounds slices.
                unsafe {
                    gemm(
                        m,
                        nb,
                        g.cout,
                        col.as_mut_ptr(),
                        nb as isize,
                        1,
                        false,
                        lhs,
                        rhs,
                        1,
                    )
                };
                col2im_band(col, g, c0, c1, r0, r1, gxb);
            }
        });
}
