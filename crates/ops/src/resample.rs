//! Bilinear resampling `Y = Mh X Mw^T` on the last two dims, differentiable (candle has no
//! backward for its own resize). The interpolation matrices follow PyTorch's
//! `F.interpolate(mode="bilinear")` for the three ways the model uses it (spec section 6).
//! Each output sample has only a few non-zero weights (2, or about `2 in/out` when shrinking
//! with antialias), so on CPU (f32/f64) a custom op applies just those taps, and its backward
//! the transposed taps; elsewhere the dense matrices go through candle's matmul.

use crate::conv::elem::Elem;
use crate::storage::contiguous;
use candle_core::backend::BackendStorage;
use candle_core::{bail, CpuStorage, CustomOp1, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Which bilinear resampling rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResizeMode {
    /// `align_corners=False`, no antialias: source `(o + 0.5) in/out - 0.5`, clamped at 0.
    HalfPixel,
    /// `align_corners=True`: source `o (in - 1)/(out - 1)`; the corners map onto each other.
    AlignCorners,
    /// `antialias=True` (`align_corners=False`): when shrinking by `s = in/out > 1` the triangle
    /// filter is widened to support `s`; when enlarging it equals [`ResizeMode::HalfPixel`].
    Antialias,
}

/// Dense interpolation matrix `[out, in]` (row o holds the weights of output sample o).
pub fn interp_matrix(input: usize, output: usize, mode: ResizeMode) -> Vec<f64> {
    let mut m = vec![0.0f64; output * input];
    if input == 0 || output == 0 {
        return m;
    }
    let scale = input as f64 / output as f64;
    for o in 0..output {
        let row = &mut m[o * input..(o + 1) * input];
        match mode {
            ResizeMode::HalfPixel => {
                let src = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
                two_taps(row, src, input);
            }
            ResizeMode::AlignCorners => {
                let src = if output > 1 {
                    o as f64 * (input as f64 - 1.0) / (output as f64 - 1.0)
                } else {
                    0.0
                };
                two_taps(row, src, input);
            }
            ResizeMode::Antialias => {
                // PyTorch's separable AA kernel: support = scale (or 1 when enlarging), taps
                // over [xmin, xmax) with truncating casts, weights normalised to sum 1.
                let support = scale.max(1.0);
                let inv = 1.0 / support;
                let center = scale * (o as f64 + 0.5);
                let xmin = ((center - support + 0.5) as i64).max(0) as usize;
                let xmax = ((center + support + 0.5) as i64).clamp(0, input as i64) as usize;
                let mut total = 0.0;
                for (j, r) in row.iter_mut().enumerate().take(xmax).skip(xmin) {
                    let x = (j as f64 - center + 0.5) * inv;
                    let w = (1.0 - x.abs()).max(0.0);
                    *r = w;
                    total += w;
                }
                if total > 0.0 {
                    for r in &mut row[xmin..xmax] {
                        *r /= total;
                    }
                }
            }
        }
    }
    m
}

fn two_taps(row: &mut [f64], src: f64, input: usize) {
    let i0 = (src.floor() as usize).min(input - 1);
    let i1 = (i0 + 1).min(input - 1);
    let l = (src - i0 as f64).clamp(0.0, 1.0);
    row[i0] += 1.0 - l;
    row[i1] += l;
}

/// The non-zero band of an interpolation matrix: output `o` reads inputs
/// `start[o] .. start[o] + n` with weights `w[o*n ..][..n]` (zero-padded to a common `n`).
#[derive(Debug, Clone, PartialEq)]
pub struct Taps {
    pub n: usize,
    pub start: Vec<usize>,
    pub w: Vec<f64>,
}

impl Taps {
    /// The band of `interp_matrix(input, output, mode)`, with the same weights bit for bit.
    pub fn new(input: usize, output: usize, mode: ResizeMode) -> Self {
        let rows = interp_rows(input, output, mode);
        let n = rows
            .iter()
            .map(|(a, b, _)| b - a)
            .max()
            .unwrap_or(0)
            .clamp(1, input.max(1));
        let mut start = Vec::with_capacity(output);
        let mut w = vec![0.0; output * n];
        for (o, (lo, hi, vals)) in rows.into_iter().enumerate() {
            // Shift the window left at the end so it stays inside the input.
            let s = lo.min(input.saturating_sub(n));
            start.push(s);
            for (j, v) in (lo..hi).zip(vals) {
                w[o * n + j - s] = v;
            }
        }
        Self { n, start, w }
    }

    fn cast<T: Elem>(&self) -> Vec<T> {
        self.w.iter().map(|&v| T::c(v)).collect()
    }
}

/// Non-zero support `[lo, hi)` and weights of every row of the interpolation matrix, computed
/// exactly as [`interp_matrix`] fills its rows.
fn interp_rows(input: usize, output: usize, mode: ResizeMode) -> Vec<(usize, usize, Vec<f64>)> {
    let m = interp_matrix(input, output, mode);
    (0..output)
        .map(|o| {
            let row = &m[o * input..(o + 1) * input];
            let lo = row.iter().position(|&v| v != 0.0).unwrap_or(0);
            let hi = row.iter().rposition(|&v| v != 0.0).map_or(lo, |i| i + 1);
            (lo, hi, row[lo..hi].to_vec())
        })
        .collect()
}

fn matrix(input: usize, output: usize, mode: ResizeMode, like: &Tensor) -> Result<Tensor> {
    let m = interp_matrix(input, output, mode);
    Tensor::from_vec(m, (output, input), like.device())?.to_dtype(like.dtype())
}

/// Resizes the last two dims of `x` ([..., H, W]) to `(out_h, out_w)`.
pub fn resize(x: &Tensor, out_h: usize, out_w: usize, mode: ResizeMode) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    if dims.len() < 2 {
        candle_core::bail!("resize needs at least 2 dims, got {:?}", dims);
    }
    let (h, w) = (dims[dims.len() - 2], dims[dims.len() - 1]);
    if h == 0 || w == 0 || out_h == 0 || out_w == 0 {
        candle_core::bail!("resize of {h}x{w} to {out_h}x{out_w}: sizes must be positive");
    }
    if !matches!(x.dtype(), DType::F32 | DType::F64) {
        candle_core::bail!("resize supports f32 and f64, got {:?}", x.dtype());
    }
    if out_h == h && out_w == w {
        return Ok(x.clone());
    }
    if x.device().is_cpu() {
        return x.contiguous()?.apply_op1(ResizeOp { out_h, out_w, mode });
    }
    resize_dense(x, out_h, out_w, mode)
}

/// [`resize`] as two dense matrix products (any device; the reference for the tap kernels).
pub fn resize_dense(x: &Tensor, out_h: usize, out_w: usize, mode: ResizeMode) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    if dims.len() < 2 {
        candle_core::bail!("resize needs at least 2 dims, got {:?}", dims);
    }
    let (h, w) = (dims[dims.len() - 2], dims[dims.len() - 1]);
    if h == 0 || w == 0 || out_h == 0 || out_w == 0 {
        candle_core::bail!("resize of {h}x{w} to {out_h}x{out_w}: sizes must be positive");
    }
    let lead: usize = dims[..dims.len() - 2].iter().product();
    let mut y = x.reshape((lead * h, w))?;
    if out_w != w {
        let mw = matrix(w, out_w, mode, x)?;
        y = y.matmul(&mw.t()?)?;
    }
    let mut y = y.reshape((lead, h, out_w))?;
    if out_h != h {
        let mh = matrix(h, out_h, mode, x)?;
        y = mh.broadcast_left(lead)?.contiguous()?.matmul(&y)?;
    }
    let mut out_dims = dims;
    let n = out_dims.len();
    out_dims[n - 2] = out_h;
    out_dims[n - 1] = out_w;
    y.reshape(out_dims)
}

/// Geometry of one resize: `lead` planes of `h x w` to `oh x ow`.
#[derive(Debug, Clone, Copy)]
struct Plan {
    lead: usize,
    h: usize,
    w: usize,
    oh: usize,
    ow: usize,
}

fn plan(dims: &[usize], oh: usize, ow: usize) -> Result<(Plan, Vec<usize>)> {
    let n = dims.len();
    if n < 2 {
        bail!("resize needs at least 2 dims, got {dims:?}");
    }
    let (h, w) = (dims[n - 2], dims[n - 1]);
    let lead = dims[..n - 2].iter().product();
    let mut out = dims.to_vec();
    out[n - 2] = oh;
    out[n - 1] = ow;
    Ok((Plan { lead, h, w, oh, ow }, out))
}

/// `y[o] = sum_t w[o][t] x[start[o] + t]` along a row.
#[inline]
fn taps_row<T: Elem>(x: &[T], start: &[usize], w: &[T], n: usize, y: &mut [T]) {
    // Fixed tap counts unroll; 2 is every non-antialiased resize.
    match n {
        1 => taps_row_n::<T, 1>(x, start, w, y),
        2 => taps_row_n::<T, 2>(x, start, w, y),
        3 => taps_row_n::<T, 3>(x, start, w, y),
        4 => taps_row_n::<T, 4>(x, start, w, y),
        _ => {
            for ((yo, &s), wo) in y.iter_mut().zip(start).zip(w.chunks_exact(n)) {
                let mut acc = T::ZERO;
                for (xv, wv) in x[s..s + n].iter().zip(wo) {
                    acc += *xv * *wv;
                }
                *yo = acc;
            }
        }
    }
}

#[inline(always)]
fn taps_row_n<T: Elem, const N: usize>(x: &[T], start: &[usize], w: &[T], y: &mut [T]) {
    for ((yo, &s), wo) in y.iter_mut().zip(start).zip(w.chunks_exact(N)) {
        let xs = &x[s..s + N];
        let mut acc = T::ZERO;
        for k in 0..N {
            acc += xs[k] * wo[k];
        }
        *yo = acc;
    }
}

/// `x[start[o] + t] += w[o][t] y[o]` along a row (the adjoint of [`taps_row`]).
#[inline]
fn taps_row_adjoint<T: Elem>(y: &[T], start: &[usize], w: &[T], n: usize, x: &mut [T]) {
    x.fill(T::ZERO);
    for ((yo, &s), wo) in y.iter().zip(start).zip(w.chunks_exact(n)) {
        for (xv, wv) in x[s..s + n].iter_mut().zip(wo) {
            *xv += *yo * *wv;
        }
    }
}

/// `out_rows[o] = sum_t w[o][t] in_rows[start[o] + t]` for rows of length `len`.
fn taps_rows<T: Elem>(x: &[T], len: usize, start: &[usize], w: &[T], n: usize, y: &mut [T]) {
    for ((yo, &s), wo) in y.chunks_exact_mut(len).zip(start).zip(w.chunks_exact(n)) {
        yo.fill(T::ZERO);
        for (t, &wv) in wo.iter().enumerate() {
            if wv == T::ZERO {
                continue;
            }
            for (a, b) in yo.iter_mut().zip(&x[(s + t) * len..(s + t + 1) * len]) {
                *a += *b * wv;
            }
        }
    }
}

/// `x_rows[start[o] + t] += w[o][t] y_rows[o]` (the adjoint of [`taps_rows`]).
fn taps_rows_adjoint<T: Elem>(
    y: &[T],
    len: usize,
    start: &[usize],
    w: &[T],
    n: usize,
    x: &mut [T],
) {
    x.fill(T::ZERO);
    for ((yo, &s), wo) in y.chunks_exact(len).zip(start).zip(w.chunks_exact(n)) {
        for (t, &wv) in wo.iter().enumerate() {
            if wv == T::ZERO {
                continue;
            }
            for (a, b) in x[(s + t) * len..(s + t + 1) * len].iter_mut().zip(yo) {
                *a += *b * wv;
            }
        }
    }
}

/// Planes per parallel task: enough work per task to amortise scheduling.
fn planes_per_task(p: &Plan) -> usize {
    let per_plane = (p.h * p.ow + p.oh * p.ow).max(1);
    (1usize << 16).div_ceil(per_plane).clamp(1, p.lead.max(1))
}

/// Forward: width pass (as in the dense version), then height pass, per plane.
fn resize_taps<T: Elem>(x: &[T], p: Plan, th: &Taps, tw: &Taps) -> Vec<T> {
    let (wh, ww) = (th.cast::<T>(), tw.cast::<T>());
    let mut y = crate::conv::elem::alloc_output(p.lead * p.oh * p.ow);
    let chunk = planes_per_task(&p);
    y.par_chunks_mut(chunk * p.oh * p.ow)
        .zip(x.par_chunks(chunk * p.h * p.w))
        .for_each_init(Vec::new, |tmp: &mut Vec<T>, (yc, xc)| {
            for (yp, xp) in yc
                .chunks_exact_mut(p.oh * p.ow)
                .zip(xc.chunks_exact(p.h * p.w))
            {
                let mid: &[T] = if p.ow != p.w {
                    tmp.resize(p.h * p.ow, T::ZERO);
                    for (r, t) in xp.chunks_exact(p.w).zip(tmp.chunks_exact_mut(p.ow)) {
                        taps_row(r, &tw.start, &ww, tw.n, t);
                    }
                    tmp
                } else {
                    xp
                };
                if p.oh != p.h {
                    taps_rows(mid, p.ow, &th.start, &wh, th.n, yp);
                } else {
                    yp.copy_from_slice(mid);
                }
            }
        });
    y
}

/// Backward: the transposed passes in reverse order, `dX = Mh^T dY Mw`.
fn resize_taps_adjoint<T: Elem>(gy: &[T], p: Plan, th: &Taps, tw: &Taps) -> Vec<T> {
    let (wh, ww) = (th.cast::<T>(), tw.cast::<T>());
    let mut gx = crate::conv::elem::alloc_output(p.lead * p.h * p.w);
    let chunk = planes_per_task(&p);
    gx.par_chunks_mut(chunk * p.h * p.w)
        .zip(gy.par_chunks(chunk * p.oh * p.ow))
        .for_each_init(Vec::new, |tmp: &mut Vec<T>, (xc, yc)| {
            for (xp, yp) in xc
                .chunks_exact_mut(p.h * p.w)
                .zip(yc.chunks_exact(p.oh * p.ow))
            {
                let mid: &[T] = if p.oh != p.h {
                    tmp.resize(p.h * p.ow, T::ZERO);
                    taps_rows_adjoint(yp, p.ow, &th.start, &wh, th.n, tmp);
                    tmp
                } else {
                    yp
                };
                if p.ow != p.w {
                    for (r, t) in xp.chunks_exact_mut(p.w).zip(mid.chunks_exact(p.ow)) {
                        taps_row_adjoint(t, &tw.start, &ww, tw.n, r);
                    }
                } else {
                    xp.copy_from_slice(mid);
                }
            }
        });
    gx
}

/// `[..., H, W] -> [..., out_h, out_w]` by the non-zero taps.
struct ResizeOp {
    out_h: usize,
    out_w: usize,
    mode: ResizeMode,
}

impl CustomOp1 for ResizeOp {
    fn name(&self) -> &'static str {
        "gagavatar-resize"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (p, out) = plan(l.dims(), self.out_h, self.out_w)?;
        let th = Taps::new(p.h, p.oh, self.mode);
        let tw = Taps::new(p.w, p.ow, self.mode);
        let y = match s {
            CpuStorage::F32(v) => CpuStorage::F32(resize_taps(
                contiguous(v, l, "resize", "input")?,
                p,
                &th,
                &tw,
            )),
            CpuStorage::F64(v) => CpuStorage::F64(resize_taps(
                contiguous(v, l, "resize", "input")?,
                p,
                &th,
                &tw,
            )),
            s => bail!("resize supports f32 and f64, got {:?}", s.dtype()),
        };
        Ok((y, Shape::from(out)))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let dims = arg.dims();
        let (h, w) = (dims[dims.len() - 2], dims[dims.len() - 1]);
        let op = ResizeAdjointOp {
            in_h: h,
            in_w: w,
            mode: self.mode,
        };
        Ok(Some(grad_res.contiguous()?.apply_op1_no_bwd(&op)?))
    }
}

/// The adjoint of [`ResizeOp`]: `[..., out_h, out_w] -> [..., in_h, in_w]`.
struct ResizeAdjointOp {
    in_h: usize,
    in_w: usize,
    mode: ResizeMode,
}

impl CustomOp1 for ResizeAdjointOp {
    fn name(&self) -> &'static str {
        "gagavatar-resize-adjoint"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (q, out) = plan(l.dims(), self.in_h, self.in_w)?;
        // q maps the gradient's (oh, ow) = its own (h, w) back to the input's size.
        let p = Plan {
            lead: q.lead,
            h: self.in_h,
            w: self.in_w,
            oh: q.h,
            ow: q.w,
        };
        let th = Taps::new(p.h, p.oh, self.mode);
        let tw = Taps::new(p.w, p.ow, self.mode);
        let gx = match s {
            CpuStorage::F32(v) => CpuStorage::F32(resize_taps_adjoint(
                contiguous(v, l, "resize", "input")?,
                p,
                &th,
                &tw,
            )),
            CpuStorage::F64(v) => CpuStorage::F64(resize_taps_adjoint(
                contiguous(v, l, "resize", "input")?,
                p,
                &th,
                &tw,
            )),
            s => bail!("resize backward supports f32 and f64, got {:?}", s.dtype()),
        };
        Ok((gx, Shape::from(out)))
    }
}
