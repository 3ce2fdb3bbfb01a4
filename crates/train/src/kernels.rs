//! CPU kernels of the perceptual network, as differentiable candle custom ops (f32 and f64),
//! each with a portable candle-op fallback for other devices:
//!
//! - [`maxpool2d`]: max-pooling with PyTorch's gradient rule;
//! - [`relu`]: ReLU whose backward is one pass (`grad * (y > 0)`, PyTorch's rule at 0) instead
//!   of candle's four temporaries;
//! - [`layer_distance`]: the per-layer perceptual distance (channel unit-normalisation, `|a - b|`,
//!   channel sum, mean over positions) in one pass over the features and one for the gradient.
//!   Written as candle ops it makes ~10 full-size temporaries per layer and took as long as the
//!   network's forward pass at 512x512.
//!
//! Fresh large buffers are what these ops save: at 512x512 a VGG block-1 feature map is 64 MB,
//! and every new buffer of that size is page-faulted in and zeroed by the kernel.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, DType, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::error::{input_err, Result};

/// Float types of the CPU kernels.
pub(crate) trait Float:
    Copy
    + Send
    + Sync
    + PartialOrd
    + Default
    + std::ops::AddAssign
    + std::ops::Mul<Output = Self>
    + 'static
{
    fn is_nan(self) -> bool;
    fn to_f64(self) -> f64;
    fn from_f64(v: f64) -> Self;
    fn zero() -> Self;
}

impl Float for f32 {
    fn is_nan(self) -> bool {
        f32::is_nan(self)
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn zero() -> Self {
        0.0
    }
}

impl Float for f64 {
    fn is_nan(self) -> bool {
        f64::is_nan(self)
    }
    fn to_f64(self) -> f64 {
        self
    }
    fn from_f64(v: f64) -> Self {
        v
    }
    fn zero() -> Self {
        0.0
    }
}

fn contiguous<'a, T>(v: &'a [T], l: &Layout, what: &str) -> candle_core::Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what} must be contiguous"),
    }
}

fn ours(x: &Tensor) -> bool {
    x.device().is_cpu() && matches!(x.dtype(), DType::F32 | DType::F64)
}

// ---------------------------------------------------------------------------------------------
// Max-pooling with PyTorch's gradient (all of it to the first maximum of each window).

/// `max_pool2d(x, kernel k, stride s)` on `[B, C, H, W]` (no padding, floor mode), with a
/// backward pass. candle's own max-pool backward only handles `k == s` and scales the gradient
/// wrongly (see [`maxpool2d_portable`]); on the CPU this op gives each window's gradient to its first maximum in
/// row-major order, like PyTorch. Other devices use candle ops (index_select + maximum).
pub fn maxpool2d(x: &Tensor, k: usize, s: usize) -> Result<Tensor> {
    pool_dims(x, k, s)?;
    if ours(x) {
        return Ok(x.contiguous()?.apply_op1(MaxPool { k, s })?);
    }
    maxpool2d_portable(x, k, s)
}

/// `(H, W)` of a `[B, C, H, W]` max-pool input, or an error when the window does not fit.
fn pool_dims(x: &Tensor, k: usize, s: usize) -> Result<(usize, usize)> {
    let (_, _, h, w) = x.dims4()?;
    if k == 0 || s == 0 || h < k || w < k {
        return Err(input_err(
            "max-pool input",
            format!(
                "{:?} is smaller than the {k}x{k} window (stride {s})",
                x.dims()
            ),
        ));
    }
    Ok((h, w))
}

/// [`maxpool2d`] from candle ops only (any device; the path used off the CPU): max reductions
/// over a reshape when `k == s`, else the maximum over the `k^2` strided `index_select`s. Tied
/// maxima do not follow PyTorch's rule here (measure zero for real features).
pub fn maxpool2d_portable(x: &Tensor, k: usize, s: usize) -> Result<Tensor> {
    let (h, w) = pool_dims(x, k, s)?;
    let (oh, ow) = ((h - k) / s + 1, (w - k) / s + 1);
    if k == s {
        // Non-overlapping windows: a reshape and two max reductions. (candle's own max-pool
        // backward scales the gradient by (number of maxima) / k^2 instead of dividing by the
        // number of maxima, and assumes sizes divisible by k, so it is not used.)
        let (b, c, _, _) = x.dims4()?;
        let x = x.narrow(2, 0, oh * k)?.narrow(3, 0, ow * k)?;
        return Ok(x.reshape((b, c, oh, k, ow, k))?.max(5)?.max(3)?);
    }
    let pick = |n: usize, off: usize| -> Result<Tensor> {
        let idx: Vec<u32> = (0..n).map(|i| (off + i * s) as u32).collect();
        Ok(Tensor::from_vec(idx, n, x.device())?)
    };
    let mut out: Option<Tensor> = None;
    for dy in 0..k {
        let rows = x.index_select(&pick(oh, dy)?, 2)?;
        for dx in 0..k {
            let t = rows.index_select(&pick(ow, dx)?, 3)?;
            out = Some(match out {
                None => t,
                Some(o) => o.maximum(&t)?,
            });
        }
    }
    out.ok_or_else(|| input_err("max-pool", "empty window"))
}

#[derive(Debug, Clone, Copy)]
struct MaxPool {
    k: usize,
    s: usize,
}

impl MaxPool {
    fn geom(&self, dims: &[usize]) -> candle_core::Result<[usize; 6]> {
        match dims {
            &[b, c, h, w] if h >= self.k && w >= self.k => Ok([
                b,
                c,
                h,
                w,
                (h - self.k) / self.s + 1,
                (w - self.k) / self.s + 1,
            ]),
            other => candle_core::bail!("max-pool {}x{}: bad input {other:?}", self.k, self.k),
        }
    }

    /// Flat offset (within the plane) of the window's first maximum (NaN wins, as in PyTorch).
    #[inline]
    fn argmax<T: Float>(&self, plane: &[T], w: usize, i: usize, j: usize) -> usize {
        let mut best = i * self.s * w + j * self.s;
        let mut bv = plane[best];
        for dy in 0..self.k {
            let row = (i * self.s + dy) * w + j * self.s;
            for dx in 0..self.k {
                let v = plane[row + dx];
                if !bv.is_nan() && (v > bv || v.is_nan()) {
                    bv = v;
                    best = row + dx;
                }
            }
        }
        best
    }

    fn forward<T: Float>(&self, x: &[T], g: [usize; 6]) -> Vec<T> {
        let [b, c, h, w, oh, ow] = g;
        let mut out = vec![T::default(); b * c * oh * ow];
        out.par_chunks_mut(oh * ow)
            .zip(x.par_chunks(h * w))
            .for_each(|(o, plane)| {
                for i in 0..oh {
                    for j in 0..ow {
                        o[i * ow + j] = plane[self.argmax(plane, w, i, j)];
                    }
                }
            });
        out
    }

    fn backward<T: Float>(&self, x: &[T], gy: &[T], g: [usize; 6]) -> Vec<T> {
        let [b, c, h, w, oh, ow] = g;
        let mut gx = vec![T::default(); b * c * h * w];
        gx.par_chunks_mut(h * w)
            .zip(x.par_chunks(h * w).zip(gy.par_chunks(oh * ow)))
            .for_each(|(gp, (plane, gyp))| {
                for i in 0..oh {
                    for j in 0..ow {
                        gp[self.argmax(plane, w, i, j)] += gyp[i * ow + j];
                    }
                }
            });
        gx
    }
}

impl CustomOp1 for MaxPool {
    fn name(&self) -> &'static str {
        "gagavatar-maxpool2d"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let g = self.geom(l.dims())?;
        let out = match s {
            CpuStorage::F32(v) => {
                CpuStorage::F32(self.forward(contiguous(v, l, "max-pool input")?, g))
            }
            CpuStorage::F64(v) => {
                CpuStorage::F64(self.forward(contiguous(v, l, "max-pool input")?, g))
            }
            other => candle_core::bail!("max-pool: f32 or f64 only, got {:?}", other.dtype()),
        };
        Ok((out, Shape::from((g[0], g[1], g[4], g[5]))))
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        let gy = grad_res.contiguous()?;
        Ok(Some(arg.apply_op2_no_bwd(&gy, &MaxPoolGrad(*self))?))
    }
}

/// `dL/dx` of [`MaxPool`] from `x` (arg 1) and `dL/dy` (arg 2).
struct MaxPoolGrad(MaxPool);

impl CustomOp2 for MaxPoolGrad {
    fn name(&self) -> &'static str {
        "gagavatar-maxpool2d-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let g = self.0.geom(l1.dims())?;
        if l2.dims() != [g[0], g[1], g[4], g[5]] {
            candle_core::bail!(
                "max-pool backward: gradient {:?} does not match input {:?}",
                l2.dims(),
                l1.dims()
            );
        }
        let out = match (s1, s2) {
            (CpuStorage::F32(x), CpuStorage::F32(gy)) => CpuStorage::F32(self.0.backward(
                contiguous(x, l1, "max-pool input")?,
                contiguous(gy, l2, "max-pool gradient")?,
                g,
            )),
            (CpuStorage::F64(x), CpuStorage::F64(gy)) => CpuStorage::F64(self.0.backward(
                contiguous(x, l1, "max-pool input")?,
                contiguous(gy, l2, "max-pool gradient")?,
                g,
            )),
            (a, b) => candle_core::bail!(
                "max-pool backward: f32 or f64 of one type, got {:?} and {:?}",
                a.dtype(),
                b.dtype()
            ),
        };
        Ok((out, Shape::from(l1.dims())))
    }
}

// ---------------------------------------------------------------------------------------------
// ReLU with a one-pass backward.

/// `max(x, 0)` (NaN stays NaN); the gradient is `grad * (y > 0)`, zero at 0 like PyTorch.
pub fn relu(x: &Tensor) -> Result<Tensor> {
    if ours(x) {
        Ok(x.contiguous()?.apply_op1(Relu)?)
    } else {
        Ok(x.relu()?)
    }
}

/// Elements per parallel task of the element-wise kernels.
const ELEM_CHUNK: usize = 1 << 16;

struct Relu;

fn relu_fwd<T: Float>(x: &[T]) -> Vec<T> {
    let mut out = vec![T::zero(); x.len()];
    out.par_chunks_mut(ELEM_CHUNK)
        .zip(x.par_chunks(ELEM_CHUNK))
        .for_each(|(o, x)| {
            for (o, &v) in o.iter_mut().zip(x) {
                *o = if v > T::zero() || v.is_nan() {
                    v
                } else {
                    T::zero()
                };
            }
        });
    out
}

fn relu_bwd<T: Float>(y: &[T], g: &[T]) -> Vec<T> {
    let mut out = vec![T::zero(); y.len()];
    out.par_chunks_mut(ELEM_CHUNK)
        .zip(y.par_chunks(ELEM_CHUNK).zip(g.par_chunks(ELEM_CHUNK)))
        .for_each(|(o, (y, g))| {
            for ((o, &y), &g) in o.iter_mut().zip(y).zip(g) {
                *o = if y > T::zero() { g } else { T::zero() };
            }
        });
    out
}

impl CustomOp1 for Relu {
    fn name(&self) -> &'static str {
        "gagavatar-relu"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let out = match s {
            CpuStorage::F32(v) => CpuStorage::F32(relu_fwd(contiguous(v, l, "relu input")?)),
            CpuStorage::F64(v) => CpuStorage::F64(relu_fwd(contiguous(v, l, "relu input")?)),
            other => candle_core::bail!("relu: f32 or f64 only, got {:?}", other.dtype()),
        };
        Ok((out, l.shape().clone()))
    }

    fn bwd(
        &self,
        _arg: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        Ok(Some(res.apply_op2_no_bwd(&grad.contiguous()?, &ReluGrad)?))
    }
}

/// `dL/dx` of [`Relu`] from its output (arg 1) and `dL/dy` (arg 2).
struct ReluGrad;

impl CustomOp2 for ReluGrad {
    fn name(&self) -> &'static str {
        "gagavatar-relu-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        if l1.dims() != l2.dims() {
            candle_core::bail!("relu backward: {:?} vs {:?}", l1.dims(), l2.dims());
        }
        let out = match (s1, s2) {
            (CpuStorage::F32(y), CpuStorage::F32(g)) => CpuStorage::F32(relu_bwd(
                contiguous(y, l1, "relu output")?,
                contiguous(g, l2, "relu gradient")?,
            )),
            (CpuStorage::F64(y), CpuStorage::F64(g)) => CpuStorage::F64(relu_bwd(
                contiguous(y, l1, "relu output")?,
                contiguous(g, l2, "relu gradient")?,
            )),
            (a, b) => candle_core::bail!(
                "relu backward: f32 or f64 of one type, got {:?} and {:?}",
                a.dtype(),
                b.dtype()
            ),
        };
        Ok((out, l1.shape().clone()))
    }
}

// ---------------------------------------------------------------------------------------------
// The fused per-layer perceptual distance.

/// Added to the channel norm before dividing (the release's `normalize_tensor` eps).
pub const NORM_EPS: f64 = 1e-10;
/// Inside the square root of the channel norm (keeps its gradient finite at zero).
pub const NORM_SQRT_EPS: f64 = 1e-20;
/// Positions per parallel task of the distance kernel.
const POS_CHUNK: usize = 256;

/// The per-layer distance between feature maps `a` (`[k B, C, H, W]`, `k` groups of `B`) and
/// `b` (`[B, C, H, W]`): the sum over the `k` groups of
/// `mean over (b, h, w) of sum over c of |a / |a| - b / |b||`, where `|f|` is the channel norm
/// `sqrt(sum_c f^2 + 1e-20) + 1e-10`. `|d|` has gradient `sign(d)` with `sign(0) = 0`.
/// A scalar; differentiable with respect to both inputs.
pub fn layer_distance(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    let (na, nb) = (a.dims4()?.0, b.dims4()?.0);
    if nb == 0 || na % nb != 0 || a.dims()[1..] != b.dims()[1..] || a.dtype() != b.dtype() {
        return Err(input_err(
            "perceptual features",
            format!(
                "prediction {:?} ({:?}) is not k groups of the target {:?} ({:?})",
                a.dims(),
                a.dtype(),
                b.dims(),
                b.dtype()
            ),
        ));
    }
    let groups = na / nb;
    if ours(a) && ours(b) {
        return Ok(a
            .contiguous()?
            .apply_op2(&b.contiguous()?, LayerDistance { groups })?);
    }
    layer_distance_portable(a, b)
}

/// [`layer_distance`] from candle ops (any device).
pub fn layer_distance_portable(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    let (na, nb) = (a.dims4()?.0, b.dims4()?.0);
    if nb == 0 || na % nb != 0 || a.dims()[1..] != b.dims()[1..] {
        return Err(input_err(
            "perceptual features",
            format!(
                "prediction {:?} is not k groups of the target {:?}",
                a.dims(),
                b.dims()
            ),
        ));
    }
    let k = na / nb;
    let unit = |f: &Tensor| -> candle_core::Result<Tensor> {
        let norm = (f.sqr()?.sum_keepdim(1)? + NORM_SQRT_EPS)?.sqrt()?;
        f.broadcast_div(&(norm + NORM_EPS)?)
    };
    let mut shape = vec![k];
    shape.extend_from_slice(b.dims());
    let d = unit(a)?
        .reshape(shape)?
        .broadcast_sub(&unit(b)?.unsqueeze(0)?)?;
    // `sign` carries no gradient in candle, so `d * sign(d)` differentiates as sign(d).
    let abs = d.mul(&d.sign()?)?;
    // Mean over (k, B, H, W) of the channel sums, times k = the sum of the k group means.
    Ok((abs.sum_keepdim(2)?.mean_all()? * k as f64)?)
}

#[derive(Debug, Clone, Copy)]
struct LayerDistance {
    groups: usize,
}

/// Geometry: `a` images, `b` images, channels, positions per image.
#[derive(Debug, Clone, Copy)]
struct DistGeom {
    na: usize,
    nb: usize,
    c: usize,
    p: usize,
}

impl DistGeom {
    fn new(la: &Layout, lb: &Layout, groups: usize) -> candle_core::Result<Self> {
        match (la.dims(), lb.dims()) {
            (&[na, c, h, w], &[nb, cb, hb, wb])
                if nb > 0 && na == groups * nb && (c, h, w) == (cb, hb, wb) =>
            {
                Ok(Self {
                    na,
                    nb,
                    c,
                    p: h * w,
                })
            }
            (a, b) => candle_core::bail!("perceptual distance: bad shapes {a:?} and {b:?}"),
        }
    }
}

/// Per position of a chunk: `1 / (sqrt(sum_c f^2 + 1e-20) + 1e-10)` and the root itself.
fn inv_norms<T: Float>(img: &[T], g: DistGeom, p0: usize, len: usize) -> (Vec<f64>, Vec<f64>) {
    let mut sq = vec![0.0f64; len];
    for c in 0..g.c {
        let row = &img[c * g.p + p0..c * g.p + p0 + len];
        for (s, &v) in sq.iter_mut().zip(row) {
            let v = v.to_f64();
            *s += v * v;
        }
    }
    let root: Vec<f64> = sq.iter().map(|s| (s + NORM_SQRT_EPS).sqrt()).collect();
    let inv = root.iter().map(|r| 1.0 / (r + NORM_EPS)).collect();
    (inv, root)
}

fn sign(d: f64) -> f64 {
    if d > 0.0 {
        1.0
    } else if d < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// Sum over all `a` positions and channels of `|a/|a| - b/|b||` (f64).
fn dist_fwd<T: Float>(a: &[T], b: &[T], g: DistGeom) -> f64 {
    let chunks = g.p.div_ceil(POS_CHUNK);
    (0..g.na * chunks)
        .into_par_iter()
        .map(|task| {
            let (n, ci) = (task / chunks, task % chunks);
            let p0 = ci * POS_CHUNK;
            let len = POS_CHUNK.min(g.p - p0);
            let ai = &a[n * g.c * g.p..(n + 1) * g.c * g.p];
            let m = n % g.nb;
            let bi = &b[m * g.c * g.p..(m + 1) * g.c * g.p];
            let (ia, _) = inv_norms(ai, g, p0, len);
            let (ib, _) = inv_norms(bi, g, p0, len);
            let mut s = 0.0;
            for c in 0..g.c {
                let (ra, rb) = (&ai[c * g.p + p0..][..len], &bi[c * g.p + p0..][..len]);
                for j in 0..len {
                    s += (ra[j].to_f64() * ia[j] - rb[j].to_f64() * ib[j]).abs();
                }
            }
            s
        })
        .sum()
}

/// Adds `scale * d/dx sum |x/|x| - y/|y||` for one image pair into `out` (chunk of positions).
fn dist_grad_pair<T: Float>(
    x: &[T],
    y: &[T],
    g: DistGeom,
    p0: usize,
    len: usize,
    scale: f64,
    out: &mut [f64],
) {
    let (ix, rx) = inv_norms(x, g, p0, len);
    let (iy, _) = inv_norms(y, g, p0, len);
    // S = sum_c sign_c x_c per position.
    let mut s_sum = vec![0.0f64; len];
    for c in 0..g.c {
        let (r1, r2) = (&x[c * g.p + p0..][..len], &y[c * g.p + p0..][..len]);
        for j in 0..len {
            let xv = r1[j].to_f64();
            s_sum[j] += sign(xv * ix[j] - r2[j].to_f64() * iy[j]) * xv;
        }
    }
    // d/dx_k = sign_k / (|x| + e) - x_k S / (root (|x| + e)^2), with 1/(|x| + e) = ix.
    let coef: Vec<f64> = (0..len).map(|j| s_sum[j] * ix[j] * ix[j] / rx[j]).collect();
    for c in 0..g.c {
        let (r1, r2) = (&x[c * g.p + p0..][..len], &y[c * g.p + p0..][..len]);
        let o = &mut out[c * len..(c + 1) * len];
        for j in 0..len {
            let xv = r1[j].to_f64();
            let s = sign(xv * ix[j] - r2[j].to_f64() * iy[j]);
            o[j] += scale * (s * ix[j] - xv * coef[j]);
        }
    }
}

/// Gradient with respect to `a` (`wrt_b == false`) or `b`, times `scale`.
fn dist_bwd<T: Float>(a: &[T], b: &[T], g: DistGeom, scale: f64, wrt_b: bool) -> Vec<T> {
    let (n_img, chunks) = (if wrt_b { g.nb } else { g.na }, g.p.div_ceil(POS_CHUNK));
    let img = g.c * g.p;
    let mut out = vec![T::zero(); n_img * img];
    // One task per (image, chunk); each writes only its own positions.
    let tasks: Vec<(usize, usize, Vec<T>)> = (0..n_img * chunks)
        .into_par_iter()
        .map(|task| {
            let (n, ci) = (task / chunks, task % chunks);
            let p0 = ci * POS_CHUNK;
            let len = POS_CHUNK.min(g.p - p0);
            let mut acc = vec![0.0f64; g.c * len];
            if wrt_b {
                let bi = &b[n * img..(n + 1) * img];
                for grp in 0..g.na / g.nb {
                    let m = grp * g.nb + n;
                    dist_grad_pair(bi, &a[m * img..(m + 1) * img], g, p0, len, scale, &mut acc);
                }
            } else {
                let m = n % g.nb;
                dist_grad_pair(
                    &a[n * img..(n + 1) * img],
                    &b[m * img..(m + 1) * img],
                    g,
                    p0,
                    len,
                    scale,
                    &mut acc,
                );
            }
            (n, p0, acc.into_iter().map(T::from_f64).collect())
        })
        .collect();
    for (n, p0, vals) in tasks {
        let len = vals.len() / g.c;
        for c in 0..g.c {
            let dst = &mut out[n * img + c * g.p + p0..][..len];
            dst.copy_from_slice(&vals[c * len..(c + 1) * len]);
        }
    }
    out
}

impl CustomOp2 for LayerDistance {
    fn name(&self) -> &'static str {
        "gagavatar-perceptual-layer-distance"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let g = DistGeom::new(l1, l2, self.groups)?;
        let denom = (g.nb * g.p) as f64;
        let out = match (s1, s2) {
            (CpuStorage::F32(a), CpuStorage::F32(b)) => {
                let s = dist_fwd(
                    contiguous(a, l1, "features")?,
                    contiguous(b, l2, "features")?,
                    g,
                );
                CpuStorage::F32(vec![(s / denom) as f32])
            }
            (CpuStorage::F64(a), CpuStorage::F64(b)) => {
                let s = dist_fwd(
                    contiguous(a, l1, "features")?,
                    contiguous(b, l2, "features")?,
                    g,
                );
                CpuStorage::F64(vec![s / denom])
            }
            (a, b) => candle_core::bail!(
                "perceptual distance: f32 or f64 of one type, got {:?} and {:?}",
                a.dtype(),
                b.dtype()
            ),
        };
        Ok((out, Shape::from(())))
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let g = grad.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        let (_, _, h, w) = b.dims4()?;
        let scale = g / (b.dims()[0] * h * w) as f64;
        let side = |wrt_b: bool| -> candle_core::Result<Tensor> {
            a.apply_op2_no_bwd(
                b,
                &LayerDistanceGrad {
                    groups: self.groups,
                    scale,
                    wrt_b,
                },
            )
        };
        let ga = if a.track_op() {
            Some(side(false)?)
        } else {
            None
        };
        let gb = if b.track_op() {
            Some(side(true)?)
        } else {
            None
        };
        Ok((ga, gb))
    }
}

/// The gradient of [`LayerDistance`] (times `scale`) for `a` or `b`, from `a` (arg 1), `b`.
struct LayerDistanceGrad {
    groups: usize,
    scale: f64,
    wrt_b: bool,
}

impl CustomOp2 for LayerDistanceGrad {
    fn name(&self) -> &'static str {
        "gagavatar-perceptual-layer-distance-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let g = DistGeom::new(l1, l2, self.groups)?;
        let out = match (s1, s2) {
            (CpuStorage::F32(a), CpuStorage::F32(b)) => CpuStorage::F32(dist_bwd(
                contiguous(a, l1, "features")?,
                contiguous(b, l2, "features")?,
                g,
                self.scale,
                self.wrt_b,
            )),
            (CpuStorage::F64(a), CpuStorage::F64(b)) => CpuStorage::F64(dist_bwd(
                contiguous(a, l1, "features")?,
                contiguous(b, l2, "features")?,
                g,
                self.scale,
                self.wrt_b,
            )),
            (a, b) => candle_core::bail!(
                "perceptual distance backward: f32 or f64 of one type, got {:?} and {:?}",
                a.dtype(),
                b.dtype()
            ),
        };
        let shape = if self.wrt_b { l2.shape() } else { l1.shape() };
        Ok((out, shape.clone()))
    }
}
