//! The StyleGAN2 renderer's element-wise epilogues (leaky ReLU with slope 0.2, residual add,
//! SFT modulation, noise injection + leaky ReLU), fused and in place.
//!
//! Without gradient tracking (inference) they overwrite their first
//! operand in place: every call site passes a tensor it has just created and owns alone, and
//! at 512x512 each avoided allocation saves a pass over tens of MB plus its page faults. When
//! any operand tracks gradients they are the plain candle expressions, so autograd sees the
//! usual graph.

use candle_core::{
    bail, CpuStorage, DType, InplaceOp1, InplaceOp2, InplaceOp3, Layout, Result, Tensor,
};
use rayon::prelude::*;

/// Elements per rayon task: enough to amortise scheduling, small enough to balance.
const CHUNK: usize = 1 << 15;

fn in_place(dst: &Tensor, srcs: &[&Tensor]) -> bool {
    let ok = |t: &Tensor| {
        !t.track_op()
            && t.device().is_cpu()
            && t.is_contiguous()
            && t.dtype() == dst.dtype()
            && matches!(t.dtype(), DType::F32 | DType::F64)
    };
    ok(dst) && srcs.iter().all(|t| ok(t))
}

/// The slope of the renderer's leaky ReLUs.
pub const SLOPE: f64 = 0.2;

/// `max(x, 0.2 x)` from candle ops (differentiable).
fn leaky_relu(x: &Tensor) -> Result<Tensor> {
    x.maximum(&(x * SLOPE)?)
}

/// Leaky ReLU with slope 0.2.
pub fn lrelu(x: Tensor) -> Result<Tensor> {
    if in_place(&x, &[]) {
        x.inplace_op1(&LeakyRelu)?;
        Ok(x)
    } else {
        leaky_relu(&x)
    }
}

/// `x + y`, same shapes.
pub fn add(x: Tensor, y: &Tensor) -> Result<Tensor> {
    if x.dims() == y.dims() && in_place(&x, &[y]) {
        x.inplace_op2(y, &AddInto)?;
        Ok(x)
    } else {
        x + y
    }
}

/// SFT: `x * scale + shift`, same shapes.
pub fn sft(x: Tensor, scale: &Tensor, shift: &Tensor) -> Result<Tensor> {
    if x.dims() != scale.dims() || x.dims() != shift.dims() {
        bail!(
            "SFT: scale {:?} / shift {:?} do not match the features {:?}",
            scale.dims(),
            shift.dims(),
            x.dims()
        );
    }
    if in_place(&x, &[scale, shift]) {
        x.inplace_op3(scale, shift, &Sft)?;
        Ok(x)
    } else {
        (x * scale)? + shift
    }
}

/// StyleConv epilogue: `lrelu(y + weight * noise)`, `y` [B, C, H, W], `noise` [1 or B, 1,
/// H, W] (shared by the channels), `weight` [1].
pub fn noise_lrelu(y: Tensor, noise: &Tensor, weight: &Tensor) -> Result<Tensor> {
    let (b, _, h, w) = y.dims4()?;
    let (nb, nc, nh, nw) = noise.dims4()?;
    if nc != 1 || nh != h || nw != w || (nb != 1 && nb != b) {
        bail!(
            "noise {:?} does not fit features {:?}",
            noise.dims(),
            y.dims()
        );
    }
    if weight.elem_count() != 1 {
        bail!("noise weight must hold one value, got {:?}", weight.dims());
    }
    if in_place(&y, &[noise, weight]) {
        y.inplace_op3(noise, weight, &NoiseLeakyRelu)?;
        Ok(y)
    } else {
        let n = noise.broadcast_mul(&weight.reshape((1, 1, 1, 1))?)?;
        leaky_relu(&y.broadcast_add(&n)?)
    }
}

trait Elem:
    Copy + Send + Sync + PartialOrd + std::ops::Add<Output = Self> + std::ops::Mul<Output = Self>
{
    const SLOPE: Self;
}
impl Elem for f32 {
    const SLOPE: Self = 0.2;
}
impl Elem for f64 {
    const SLOPE: Self = 0.2;
}

#[inline(always)]
fn leaky<T: Elem>(v: T) -> T {
    // As `max(v, 0.2 v)`, the expression of the tracked path.
    let s = v * T::SLOPE;
    if v > s {
        v
    } else {
        s
    }
}

fn slice<'a, T>(v: &'a [T], l: &Layout) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => bail!("fused op needs contiguous operands"),
    }
}

fn slice_mut<'a, T>(v: &'a mut [T], l: &Layout) -> Result<&'a mut [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&mut v[a..b]),
        None => bail!("fused op needs contiguous operands"),
    }
}

struct LeakyRelu;
impl InplaceOp1 for LeakyRelu {
    fn name(&self) -> &'static str {
        "leaky-relu-inplace"
    }
    fn cpu_fwd(&self, s: &mut CpuStorage, l: &Layout) -> Result<()> {
        fn run<T: Elem>(d: &mut [T]) {
            d.par_chunks_mut(CHUNK)
                .for_each(|c| c.iter_mut().for_each(|v| *v = leaky(*v)));
        }
        match s {
            CpuStorage::F32(v) => run(slice_mut(v, l)?),
            CpuStorage::F64(v) => run(slice_mut(v, l)?),
            _ => bail!("leaky-relu-inplace: f32 and f64 only"),
        }
        Ok(())
    }
}

struct AddInto;
impl InplaceOp2 for AddInto {
    fn name(&self) -> &'static str {
        "add-inplace"
    }
    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<()> {
        fn run<T: Elem>(d: &mut [T], a: &[T]) {
            d.par_chunks_mut(CHUNK)
                .zip(a.par_chunks(CHUNK))
                .for_each(|(d, a)| d.iter_mut().zip(a).for_each(|(d, &a)| *d = *d + a));
        }
        match (s1, s2) {
            (CpuStorage::F32(d), CpuStorage::F32(a)) => run(slice_mut(d, l1)?, slice(a, l2)?),
            (CpuStorage::F64(d), CpuStorage::F64(a)) => run(slice_mut(d, l1)?, slice(a, l2)?),
            _ => bail!("add-inplace: matching f32 or f64 operands only"),
        }
        Ok(())
    }
}

struct Sft;
impl InplaceOp3 for Sft {
    fn name(&self) -> &'static str {
        "sft-inplace"
    }
    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<()> {
        fn run<T: Elem>(d: &mut [T], scale: &[T], shift: &[T]) {
            d.par_chunks_mut(CHUNK)
                .zip(scale.par_chunks(CHUNK).zip(shift.par_chunks(CHUNK)))
                .for_each(|(d, (a, b))| {
                    for ((d, &a), &b) in d.iter_mut().zip(a).zip(b) {
                        *d = *d * a + b;
                    }
                });
        }
        match (s1, s2, s3) {
            (CpuStorage::F32(d), CpuStorage::F32(a), CpuStorage::F32(b)) => {
                run(slice_mut(d, l1)?, slice(a, l2)?, slice(b, l3)?)
            }
            (CpuStorage::F64(d), CpuStorage::F64(a), CpuStorage::F64(b)) => {
                run(slice_mut(d, l1)?, slice(a, l2)?, slice(b, l3)?)
            }
            _ => bail!("sft-inplace: matching f32 or f64 operands only"),
        }
        Ok(())
    }
}

struct NoiseLeakyRelu;
impl InplaceOp3 for NoiseLeakyRelu {
    fn name(&self) -> &'static str {
        "noise-leaky-relu-inplace"
    }
    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<()> {
        let (b, c, h, w) = l1.shape().dims4()?;
        let plane = h * w;
        let noise_batch = l2.shape().dims()[0];
        fn run<T: Elem>(
            d: &mut [T],
            noise: &[T],
            weight: T,
            c: usize,
            plane: usize,
            per_sample: bool,
        ) {
            d.par_chunks_mut(plane).enumerate().for_each(|(p, d)| {
                let n = if per_sample {
                    &noise[(p / c) * plane..][..plane]
                } else {
                    &noise[..plane]
                };
                for (d, &n) in d.iter_mut().zip(n) {
                    *d = leaky(*d + weight * n);
                }
            });
        }
        let per_sample = noise_batch == b && b > 1;
        if plane == 0 || c == 0 {
            return Ok(());
        }
        match (s1, s2, s3) {
            (CpuStorage::F32(d), CpuStorage::F32(n), CpuStorage::F32(wt)) => {
                let wt = slice(wt, l3)?[0];
                run(slice_mut(d, l1)?, slice(n, l2)?, wt, c, plane, per_sample)
            }
            (CpuStorage::F64(d), CpuStorage::F64(n), CpuStorage::F64(wt)) => {
                let wt = slice(wt, l3)?[0];
                run(slice_mut(d, l1)?, slice(n, l2)?, wt, c, plane, per_sample)
            }
            _ => bail!("noise-leaky-relu-inplace: matching f32 or f64 operands only"),
        }
        Ok(())
    }
}
