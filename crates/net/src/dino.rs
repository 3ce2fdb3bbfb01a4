//! The frozen DINOv2 ViT-B/14 of the encoder (`base_model.dino_model.*`, spec section 4) and the
//! source preprocessing that feeds it (spec section 3).
//!
//! The ViT is frozen in the release, so its default forward is inference-only: fused CPU kernels
//! without a backward (layer norm, GELU, in-place softmax; see `rows`) and linear weights copied
//! into a transposed layout at load time. No gradient flows through it or into its weights, which
//! is what "frozen" asks.
//!
//! The small presets have no pretrained backbone, so there the ViT trains. Built from variables
//! (a `VarMap`), it keeps the live weights (views only, so an optimiser's in-place `Var::set`
//! is seen by the next forward) and runs differentiable candle ops wherever a value tracks
//! gradients. The rule is per op: the fused kernels run only when nothing they touch tracks
//! gradients, so a frozen backbone (fixed tensors, untracked input) keeps the fast path.

use candle_core::{
    backend::BackendStorage, bail, CpuStorage, CustomOp1, CustomOp3, DType, InplaceOp1, Layout,
    Result, Shape, Tensor, D,
};
use candle_nn::VarBuilder;
use gagavatar_ops::{resize, ResizeMode};
use rayon::prelude::*;

use crate::config::ModelConfig;

/// DINOv2's LayerNorm epsilon (not PyTorch's default 1e-5).
const LN_EPS: f64 = 1e-6;
/// ImageNet statistics the DINO input is normalised with (spec section 3).
pub const IMAGENET_MEAN: [f64; 3] = [0.485, 0.456, 0.406];
pub const IMAGENET_STD: [f64; 3] = [0.229, 0.224, 0.225];

/// Source image [B, 3, image, image] in [0, 1] -> DINO input [B, 3, dino, dino]: antialiased
/// bilinear resize (512 -> 518 in the release, an upscale, so plain half-pixel bilinear), then
/// ImageNet normalisation. The same tensor is the image pyramid input of the DPT head.
pub fn preprocess(image: &Tensor, cfg: &ModelConfig) -> Result<Tensor> {
    let (_, c, h, w) = image.dims4()?;
    if c != 3 || h != cfg.image_size || w != cfg.image_size {
        bail!(
            "preprocess expects a [B, 3, {s}, {s}] image, got {:?}",
            image.dims(),
            s = cfg.image_size
        );
    }
    let x = resize(image, cfg.dino_size, cfg.dino_size, ResizeMode::Antialias)?;
    let dev = image.device();
    let mean = Tensor::new(&IMAGENET_MEAN, dev)?
        .to_dtype(image.dtype())?
        .reshape((1, 3, 1, 1))?;
    let inv_std = Tensor::new(&IMAGENET_STD.map(|s| 1.0 / s), dev)?
        .to_dtype(image.dtype())?
        .reshape((1, 3, 1, 1))?;
    x.broadcast_sub(&mean)?.broadcast_mul(&inv_std)
}

/// `nn.Linear` on token rows: `x [M, in] -> [M, out]`.
#[derive(Debug, Clone)]
struct Linear {
    weight: LinearWeight,
    bias: Tensor,
}

#[derive(Debug, Clone)]
enum LinearWeight {
    /// `weight^T` [in, out], stored transposed once: the GEMM runs ~15% faster on a row-major
    /// right operand than on the transposed view. A copy, so only for fixed weights.
    Transposed(Tensor),
    /// A trainable `weight` [out, in] as given (a variable): used through a transposed view so
    /// that updates to the variable reach the forward and gradients reach the variable.
    Live(Tensor),
}

impl Linear {
    fn new(vb: VarBuilder, cin: usize, cout: usize) -> Result<Self> {
        Self::from_parts(vb.get((cout, cin), "weight")?, vb.get(cout, "bias")?)
    }

    /// `w` [out, in]: kept as is when it is a variable (or a view of one), else transposed.
    fn from_parts(w: Tensor, bias: Tensor) -> Result<Self> {
        let weight = if w.track_op() {
            LinearWeight::Live(w)
        } else {
            LinearWeight::Transposed(w.t()?.contiguous()?)
        };
        Ok(Self { weight, bias })
    }

    fn is_live(&self) -> bool {
        matches!(self.weight, LinearWeight::Live(_))
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = match &self.weight {
            LinearWeight::Transposed(wt) => x.matmul(wt)?,
            LinearWeight::Live(w) => x.matmul(&w.t()?)?,
        };
        y.broadcast_add(&self.bias)
    }

    /// The checkpoint's `weight` [out, in] (a view, exact for both layouts).
    fn weight(&self) -> Result<Tensor> {
        match &self.weight {
            LinearWeight::Transposed(wt) => wt.t(),
            LinearWeight::Live(w) => Ok(w.clone()),
        }
    }

    fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) -> Result<()> {
        out.push((format!("{prefix}.weight"), self.weight()?));
        out.push((format!("{prefix}.bias"), self.bias.clone()));
        Ok(())
    }
}

#[derive(Debug, Clone)]
struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
}

impl LayerNorm {
    fn new(vb: VarBuilder, dim: usize) -> Result<Self> {
        Ok(Self {
            weight: vb.get(dim, "weight")?,
            bias: vb.get(dim, "bias")?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if x.track_op() || self.weight.track_op() || self.bias.track_op() {
            // Same two-pass arithmetic as the fused op, from ops that have a backward (candle-nn's
            // fused layer norm has none).
            let mean = x.mean_keepdim(D::Minus1)?;
            let centred = x.broadcast_sub(&mean)?;
            let var = centred.sqr()?.mean_keepdim(D::Minus1)?;
            let normed = centred.broadcast_div(&(var + LN_EPS)?.sqrt()?)?;
            return normed
                .broadcast_mul(&self.weight)?
                .broadcast_add(&self.bias);
        }
        x.contiguous()?
            .apply_op3_no_bwd(&self.weight, &self.bias, &LayerNormOp { eps: LN_EPS })
    }

    fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        out.push((format!("{prefix}.weight"), self.weight.clone()));
        out.push((format!("{prefix}.bias"), self.bias.clone()));
    }
}

/// Row-wise layer norm over the last dim with a two-pass (mean, then centred variance) reduction:
/// candle's fused op uses `E[x^2] - E[x]^2` in f32, which cancels badly on the large-magnitude
/// channels of the DINOv2 residual stream.
struct LayerNormOp {
    eps: f64,
}

fn contiguous_slice<'a, T>(x: &'a [T], l: &Layout, what: &str) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&x[a..b]),
        None => bail!("{what}: operand must be contiguous"),
    }
}

impl LayerNormOp {
    fn check(&self, lx: &Layout, w: usize, b: usize) -> Result<usize> {
        let n = lx.dims().last().copied().unwrap_or(0);
        if n == 0 || w != n || b != n {
            bail!(
                "layer norm: input {:?} does not match weight [{w}] / bias [{b}]",
                lx.dims()
            );
        }
        Ok(n)
    }
}

impl CustomOp3 for LayerNormOp {
    fn name(&self) -> &'static str {
        "dino-layer-norm"
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
        const WHAT: &str = "layer norm";
        let storage = match (s1, s2, s3) {
            (CpuStorage::F32(x), CpuStorage::F32(w), CpuStorage::F32(b)) => {
                let x = contiguous_slice(x, l1, WHAT)?;
                let w = contiguous_slice(w, l2, WHAT)?;
                let b = contiguous_slice(b, l3, WHAT)?;
                let n = self.check(l1, w.len(), b.len())?;
                let mut out = vec![0f32; x.len()];
                let eps = self.eps as f32;
                par_rows(x, &mut out, n, |x, o| rows::layer_norm(x, o, n, w, b, eps));
                CpuStorage::F32(out)
            }
            (CpuStorage::F64(x), CpuStorage::F64(w), CpuStorage::F64(b)) => {
                let x = contiguous_slice(x, l1, WHAT)?;
                let w = contiguous_slice(w, l2, WHAT)?;
                let b = contiguous_slice(b, l3, WHAT)?;
                let n = self.check(l1, w.len(), b.len())?;
                let mut out = vec![0f64; x.len()];
                par_rows(x, &mut out, n, |x, o| {
                    for (x, o) in x.chunks_exact(n).zip(o.chunks_exact_mut(n)) {
                        let mean = x.iter().sum::<f64>() / n as f64;
                        let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n as f64;
                        let inv = 1.0 / (var + self.eps).sqrt();
                        for (((o, v), w), b) in o.iter_mut().zip(x).zip(w).zip(b) {
                            *o = (v - mean) * inv * w + b;
                        }
                    }
                });
                CpuStorage::F64(out)
            }
            _ => bail!(
                "layer norm supports f32 or f64 operands of one dtype, got {:?}",
                s1.dtype()
            ),
        };
        Ok((storage, l1.shape().clone()))
    }
}

/// Attention logits computed at once (8 MiB in f32), see [`attend`].
const LOGITS_PER_CHUNK: usize = 1 << 21;

#[derive(Debug, Clone)]
struct Attention {
    qkv: Linear,
    proj: Linear,
    heads: usize,
}

impl Attention {
    /// `x [B, N, C]` -> `[B * N, C]`.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, n, c) = x.dims3()?;
        let (h, d) = (self.heads, c / self.heads);
        let qkv = self
            .qkv
            .forward(&x.reshape((b * n, c))?)?
            .reshape((b, n, 3, h, d))?
            .permute((2, 0, 3, 1, 4))?
            .contiguous()?;
        // Scaling q (N d values) is cheaper than scaling the N x N logits; mathematically equal.
        let q = (qkv.get(0)?.reshape((b * h, n, d))? * (1.0 / (d as f64).sqrt()))?;
        let k = qkv.get(1)?.reshape((b * h, n, d))?;
        let v = qkv.get(2)?.reshape((b * h, n, d))?;
        let fused = !(q.track_op() || k.track_op() || v.track_op())
            && q.dtype() == DType::F32
            && q.device().is_cpu();
        let y = if fused {
            q.apply_op3_no_bwd(&k, &v, &AttentionOp)?
        } else {
            attend(&q, &k, &v, (LOGITS_PER_CHUNK / (n * n)).max(1))?
        };
        let y = y
            .reshape((b, h, n, d))?
            .transpose(1, 2)?
            .contiguous()?
            .reshape((b * n, c))?;
        self.proj.forward(&y)
    }
}

/// `softmax(q k^T) v` over `[heads, N, d]`, `per_chunk` heads at a time: the logits of one
/// chunk (<= 8 MiB in f32 at the release size) stay in the L3 cache between the two GEMMs and
/// the softmax, and the allocator reuses the buffer instead of mapping (and page-faulting)
/// fresh pages for a [B H, N, N] tensor.
fn attend(q: &Tensor, k: &Tensor, v: &Tensor, per_chunk: usize) -> Result<Tensor> {
    let heads = q.dim(0)?;
    let per_chunk = per_chunk.max(1);
    let mut chunks = Vec::with_capacity(heads.div_ceil(per_chunk));
    for start in (0..heads).step_by(per_chunk) {
        let len = per_chunk.min(heads - start);
        let logits = q
            .narrow(0, start, len)?
            .matmul(&k.narrow(0, start, len)?.t()?)?;
        let weights = if logits.track_op() || v.track_op() {
            softmax_tracked(&logits)?
        } else {
            softmax_in_place(&logits)?;
            logits
        };
        chunks.push(weights.matmul(&v.narrow(0, start, len)?)?);
    }
    Tensor::cat(&chunks, 0)
}

/// Query rows per block of the fused attention: one block's logits (128 x 1370 f32, 700 KiB at
/// the release size) stay in the core's L2 cache from the first GEMM through the softmax to the
/// second. Whole-head logits (7.3 MiB) live in L3, where the softmax alone took a third of the
/// attention time.
const ATTN_ROWS: usize = 128;

/// Inference attention `softmax(q k^T) v` over contiguous f32 `[heads, N, d]` (q already
/// scaled), heads in parallel and each head in blocks of [`ATTN_ROWS`] query rows: single-thread
/// GEMMs on an L2-resident logits block and the in-place row softmax between them.
struct AttentionOp;

impl CustomOp3 for AttentionOp {
    fn name(&self) -> &'static str {
        "dino-attention"
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
        let (CpuStorage::F32(q), CpuStorage::F32(k), CpuStorage::F32(v)) = (s1, s2, s3) else {
            bail!("attention: the fused kernel runs in f32");
        };
        let (heads, n, d) = l1.shape().dims3()?;
        if l2.shape() != l1.shape() || l3.shape() != l1.shape() {
            bail!(
                "attention: q {:?}, k {:?} and v {:?} must share one shape",
                l1.dims(),
                l2.dims(),
                l3.dims()
            );
        }
        let q = contiguous_slice(q, l1, "attention q")?;
        let k = contiguous_slice(k, l2, "attention k")?;
        let v = contiguous_slice(v, l3, "attention v")?;
        let mut out = vec![0f32; heads * n * d];
        if n == 0 || d == 0 {
            return Ok((CpuStorage::F32(out), l1.shape().clone()));
        }
        let rows = ATTN_ROWS.min(n);
        out.par_chunks_mut(n * d).enumerate().for_each_init(
            || vec![0f32; rows * n],
            |logits, (h, out_h)| {
                let (qh, kh, vh) = (
                    &q[h * n * d..(h + 1) * n * d],
                    &k[h * n * d..(h + 1) * n * d],
                    &v[h * n * d..(h + 1) * n * d],
                );
                for (b, out_b) in out_h.chunks_mut(rows * d).enumerate() {
                    let r = out_b.len() / d;
                    let lg = &mut logits[..r * n];
                    // SAFETY: every operand is a live slice covering the extents given (q block
                    // r x d, k read as its transpose d x n, logits r x n, v n x d, out r x d);
                    // the destinations do not alias the sources.
                    unsafe {
                        gemm::gemm(
                            r,
                            n,
                            d,
                            lg.as_mut_ptr(),
                            1,
                            n as isize,
                            false,
                            qh[b * rows * d..].as_ptr(),
                            1,
                            d as isize,
                            kh.as_ptr(),
                            d as isize,
                            1,
                            0.0,
                            1.0,
                            false,
                            false,
                            false,
                            gemm::Parallelism::None,
                        );
                    }
                    rows::softmax(lg, n);
                    // SAFETY: as above.
                    unsafe {
                        gemm::gemm(
                            r,
                            d,
                            n,
                            out_b.as_mut_ptr(),
                            1,
                            d as isize,
                            false,
                            lg.as_ptr(),
                            1,
                            n as isize,
                            vh.as_ptr(),
                            1,
                            d as isize,
                            0.0,
                            1.0,
                            false,
                            false,
                            false,
                            gemm::Parallelism::None,
                        );
                    }
                }
            },
        );
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

#[derive(Debug, Clone)]
struct Block {
    norm1: LayerNorm,
    attn: Attention,
    ls1: Tensor,
    norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    ls2: Tensor,
}

impl Block {
    fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        let c = cfg.vit_dim;
        Ok(Self {
            norm1: LayerNorm::new(vb.pp("norm1"), c)?,
            attn: Attention {
                qkv: Linear::new(vb.pp("attn.qkv"), c, 3 * c)?,
                proj: Linear::new(vb.pp("attn.proj"), c, c)?,
                heads: cfg.vit_heads,
            },
            ls1: vb.get(c, "ls1.gamma")?,
            norm2: LayerNorm::new(vb.pp("norm2"), c)?,
            fc1: Linear::new(vb.pp("mlp.fc1"), c, cfg.vit_mlp)?,
            fc2: Linear::new(vb.pp("mlp.fc2"), cfg.vit_mlp, c)?,
            ls2: vb.get(c, "ls2.gamma")?,
        })
    }

    fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) -> Result<()> {
        self.norm1.named(&format!("{prefix}.norm1"), out);
        self.attn.qkv.named(&format!("{prefix}.attn.qkv"), out)?;
        self.attn.proj.named(&format!("{prefix}.attn.proj"), out)?;
        out.push((format!("{prefix}.ls1.gamma"), self.ls1.clone()));
        self.norm2.named(&format!("{prefix}.norm2"), out);
        self.fc1.named(&format!("{prefix}.mlp.fc1"), out)?;
        self.fc2.named(&format!("{prefix}.mlp.fc2"), out)?;
        out.push((format!("{prefix}.ls2.gamma"), self.ls2.clone()));
        Ok(())
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, n, c) = x.dims3()?;
        let a = self.attn.forward(&self.norm1.forward(x)?)?;
        let x = (x + a.broadcast_mul(&self.ls1)?.reshape((b, n, c))?)?;
        let h = self.norm2.forward(&x)?.reshape((b * n, c))?;
        let m = self.fc2.forward(&gelu_erf(&self.fc1.forward(&h)?)?)?;
        x + m.broadcast_mul(&self.ls2)?.reshape((b, n, c))?
    }
}

/// Exact (erf, not tanh) GELU, `x (1 + erf(x / sqrt 2)) / 2`.
fn gelu_erf(x: &Tensor) -> Result<Tensor> {
    if x.track_op() {
        // Spelled out rather than `Tensor::gelu_erf`, whose backward rounds 1/sqrt(2 pi) to six
        // digits; `erf`'s backward is exact.
        let e = (x * std::f64::consts::FRAC_1_SQRT_2)?.erf()?;
        return ((e + 1.0)? * x)? * 0.5;
    }
    x.contiguous()?.apply_op1_no_bwd(&GeluErfOp)
}

/// Softmax over the last dim from ops with a backward. The row maximum is detached: subtracting
/// any per-row constant leaves the softmax and its gradient unchanged, and a detached one keeps
/// the max's own (zero-sum) gradient out of the graph.
fn softmax_tracked(x: &Tensor) -> Result<Tensor> {
    let max = x.max_keepdim(D::Minus1)?.detach();
    let e = x.broadcast_sub(&max)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
}

struct GeluErfOp;

impl CustomOp1 for GeluErfOp {
    fn name(&self) -> &'static str {
        "dino-gelu-erf"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let storage = match s {
            CpuStorage::F32(x) => {
                let x = contiguous_slice(x, l, "gelu")?;
                let mut out = vec![0f32; x.len()];
                par_rows(x, &mut out, 1, rows::gelu_erf);
                CpuStorage::F32(out)
            }
            CpuStorage::F64(x) => {
                let x = contiguous_slice(x, l, "gelu")?;
                let mut out = vec![0f64; x.len()];
                par_rows(x, &mut out, 1, |x, o| {
                    for (o, &v) in o.iter_mut().zip(x) {
                        let e = candle_core::cpu::erf::erf_f64(v * std::f64::consts::FRAC_1_SQRT_2);
                        *o = 0.5 * v * (1.0 + e);
                    }
                });
                CpuStorage::F64(out)
            }
            _ => bail!("gelu supports f32 and f64, got {:?}", s.dtype()),
        };
        Ok((storage, l.shape().clone()))
    }
}

/// Softmax over the last dim (the attention rows), in place: the logits are a fresh tensor
/// nobody else holds, and a second [B H, N, N] buffer would be the largest allocation
/// of the ViT.
fn softmax_in_place(x: &Tensor) -> Result<()> {
    if !x.is_contiguous() {
        bail!("softmax: logits must be contiguous");
    }
    x.inplace_op1(&SoftmaxOp)
}

struct SoftmaxOp;

impl InplaceOp1 for SoftmaxOp {
    fn name(&self) -> &'static str {
        "dino-softmax"
    }

    fn cpu_fwd(&self, s: &mut CpuStorage, l: &Layout) -> Result<()> {
        let n = l.dims().last().copied().unwrap_or(0);
        let Some((o0, o1)) = l.contiguous_offsets() else {
            bail!("softmax: logits must be contiguous");
        };
        if n == 0 {
            bail!("softmax of an empty row: {:?}", l.dims());
        }
        let block = n * (16_384 / n).max(1);
        match s {
            CpuStorage::F32(x) => x[o0..o1]
                .par_chunks_mut(block)
                .for_each(|x| rows::softmax(x, n)),
            CpuStorage::F64(x) => x[o0..o1].par_chunks_mut(block).for_each(|x| {
                for r in x.chunks_exact_mut(n) {
                    let max = r.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    r.iter_mut().for_each(|v| *v = (*v - max).exp());
                    let sum: f64 = r.iter().sum();
                    r.iter_mut().for_each(|v| *v /= sum);
                }
            }),
            _ => bail!("softmax supports f32 and f64, got {:?}", s.dtype()),
        }
        Ok(())
    }
}

/// Runs `f` on blocks of whole rows of `row` elements (about 16k values each) on the rayon pool.
fn par_rows<T: Send + Sync>(
    x: &[T],
    out: &mut [T],
    row: usize,
    f: impl Fn(&[T], &mut [T]) + Send + Sync,
) {
    let block = row * (16_384 / row).max(1);
    out.par_chunks_mut(block)
        .zip(x.par_chunks(block))
        .for_each(|(o, x)| f(x, o));
}

/// f32 row kernels for the ViT, compiled for AVX-512 or AVX2 when the CPU has them (same
/// arithmetic in every version, so the results do not depend on the CPU).
mod rows {
    /// `exp` for `x <= 88`: Cody-Waite reduction by ln 2 and a degree-7 polynomial (Cephes'
    /// `expf` coefficients), about 1 ulp; 0 below the f32 normal range.
    #[inline(always)]
    fn exp(x: f32) -> f32 {
        const LN2_HI: f32 = 0.693_359_4;
        const LN2_LO: f32 = -2.121_944_4e-4;
        let n = (x * std::f32::consts::LOG2_E + 0.5).floor();
        let r = x - n * LN2_HI - n * LN2_LO;
        let p = ((((1.987_569_1e-4 * r + 1.398_2e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
            + 1.666_666_5e-1)
            * r
            + 0.5;
        let y = p * (r * r) + r + 1.0;
        // 2^n built in the exponent field. The biased exponent (an integer in 1..=254) is read
        // from the mantissa of `e + 2^23` by a bit cast: a float-to-int `as` cast saturates and
        // maps NaN, which compiles to per-lane scalar code and kept these loops from
        // vectorising (the softmax took a third of the attention time).
        const MANTISSA: f32 = 8_388_608.0;
        let e = n.max(-126.0) + 127.0;
        let scale = f32::from_bits((e + MANTISSA).to_bits().wrapping_sub(MANTISSA.to_bits()) << 23);
        if x < -87.3 {
            0.0
        } else {
            y * scale
        }
    }

    /// Sum with 16 independent accumulators, so the loop vectorises.
    #[inline(always)]
    fn sum(x: &[f32]) -> f32 {
        let mut acc = [0f32; 16];
        let chunks = x.chunks_exact(16);
        let tail: f32 = chunks.remainder().iter().sum();
        for c in chunks {
            for (a, v) in acc.iter_mut().zip(c) {
                *a += v;
            }
        }
        acc.iter().sum::<f32>() + tail
    }

    #[inline(always)]
    fn max(x: &[f32]) -> f32 {
        let mut acc = [f32::NEG_INFINITY; 16];
        let chunks = x.chunks_exact(16);
        let tail = chunks
            .remainder()
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        for c in chunks {
            for (a, &v) in acc.iter_mut().zip(c) {
                *a = a.max(v);
            }
        }
        acc.iter().copied().fold(tail, f32::max)
    }

    #[inline(always)]
    fn softmax_body(x: &mut [f32], n: usize) {
        for r in x.chunks_exact_mut(n) {
            let m = max(r);
            r.iter_mut().for_each(|v| *v = exp(*v - m));
            let inv = 1.0 / sum(r);
            r.iter_mut().for_each(|v| *v *= inv);
        }
    }

    /// GELU with erf from Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7, the formula PyTorch's
    /// vectorised CPU `erf` uses): `erf(z) = 1 - t (a1 + t (a2 + ...)) exp(-z^2)`,
    /// `t = 1 / (1 + p z)` for `z >= 0`, odd in `z`.
    #[inline(always)]
    fn gelu_body(x: &[f32], out: &mut [f32]) {
        const P: f32 = 0.327_591_1;
        const A: [f32; 5] = [
            0.254_829_6,
            -0.284_496_74,
            1.421_413_8,
            -1.453_152,
            1.061_405_4,
        ];
        for (o, &v) in out.iter_mut().zip(x) {
            let z = (v * std::f32::consts::FRAC_1_SQRT_2).abs();
            let t = 1.0 / (1.0 + P * z);
            let poly = t * (A[0] + t * (A[1] + t * (A[2] + t * (A[3] + t * A[4]))));
            let erf_abs = 1.0 - poly * exp(-z * z);
            let erf = if v < 0.0 { -erf_abs } else { erf_abs };
            *o = 0.5 * v * (1.0 + erf);
        }
    }

    #[inline(always)]
    fn layer_norm_body(x: &[f32], out: &mut [f32], n: usize, w: &[f32], b: &[f32], eps: f32) {
        for (x, o) in x.chunks_exact(n).zip(out.chunks_exact_mut(n)) {
            let mean = sum(x) / n as f32;
            for (o, &v) in o.iter_mut().zip(x) {
                *o = v - mean;
            }
            let mut sq = [0f32; 16];
            let chunks = o.chunks_exact(16);
            let tail: f32 = chunks.remainder().iter().map(|d| d * d).sum();
            for c in chunks {
                for (a, d) in sq.iter_mut().zip(c) {
                    *a += d * d;
                }
            }
            let var = (sq.iter().sum::<f32>() + tail) / n as f32;
            let inv = 1.0 / (var + eps).sqrt();
            for ((o, w), b) in o.iter_mut().zip(w).zip(b) {
                *o = *o * inv * w + b;
            }
        }
    }

    /// Defines `pub fn $name` calling `$body` through the widest instruction set available.
    macro_rules! dispatch {
        ($name:ident, $body:ident, ($($arg:ident: $ty:ty),*)) => {
            pub(super) fn $name($($arg: $ty),*) {
                #[cfg(target_arch = "x86_64")]
                {
                    #[target_feature(enable = "avx512f,avx2,fma")]
                    unsafe fn avx512($($arg: $ty),*) {
                        $body($($arg),*)
                    }
                    #[target_feature(enable = "avx2,fma")]
                    unsafe fn avx2($($arg: $ty),*) {
                        $body($($arg),*)
                    }
                    let avx2_fma = std::arch::is_x86_feature_detected!("avx2")
                        && std::arch::is_x86_feature_detected!("fma");
                    if avx2_fma && std::arch::is_x86_feature_detected!("avx512f") {
                        // SAFETY: the CPU supports every feature the function is compiled for.
                        return unsafe { avx512($($arg),*) };
                    }
                    if avx2_fma {
                        // SAFETY: as above.
                        return unsafe { avx2($($arg),*) };
                    }
                }
                $body($($arg),*)
            }
        };
    }

    dispatch!(softmax, softmax_body, (x: &mut [f32], n: usize));
    dispatch!(gelu_erf, gelu_body, (x: &[f32], out: &mut [f32]));
    dispatch!(
        layer_norm,
        layer_norm_body,
        (x: &[f32], out: &mut [f32], n: usize, w: &[f32], b: &[f32], eps: f32)
    );

    #[cfg(test)]
    mod tests {
        use super::*;

        /// Deterministic values in [-1, 1) (a 64-bit LCG), so failures reproduce.
        fn values(n: usize, seed: u64) -> Vec<f32> {
            let mut s = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (0..n)
                .map(|_| {
                    s = s
                        .wrapping_mul(6_364_136_223_846_793_005)
                        .wrapping_add(1_442_695_040_888_963_407);
                    ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
                })
                .collect()
        }

        /// Polynomial `exp`: under 2 f32 ulps (8e-8 measured).
        const EXP_REL_TOL: f64 = 2e-7;
        /// GELU: A&S erf's 1.5e-7 absolute error times |x| / 2, plus f32 rounding.
        const GELU_TOL: f64 = 3e-7;
        /// Softmax and layer norm outputs: f32 rounding of O(1) values over rows of <= 1000.
        const ROW_TOL: f64 = 2e-6;

        #[test]
        fn exp_matches_f64() {
            let mut worst = (0f32, 0f64);
            for i in 0..=200_000 {
                let x = -87.0 + 97.0 * i as f32 / 200_000.0;
                let want = (x as f64).exp();
                let rel = ((exp(x) as f64 - want) / want).abs();
                if rel > worst.1 {
                    worst = (x, rel);
                }
            }
            assert!(
                worst.1 < EXP_REL_TOL,
                "exp({}) relative error {:.2e}",
                worst.0,
                worst.1
            );
            assert_eq!(exp(-90.0), 0.0);
            assert_eq!(exp(0.0), 1.0);
        }

        #[test]
        fn gelu_matches_f64_erf() {
            let x: Vec<f32> = (0..=40_000).map(|i| -10.0 + i as f32 / 2000.0).collect();
            let mut out = vec![0f32; x.len()];
            gelu_erf(&x, &mut out);
            for (i, (&v, &o)) in x.iter().zip(&out).enumerate() {
                let v = v as f64;
                let want =
                    0.5 * v * (1.0 + candle_core::cpu::erf::erf_f64(v / std::f64::consts::SQRT_2));
                let tol = GELU_TOL * v.abs().max(1.0);
                assert!(
                    (o as f64 - want).abs() <= tol,
                    "gelu index {i} (x = {v}): expected {want}, actual {o}"
                );
            }
        }

        #[test]
        fn softmax_and_layer_norm_match_f64() {
            // Rows of 16 + 7 and 1000 + 5 values (tails off the 16-lane chunks); the layer-norm
            // rows sit on a mean of 300, where `E[x^2] - E[x]^2` in f32 would lose every digit.
            for n in [23usize, 1005] {
                let x: Vec<f32> = values(3 * n, n as u64).iter().map(|v| 8.0 * v).collect();
                let mut sm = x.clone();
                softmax(&mut sm, n);
                let shifted: Vec<f32> = x.iter().map(|v| v + 300.0).collect();
                let (w, b) = (values(n, 1), values(n, 2));
                let mut ln = vec![0f32; x.len()];
                layer_norm(&shifted, &mut ln, n, &w, &b, 1e-6);
                for r in 0..3 {
                    let row: Vec<f64> = x[r * n..(r + 1) * n].iter().map(|&v| v as f64).collect();
                    let max = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    let total: f64 = row.iter().map(|v| (v - max).exp()).sum();
                    let mean = row.iter().sum::<f64>() / n as f64;
                    let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
                    for j in 0..n {
                        let i = r * n + j;
                        let want = (row[j] - max).exp() / total;
                        assert!(
                            (sm[i] as f64 - want).abs() <= ROW_TOL,
                            "softmax n={n} index {i}: expected {want}, actual {}",
                            sm[i]
                        );
                        let want =
                            (row[j] - mean) / (var + 1e-6).sqrt() * w[j] as f64 + b[j] as f64;
                        assert!(
                            (ln[i] as f64 - want).abs() <= ROW_TOL * 10.0,
                            "layer norm n={n} index {i}: expected {want}, actual {}",
                            ln[i]
                        );
                    }
                }
            }
        }

        /// The vectorised builds do the same operations in the same order as the portable one.
        #[test]
        fn dispatched_kernels_equal_the_portable_ones() {
            let n = 777;
            let x: Vec<f32> = values(4 * n, 9).iter().map(|v| 10.0 * v).collect();
            let (w, b) = (values(n, 3), values(n, 4));
            let (mut fast, mut slow) = (x.clone(), x.clone());
            softmax(&mut fast, n);
            softmax_body(&mut slow, n);
            assert_eq!(fast, slow, "softmax");
            let (mut fast, mut slow) = (vec![0f32; x.len()], vec![0f32; x.len()]);
            gelu_erf(&x, &mut fast);
            gelu_body(&x, &mut slow);
            assert_eq!(fast, slow, "gelu");
            layer_norm(&x, &mut fast, n, &w, &b, 1e-6);
            layer_norm_body(&x, &mut slow, n, &w, &b, 1e-6);
            assert_eq!(fast, slow, "layer norm");
        }
    }
}

/// DINOv2 ViT returning the normed patch tokens of its last four blocks.
#[derive(Debug, Clone)]
pub struct Dinov2 {
    cls_token: Tensor,
    pos_embed: Tensor,
    /// Checkpoint key only: masked-image modelling is a pretraining feature.
    mask_token: Tensor,
    /// Kernel == stride: the patch embedding is one GEMM over flattened patches, a linear layer
    /// `[C, 3 p p]`.
    patch_embed: Linear,
    blocks: Vec<Block>,
    norm: LayerNorm,
    patch: usize,
    size: usize,
    dim: usize,
}

impl Dinov2 {
    /// `vb` at `base_model.dino_model`.
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        if cfg.patch == 0 || !cfg.dino_size.is_multiple_of(cfg.patch) {
            bail!(
                "DINOv2 needs dino_size ({}) to be a multiple of the patch size ({})",
                cfg.dino_size,
                cfg.patch
            );
        }
        let (c, p, g) = (cfg.vit_dim, cfg.patch, cfg.grid());
        if cfg.vit_heads == 0 || c % cfg.vit_heads != 0 || cfg.vit_depth < 4 {
            bail!(
                "DINOv2 needs vit_dim divisible by vit_heads and at least 4 blocks, got dim {c}, \
                 {} heads, {} blocks",
                cfg.vit_heads,
                cfg.vit_depth
            );
        }
        let blocks = (0..cfg.vit_depth)
            .map(|i| Block::new(cfg, vb.pp(format!("blocks.{i}"))))
            .collect::<Result<Vec<_>>>()?;
        let patch_weight = vb
            .get((c, 3, p, p), "patch_embed.proj.weight")?
            .reshape((c, 3 * p * p))?;
        let patch_embed = Linear::from_parts(patch_weight, vb.get(c, "patch_embed.proj.bias")?)?;
        Ok(Self {
            cls_token: vb.get((1, 1, c), "cls_token")?,
            pos_embed: vb.get((1, 1 + g * g, c), "pos_embed")?,
            mask_token: vb.get((1, c), "mask_token")?,
            patch_embed,
            blocks,
            norm: LayerNorm::new(vb.pp("norm"), c)?,
            patch: p,
            size: cfg.dino_size,
            dim: c,
        })
    }

    /// `x` [B, 3, dino, dino] (normalised, see [`preprocess`]) -> the outputs of the last four
    /// blocks through the final norm without the class token: 4 x [B, grid^2, vit_dim], patches
    /// row-major.
    pub fn forward(&self, x: &Tensor) -> Result<[Tensor; 4]> {
        let (b, ch, h, w) = x.dims4()?;
        if ch != 3 || h != self.size || w != self.size {
            bail!(
                "DINOv2 expects a [B, 3, {s}, {s}] input (no position-embedding interpolation), \
                 got {:?}",
                x.dims(),
                s = self.size
            );
        }
        let (p, c) = (self.patch, self.dim);
        let g = self.size / p;
        let patches = x
            .reshape((b, 3, g, p, g, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((b * g * g, 3 * p * p))?;
        let tokens = self.patch_embed.forward(&patches)?.reshape((b, g * g, c))?;
        let cls = self.cls_token.broadcast_as((b, 1, c))?;
        let mut x = Tensor::cat(&[&cls, &tokens], 1)?.broadcast_add(&self.pos_embed)?;
        let first_out = self.blocks.len() - 4;
        let mut outs = Vec::with_capacity(4);
        for (i, block) in self.blocks.iter().enumerate() {
            x = block.forward(&x)?;
            if i >= first_out {
                // Norm is per token, so dropping the class token first saves a row.
                outs.push(self.norm.forward(&x.narrow(1, 1, g * g)?)?);
            }
        }
        match <[Tensor; 4]>::try_from(outs) {
            Ok(o) => Ok(o),
            Err(_) => bail!("DINOv2: expected four intermediate outputs"),
        }
    }

    /// Whether the weights are trainable variables (built from a `VarMap`), i.e. the forward
    /// uses them live and differentiably; otherwise they are fixed copies and the forward runs
    /// the fused inference kernels.
    pub fn is_trainable(&self) -> bool {
        self.patch_embed.is_live()
    }

    /// Every weight under its checkpoint key relative to `base_model.dino_model` and in the
    /// checkpoint's layout (views of what the module holds; exact, the transposed copies are
    /// transposed back), for writing a model whose backbone was frozen.
    pub fn named_weights(&self) -> Result<Vec<(String, Tensor)>> {
        let c = self.dim;
        let p = self.patch;
        let mut out = vec![
            ("cls_token".to_string(), self.cls_token.clone()),
            ("pos_embed".to_string(), self.pos_embed.clone()),
            ("mask_token".to_string(), self.mask_token.clone()),
            (
                "patch_embed.proj.weight".to_string(),
                self.patch_embed.weight()?.reshape((c, 3, p, p))?,
            ),
            (
                "patch_embed.proj.bias".to_string(),
                self.patch_embed.bias.clone(),
            ),
        ];
        for (i, block) in self.blocks.iter().enumerate() {
            block.named(&format!("blocks.{i}"), &mut out)?;
        }
        self.norm.named("norm", &mut out);
        Ok(out)
    }
}

/// `F_id` (spec section 4): the first *patch* token of the last normed output (not the class
/// token), `[B, N, C] -> [B, C]`.
pub fn f_id(last: &Tensor) -> Result<Tensor> {
    let (_, n, _) = last.dims3()?;
    if n == 0 {
        bail!("f_id: no tokens in {:?}", last.dims());
    }
    last.narrow(1, 0, 1)?.squeeze(1)?.contiguous()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Attention in chunks of heads equals attention computed at once (the release size always
    /// chunks, the tiny goldens never do).
    #[test]
    fn chunked_attention_equals_unchunked() -> Result<()> {
        let (heads, n, d) = (5, 37, 8);
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (heads, n, d), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (heads, n, d), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (heads, n, d), &dev)?;
        let whole = attend(&q, &k, &v, heads)?;
        // Plain-op reference for the unchunked result itself.
        let logits = q.matmul(&k.t()?)?;
        let e = logits.broadcast_sub(&logits.max_keepdim(2)?)?.exp()?;
        let reference = e.broadcast_div(&e.sum_keepdim(2)?)?.matmul(&v)?;
        let err = (&whole - &reference)?
            .abs()?
            .flatten_all()?
            .max(0)?
            .to_scalar::<f32>()?;
        assert!(err < 1e-5, "attention vs plain ops: max abs error {err:e}");
        for per_chunk in [1, 2, 3] {
            let chunked = attend(&q, &k, &v, per_chunk)?;
            let same = chunked.flatten_all()?.to_vec1::<f32>()?
                == whole.flatten_all()?.to_vec1::<f32>()?;
            assert!(same, "chunks of {per_chunk} heads differ from the whole");
        }
        Ok(())
    }

    /// The fused inference attention (row blocks of [`ATTN_ROWS`], the last one partial) equals
    /// the plain ops, and refuses mismatched operands with an error.
    #[test]
    fn fused_attention_equals_plain_ops() -> Result<()> {
        // f32 sums of 300 products, computed in different orders by the two GEMM paths.
        const FUSED_ATTENTION_TOL: f32 = 1e-5;
        let (heads, n, d) = (3, ATTN_ROWS * 2 + 44, 16);
        let dev = Device::Cpu;
        let q = (Tensor::randn(0f32, 1.0, (heads, n, d), &dev)? * 0.25)?;
        let k = Tensor::randn(0f32, 1.0, (heads, n, d), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (heads, n, d), &dev)?;
        let fused = q.apply_op3_no_bwd(&k, &v, &AttentionOp)?;
        let logits = q.matmul(&k.t()?)?;
        let e = logits.broadcast_sub(&logits.max_keepdim(2)?)?.exp()?;
        let reference = e.broadcast_div(&e.sum_keepdim(2)?)?.matmul(&v)?;
        let (f, r) = (
            fused.flatten_all()?.to_vec1::<f32>()?,
            reference.flatten_all()?.to_vec1::<f32>()?,
        );
        for (i, (a, b)) in f.iter().zip(&r).enumerate() {
            assert!(
                (a - b).abs() <= FUSED_ATTENTION_TOL,
                "index {i}: expected {b}, got {a}"
            );
        }
        let short = k.narrow(1, 0, n - 1)?;
        assert!(q.apply_op3_no_bwd(&short, &v, &AttentionOp).is_err());
        let q64 = q.to_dtype(DType::F64)?;
        let (k64, v64) = (k.to_dtype(DType::F64)?, v.to_dtype(DType::F64)?);
        assert!(q64.apply_op3_no_bwd(&k64, &v64, &AttentionOp).is_err());
        Ok(())
    }
}
