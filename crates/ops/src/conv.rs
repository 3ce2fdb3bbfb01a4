//! 2-D convolution for NCHW tensors, as a differentiable candle custom op with fast CPU
//! kernels (f32 and f64): Winograd F(4x4, 3x3) for 3x3 stride-1 layers, banded implicit-im2col
//! GEMM for everything else. Other devices and dtypes fall back to candle's `conv2d`.

mod bf16;
pub use bf16::Bf16Conv;
pub(crate) mod elem;
pub use elem::{active_simd_level, limit_simd};
mod geom;
pub use geom::Conv2dSpec;
use geom::Geom;

use crate::storage::{contiguous, contiguous_f32};
mod im2col;
#[cfg(target_arch = "x86_64")]
mod wino_x86;
mod winograd;
pub use winograd::WinogradCache;

use candle_core::backend::BackendStorage;
use candle_core::{
    bail, CpuStorage, CustomOp1, CustomOp2, CustomOp3, DType, Layout, Result, Shape, Tensor,
    TensorId,
};
use rayon::prelude::*;

/// Which kernel runs a convolution. The network uses [`ConvAlgo::Auto`]; the others exist so
/// tests and benchmarks can compare the paths on the same shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvAlgo {
    /// Winograd where it pays off, banded GEMM otherwise (overridable, see [`conv2d`]).
    Auto,
    /// Banded implicit-im2col GEMM (any kernel, stride, padding).
    Gemm,
    /// Winograd F(4x4, 3x3); only for 3x3 kernels with stride 1 (an error otherwise).
    Winograd,
    /// candle's own `conv2d` (im2col over the whole image), the reference.
    Candle,
}

/// `x` [B, Cin, H, W], `w` [Cout, Cin, kh, kw], optional `bias` [Cout] -> [B, Cout, OH, OW].
///
/// The environment variable `GAGAVATAR_CONV` (`candle`, `gemm` or `winograd`: Winograd where
/// it applies, GEMM elsewhere) replaces the automatic choice everywhere, for A/B comparisons of
/// whole-model runs.
pub fn conv2d(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, spec: Conv2dSpec) -> Result<Tensor> {
    conv2d_with_algo(x, w, bias, spec, ConvAlgo::Auto)
}

/// [`conv2d`] with an explicit kernel choice (for tests and benchmarks).
pub fn conv2d_with_algo(
    x: &Tensor,
    w: &Tensor,
    bias: Option<&Tensor>,
    spec: Conv2dSpec,
    algo: ConvAlgo,
) -> Result<Tensor> {
    let g = Geom::new(x.dims(), w.dims(), spec)?;
    if x.dtype() != w.dtype() {
        bail!(
            "conv2d: input is {:?} but weight is {:?}",
            x.dtype(),
            w.dtype()
        );
    }
    if let Some(b) = bias {
        if b.dims() != [g.cout] {
            bail!(
                "conv2d: bias must be [{}] for weight {:?}, got {:?}",
                g.cout,
                w.dims(),
                b.dims()
            );
        }
        if b.dtype() != x.dtype() {
            bail!(
                "conv2d: bias is {:?} but input is {:?}",
                b.dtype(),
                x.dtype()
            );
        }
    }
    let algo = match (algo, env_algo()) {
        // The override asks for Winograd wherever it applies, not for errors elsewhere.
        (ConvAlgo::Auto, Some(ConvAlgo::Winograd)) if !winograd::eligible(&g) => ConvAlgo::Gemm,
        (ConvAlgo::Auto, Some(a)) => a,
        (a, _) => a,
    };
    if algo == ConvAlgo::Winograd && !winograd::eligible(&g) {
        bail!(
            "conv2d: Winograd needs a 3x3 kernel with stride 1, got {:?} stride {}",
            w.dims(),
            spec.stride
        );
    }
    let ours = algo != ConvAlgo::Candle
        && x.device().is_cpu()
        && matches!(x.dtype(), DType::F32 | DType::F64);
    if !ours {
        let y = x.conv2d(w, spec.padding, spec.stride, 1, 1)?;
        return match bias {
            Some(b) => y.broadcast_add(&b.reshape((1, g.cout, 1, 1))?),
            None => Ok(y),
        };
    }
    let op = ConvOp { spec, algo };
    let (x, w) = (x.contiguous()?, w.contiguous()?);
    match bias {
        Some(b) => x.apply_op3(&w, &b.contiguous()?, op),
        None => x.apply_op2(&w, op),
    }
}

/// `GAGAVATAR_CONV`, read once.
fn env_algo() -> Option<ConvAlgo> {
    use std::sync::OnceLock;
    static ALGO: OnceLock<Option<ConvAlgo>> = OnceLock::new();
    *ALGO.get_or_init(|| {
        match std::env::var("GAGAVATAR_CONV")
            .ok()?
            .to_ascii_lowercase()
            .as_str()
        {
            "candle" => Some(ConvAlgo::Candle),
            "gemm" => Some(ConvAlgo::Gemm),
            "winograd" => Some(ConvAlgo::Winograd),
            _ => None,
        }
    })
}

/// Winograd pays off from about this many 4x4 output tiles per image (weight transform and
/// per-GEMM overheads amortised; measured with examples/conv_probe: at 100 tiles of 256
/// channels both paths tie, at 64 tiles of 512 channels the GEMM path is 1.5x faster, at 256
/// tiles Winograd is 2x faster) and this many input and output channels (below, the tile
/// transforms cost more than the multiplies they save). Per image, not per batch, so that an
/// image gets the same kernel, hence the same rounding, alone and in a batch.
const WINOGRAD_MIN_TILES: usize = 128;
const WINOGRAD_MIN_CHANNELS: usize = 8;
/// [`WINOGRAD_MIN_TILES`] when the weight's transform is kept ([`conv2d_fixed`]): with no
/// transform per call Winograd also wins on 32x32 images (64 tiles; the release renderer's
/// 512-channel 32x32 layers, 24.5 -> ~10 ms each), not yet on 16x16 (16 tiles). Measured on
/// the release renderer with `bench model`: 128 -> 485 ms, 64 -> 420-429 ms, 16 -> 437 ms.
const WINOGRAD_MIN_TILES_KEPT: usize = 64;

impl Bf16Conv {
    /// `x` [B, cin, H, W] f32 on the CPU -> [B, cout, OH, OW]: bf16 products where the layer
    /// runs the im2col GEMM, the f32 Winograd op (same weight tensor) where it runs Winograd.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let g = Geom::new(x.dims(), &self.dims, self.spec)?;
        if use_kept_winograd(&g) {
            conv2d_fixed(
                x,
                &self.weight,
                None,
                self.bias.as_ref(),
                self.spec,
                &self.wino,
            )
        } else {
            self.gemm_forward(x)
        }
    }

    /// `conv2d(x, weight * scale[co, ci], bias)` (a modulated weight, `scale` [cout, cin]): the
    /// kept Winograd transform scaled per call where the layer runs Winograd, a freshly packed
    /// scaled weight for the bf16 GEMM elsewhere. The layer's own bias is not used.
    pub fn forward_scaled(
        &self,
        x: &Tensor,
        scale: &Tensor,
        bias: Option<&Tensor>,
    ) -> Result<Tensor> {
        let g = Geom::new(x.dims(), &self.dims, self.spec)?;
        if use_kept_winograd(&g) {
            conv2d_fixed(x, &self.weight, Some(scale), bias, self.spec, &self.wino)
        } else {
            let w = self
                .weight
                .broadcast_mul(&scale.reshape((g.cout, g.cin, 1, 1))?)?;
            Bf16Conv::new(&w, bias, self.spec)?.gemm_forward(x)
        }
    }
}

/// The automatic choice of a layer whose Winograd transform is kept.
fn use_kept_winograd(g: &Geom) -> bool {
    winograd_pays_off(g, WINOGRAD_MIN_TILES_KEPT)
}

fn use_winograd(g: &Geom, algo: ConvAlgo) -> bool {
    match algo {
        ConvAlgo::Winograd => true,
        ConvAlgo::Gemm | ConvAlgo::Candle => false,
        ConvAlgo::Auto => winograd_pays_off(g, WINOGRAD_MIN_TILES),
    }
}

/// The automatic choice: a 3x3 stride-1 layer with `min_tiles` 4x4 output tiles per image and
/// enough channels.
fn winograd_pays_off(g: &Geom, min_tiles: usize) -> bool {
    winograd::eligible(g)
        && g.oh.div_ceil(4) * g.ow.div_ceil(4) >= min_tiles
        && g.cin.min(g.cout) >= WINOGRAD_MIN_CHANNELS
}

fn forward_impl<T: elem::Elem>(
    x: &[T],
    w: &[T],
    bias: Option<&[T]>,
    g: &Geom,
    algo: ConvAlgo,
) -> Vec<T> {
    let mut y = elem::alloc_output(g.b * g.cout * g.oh * g.ow);
    if use_winograd(g, algo) && winograd::eligible(g) {
        let u = winograd::transform_weights(w, g.cout, g.cin);
        winograd::forward(x, &u, bias, g, &mut y);
    } else {
        im2col::forward(x, w, bias, g, &mut y);
    }
    y
}

/// Inference convolution with a fixed weight whose filters may be scaled:
/// `conv2d(x, w * scale[co, ci], bias)`, `scale` [Cout, Cin] (StyleGAN2's modulated weight,
/// per image). Where the layer runs Winograd the weight's transform comes from `cache` and is
/// scaled in the transformed domain (`G (s g) G^T = s G g G^T`: 36 multiplies per filter instead
/// of a transform), elsewhere the scaled weight is formed and convolved. Tracked inputs or a
/// trainable weight take the differentiable path ([`conv2d`]) instead, so training is unchanged.
pub fn conv2d_fixed(
    x: &Tensor,
    w: &Tensor,
    scale: Option<&Tensor>,
    bias: Option<&Tensor>,
    spec: Conv2dSpec,
    cache: &WinogradCache,
) -> Result<Tensor> {
    let g = Geom::new(x.dims(), w.dims(), spec)?;
    if let Some(s) = scale {
        if s.dims() != [g.cout, g.cin] {
            bail!(
                "conv2d: filter scale must be [{}, {}] for weight {:?}, got {:?}",
                g.cout,
                g.cin,
                w.dims(),
                s.dims()
            );
        }
    }
    let scaled = |w: &Tensor| -> Result<Tensor> {
        match scale {
            Some(s) => w.broadcast_mul(&s.reshape((g.cout, g.cin, 1, 1))?),
            None => Ok(w.clone()),
        }
    };
    let tracked = x.track_op()
        || w.track_op()
        || w.is_variable()
        || scale.is_some_and(|s| s.track_op())
        || bias.is_some_and(|b| b.track_op());
    let winograd = match env_algo() {
        Some(ConvAlgo::Winograd) => winograd::eligible(&g),
        Some(_) => false,
        None => use_kept_winograd(&g),
    };
    let cpu_f32 = x.device().is_cpu() && x.dtype() == DType::F32 && w.dtype() == DType::F32;
    if tracked || !winograd || !cpu_f32 {
        return conv2d(x, &scaled(w)?, bias, spec);
    }
    let op = FixedConvOp {
        spec,
        cache: cache.clone(),
        weight: w.id(),
        scale: match scale {
            Some(s) => Some(s.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()?),
            None => None,
        },
    };
    let (x, w) = (x.contiguous()?, w.contiguous()?);
    match bias {
        Some(b) => x.apply_op3_no_bwd(&w, &b.to_dtype(DType::F32)?.contiguous()?, &op),
        None => x.apply_op2_no_bwd(&w, &op),
    }
}

/// [`conv2d_fixed`]'s Winograd run (f32, CPU, inference only).
struct FixedConvOp {
    spec: Conv2dSpec,
    cache: WinogradCache,
    weight: TensorId,
    scale: Option<Vec<f32>>,
}

impl FixedConvOp {
    fn run(&self, x: &[f32], w: &[f32], bias: Option<&[f32]>, g: &Geom) -> Vec<f32> {
        let base = self.cache.transform(self.weight, w, g);
        let mut y = elem::alloc_output(g.b * g.cout * g.oh * g.ow);
        match &self.scale {
            Some(s) => {
                let mut u = elem::alloc_output::<f32>(base.len());
                let slab = g.cout * g.cin;
                u.par_chunks_mut(slab.max(1))
                    .zip(base.par_chunks(slab.max(1)))
                    .for_each(|(dst, src)| {
                        for ((d, &b), &f) in dst.iter_mut().zip(src).zip(s) {
                            *d = b * f;
                        }
                    });
                winograd::forward(x, &u, bias, g, &mut y);
            }
            None => winograd::forward(x, &base, bias, g, &mut y),
        }
        y
    }
}

impl CustomOp2 for FixedConvOp {
    fn name(&self) -> &'static str {
        "gagavatar-conv2d-fixed"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = Geom::new(l1.dims(), l2.dims(), self.spec)?;
        let x = contiguous_f32(s1, l1, "conv2d", "input")?;
        let w = contiguous_f32(s2, l2, "conv2d", "weight")?;
        Ok((CpuStorage::F32(self.run(x, w, None, &g)), g.out_shape()))
    }
}

impl CustomOp3 for FixedConvOp {
    fn name(&self) -> &'static str {
        "gagavatar-conv2d-fixed-bias"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = Geom::new(l1.dims(), l2.dims(), self.spec)?;
        let x = contiguous_f32(s1, l1, "conv2d", "input")?;
        let w = contiguous_f32(s2, l2, "conv2d", "weight")?;
        let b = contiguous_f32(s3, l3, "conv2d", "bias")?;
        if b.len() != g.cout {
            bail!("conv2d: bias must be [{}], got {:?}", g.cout, l3.dims());
        }
        Ok((CpuStorage::F32(self.run(x, w, Some(b), &g)), g.out_shape()))
    }
}

/// `w` [cout, cin, kh, kw] -> [cin, cout, kh, kw] with both spatial axes reversed.
fn flip_transpose<T: elem::Elem>(w: &[T], g: &Geom) -> Vec<T> {
    let khw = g.kh * g.kw;
    let mut out = vec![T::ZERO; w.len()];
    for co in 0..g.cout {
        for ci in 0..g.cin {
            let src = &w[(co * g.cin + ci) * khw..][..khw];
            let dst = &mut out[(ci * g.cout + co) * khw..][..khw];
            for (d, s) in dst.iter_mut().zip(src.iter().rev()) {
                *d = *s;
            }
        }
    }
    out
}

/// Runs `f` on the contiguous f32 or f64 slices of two storages.
macro_rules! with_float_slices {
    ($name:literal, ($a:expr, $la:expr), ($b:expr, $lb:expr), |$sa:ident, $sb:ident| $body:expr) => {
        match ($a, $b) {
            (CpuStorage::F32(a), CpuStorage::F32(b)) => {
                let ($sa, $sb) = (
                    contiguous(a, $la, "conv2d", $name)?,
                    contiguous(b, $lb, "conv2d", $name)?,
                );
                CpuStorage::F32($body)
            }
            (CpuStorage::F64(a), CpuStorage::F64(b)) => {
                let ($sa, $sb) = (
                    contiguous(a, $la, "conv2d", $name)?,
                    contiguous(b, $lb, "conv2d", $name)?,
                );
                CpuStorage::F64($body)
            }
            (a, b) => bail!(
                "{}: needs matching f32 or f64 operands, got {:?} and {:?}",
                $name,
                a.dtype(),
                b.dtype()
            ),
        }
    };
}

#[derive(Debug, Clone, Copy)]
struct ConvOp {
    spec: Conv2dSpec,
    algo: ConvAlgo,
}

impl ConvOp {
    fn backward(
        &self,
        x: &Tensor,
        w: &Tensor,
        gy: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let gy = gy.contiguous()?;
        let gx = if x.track_op() {
            let (_, _, h, wd) = x.dims4()?;
            Some(gy.apply_op2_no_bwd(
                w,
                &GradInputOp {
                    op: *self,
                    h,
                    w: wd,
                },
            )?)
        } else {
            None
        };
        let gw = if w.track_op() {
            let (_, _, kh, kw) = w.dims4()?;
            Some(x.apply_op2_no_bwd(&gy, &GradWeightOp { op: *self, kh, kw })?)
        } else {
            None
        };
        Ok((gx, gw))
    }
}

impl CustomOp2 for ConvOp {
    fn name(&self) -> &'static str {
        "gagavatar-conv2d"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = Geom::new(l1.dims(), l2.dims(), self.spec)?;
        let y = with_float_slices!("conv2d", (s1, l1), (s2, l2), |x, w| forward_impl(
            x, w, None, &g, self.algo
        ));
        Ok((y, g.out_shape()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _y: &Tensor,
        gy: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        self.backward(x, w, gy)
    }
}

impl CustomOp3 for ConvOp {
    fn name(&self) -> &'static str {
        "gagavatar-conv2d-bias"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = Geom::new(l1.dims(), l2.dims(), self.spec)?;
        if l3.dims() != [g.cout] {
            bail!("conv2d: bias must be [{}], got {:?}", g.cout, l3.dims());
        }
        let y = match (s1, s2, s3) {
            (CpuStorage::F32(x), CpuStorage::F32(w), CpuStorage::F32(b)) => {
                let (x, w, b) = (
                    contiguous(x, l1, "conv2d", "input")?,
                    contiguous(w, l2, "conv2d", "weight")?,
                    contiguous(b, l3, "conv2d", "bias")?,
                );
                CpuStorage::F32(forward_impl(x, w, Some(b), &g, self.algo))
            }
            (CpuStorage::F64(x), CpuStorage::F64(w), CpuStorage::F64(b)) => {
                let (x, w, b) = (
                    contiguous(x, l1, "conv2d", "input")?,
                    contiguous(w, l2, "conv2d", "weight")?,
                    contiguous(b, l3, "conv2d", "bias")?,
                );
                CpuStorage::F64(forward_impl(x, w, Some(b), &g, self.algo))
            }
            (x, w, b) => bail!(
                "conv2d: needs f32 or f64 operands of one type, got {:?}, {:?}, {:?}",
                x.dtype(),
                w.dtype(),
                b.dtype()
            ),
        };
        Ok((y, g.out_shape()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _y: &Tensor,
        gy: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (gx, gw) = self.backward(x, w, gy)?;
        let gb = if b.track_op() {
            Some(gy.contiguous()?.apply_op1_no_bwd(&GradBiasOp)?)
        } else {
            None
        };
        Ok((gx, gw, gb))
    }
}

/// `dL/dx` from `dL/dy` (arg 1) and `w` (arg 2); `h`, `w` are the input's spatial size.
struct GradInputOp {
    op: ConvOp,
    h: usize,
    w: usize,
}

impl GradInputOp {
    fn run<T: elem::Elem>(&self, gy: &[T], w: &[T], g: &Geom) -> Vec<T> {
        match g.transposed() {
            Some(gt) => forward_impl(gy, &flip_transpose(w, g), None, &gt, self.op.algo),
            None => {
                let mut gx = elem::alloc_output(g.b * g.cin * g.h * g.w);
                im2col::grad_input_col2im(gy, w, g, &mut gx);
                gx
            }
        }
    }
}

impl CustomOp2 for GradInputOp {
    fn name(&self) -> &'static str {
        "gagavatar-conv2d-grad-input"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (&[b, cout, oh, ow], &[wcout, cin, _, _]) = (l1.dims(), l2.dims()) else {
            bail!(
                "conv2d backward: bad gradient {:?} or weight {:?}",
                l1.dims(),
                l2.dims()
            );
        };
        let g = Geom::new(&[b, cin, self.h, self.w], l2.dims(), self.op.spec)?;
        if (wcout, oh, ow) != (g.cout, g.oh, g.ow) || cout != g.cout {
            bail!(
                "conv2d backward: gradient {:?} does not match the output of weight {:?}",
                l1.dims(),
                l2.dims()
            );
        }
        let gx = with_float_slices!("conv2d backward", (s1, l1), (s2, l2), |gy, w| self
            .run(gy, w, &g));
        Ok((gx, Shape::from((b, cin, self.h, self.w))))
    }
}

/// `dL/dw` from `x` (arg 1) and `dL/dy` (arg 2).
struct GradWeightOp {
    op: ConvOp,
    kh: usize,
    kw: usize,
}

impl GradWeightOp {
    fn run<T: elem::Elem>(&self, x: &[T], gy: &[T], g: &Geom) -> Vec<T> {
        if use_winograd(g, self.op.algo) && winograd::eligible(g) {
            winograd::grad_weight(x, gy, g)
        } else {
            im2col::grad_weight(x, gy, g)
        }
    }
}

impl CustomOp2 for GradWeightOp {
    fn name(&self) -> &'static str {
        "gagavatar-conv2d-grad-weight"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (&[_, cin, _, _], &[_, cout, _, _]) = (l1.dims(), l2.dims()) else {
            bail!(
                "conv2d backward: bad input {:?} or gradient {:?}",
                l1.dims(),
                l2.dims()
            );
        };
        let g = Geom::new(l1.dims(), &[cout, cin, self.kh, self.kw], self.op.spec)?;
        if l2.dims() != [g.b, g.cout, g.oh, g.ow] {
            bail!(
                "conv2d backward: gradient {:?} does not match input {:?}",
                l2.dims(),
                l1.dims()
            );
        }
        let gw = with_float_slices!("conv2d backward", (s1, l1), (s2, l2), |x, gy| self
            .run(x, gy, &g));
        Ok((gw, Shape::from((cout, cin, self.kh, self.kw))))
    }
}

/// `dL/dbias`: per-channel sums of `dL/dy` (candle's reduction over dims (0, 2, 3) walks the
/// tensor with strided indexing, several times slower than these contiguous row sums).
struct GradBiasOp;

fn channel_sums<T: elem::Elem>(gy: &[T], b: usize, c: usize) -> Vec<T> {
    use rayon::prelude::*;
    let plane = gy.len() / (b * c).max(1);
    (0..c)
        .into_par_iter()
        .map(|ci| {
            let mut acc = T::ZERO;
            for bi in 0..b {
                acc += elem::sum(&gy[(bi * c + ci) * plane..(bi * c + ci + 1) * plane]);
            }
            acc
        })
        .collect()
}

impl CustomOp1 for GradBiasOp {
    fn name(&self) -> &'static str {
        "gagavatar-conv2d-grad-bias"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let &[b, c, _, _] = l.dims() else {
            bail!("conv2d backward: gradient must be 4-D, got {:?}", l.dims());
        };
        let out = match s {
            CpuStorage::F32(v) => {
                CpuStorage::F32(channel_sums(contiguous(v, l, "conv2d", "gradient")?, b, c))
            }
            CpuStorage::F64(v) => {
                CpuStorage::F64(channel_sums(contiguous(v, l, "conv2d", "gradient")?, b, c))
            }
            s => bail!(
                "conv2d backward: needs an f32 or f64 gradient, got {:?}",
                s.dtype()
            ),
        };
        Ok((out, Shape::from(c)))
    }
}
