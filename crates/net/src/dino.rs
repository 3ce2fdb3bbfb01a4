//! The frozen DINOv2 ViT-B/14 of the encoder (`base_model.dino_model.*`, spec section 4) and the
//! source preprocessing that feeds it (spec section 3).
//!
//! The ViT is frozen in the release, so its default forward is inference-only: fused CPU kernels
//! without a backward (layer norm, attention, GELU, in-place softmax; `gagavatar_ops::vit`) and linear weights copied
//! into a transposed layout at load time. No gradient flows through it or into its weights, which
//! is what "frozen" asks.
//!
//! The small presets have no pretrained backbone, so there the ViT trains. Built from variables
//! (a `VarMap`), it keeps the live weights (views only, so an optimiser's in-place `Var::set`
//! is seen by the next forward) and runs differentiable candle ops wherever a value tracks
//! gradients. The rule is per op: the fused kernels run only when nothing they touch tracks
//! gradients, so a frozen backbone (fixed tensors, untracked input) keeps the fast path.

use candle_core::{bail, DType, Result, Tensor, D};
use candle_nn::VarBuilder;
use std::sync::Arc;

use gagavatar_ops::bf16::Bf16Linear;
use gagavatar_ops::vit::{self, LinearEpilogue};
use gagavatar_ops::Precision;
use gagavatar_ops::{resize, ResizeMode};

use crate::config::ModelConfig;
use crate::layers::packed_linear;

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

/// What follows a [`Linear`] in the ViT's blocks.
#[derive(Debug, Clone, Copy)]
enum After<'a> {
    /// Nothing (the bias is the layer's).
    Bias,
    /// Exact GELU (the MLP's first layer).
    Gelu,
    /// `residual + ls * y` (LayerScale and the residual connection; `residual` has `y`'s
    /// elements in any shape).
    LayerScale {
        ls: &'a Tensor,
        residual: &'a Tensor,
    },
}

/// `nn.Linear` on token rows: `x [M, in] -> [M, out]`.
#[derive(Debug, Clone)]
struct Linear {
    weight: LinearWeight,
    bias: Tensor,
    /// The weight packed for bf16 products, under `Precision::Bf16` (fixed weights only).
    bf16: Option<Arc<Bf16Linear>>,
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
        Ok(Self {
            weight,
            bias,
            bf16: None,
        })
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.bf16 = packed_linear(precision, &self.weight()?, Some(&self.bias))?;
        Ok(())
    }

    fn is_live(&self) -> bool {
        matches!(self.weight, LinearWeight::Live(_))
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if let Some(packed) = &self.bf16 {
            if !x.track_op() {
                return packed.forward(x);
            }
        }
        let y = match &self.weight {
            LinearWeight::Transposed(wt) => x.matmul(wt)?,
            LinearWeight::Live(w) => x.matmul(&w.t()?)?,
        };
        y.broadcast_add(&self.bias)
    }

    /// The layer and what follows it. Without gradients and bf16, in f32 on the CPU, the
    /// product is written once and `after` applied to it in place (`vit::linear_epilogue`);
    /// otherwise the same arithmetic from candle ops.
    fn forward_then(&self, x: &Tensor, after: After) -> Result<Tensor> {
        let operands_fixed = match after {
            After::LayerScale { ls, residual } => !ls.track_op() && !residual.track_op(),
            _ => true,
        };
        if let LinearWeight::Transposed(wt) = &self.weight {
            if self.bf16.is_none() && fused_path(x) && !self.bias.track_op() && operands_fixed {
                let y = x.matmul(wt)?;
                let bias = &self.bias;
                vit::linear_epilogue(
                    &y,
                    match after {
                        After::Bias => LinearEpilogue::Bias(bias),
                        After::Gelu => LinearEpilogue::BiasGelu(bias),
                        After::LayerScale { ls, residual } => {
                            LinearEpilogue::LayerScale { bias, ls, residual }
                        }
                    },
                )?;
                return Ok(y);
            }
        }
        let y = self.forward(x)?;
        match after {
            After::Bias => Ok(y),
            After::Gelu => gelu_erf(&y),
            After::LayerScale { ls, residual } => {
                residual.reshape(y.dims())? + y.broadcast_mul(ls)?
            }
        }
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
        vit::layer_norm(x, &self.weight, &self.bias, LN_EPS)
    }

    fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        out.push((format!("{prefix}.weight"), self.weight.clone()));
        out.push((format!("{prefix}.bias"), self.bias.clone()));
    }
}

/// Attention logits computed at once (8 MiB in f32), see [`attend`].
const LOGITS_PER_CHUNK: usize = 1 << 21;

#[derive(Debug, Clone)]
struct Attention {
    qkv: Linear,
    proj: Linear,
    heads: usize,
    /// Both attention products in bf16 (`Precision::Bf16`).
    bf16: bool,
}

impl Attention {
    /// `x [B, N, C]` (normalised) -> the heads' outputs `[B * N, C]`, before the projection.
    fn heads(&self, x: &Tensor) -> Result<Tensor> {
        let (b, n, c) = x.dims3()?;
        let (h, d) = (self.heads, c / self.heads);
        let scale = 1.0 / (d as f64).sqrt();
        let rows = x.reshape((b * n, c))?;
        if !self.bf16 && fused_path(&rows) && !self.qkv.is_live() {
            // q, k and v read in place from the qkv product: no permuted copies.
            let qkv = self.qkv.forward_then(&rows, After::Bias)?;
            return vit::attention_qkv(&qkv.reshape((b, n, 3 * c))?, h, scale)?.reshape((b * n, c));
        }
        let qkv = self
            .qkv
            .forward(&rows)?
            .reshape((b, n, 3, h, d))?
            .permute((2, 0, 3, 1, 4))?
            .contiguous()?;
        // Scaling q (N d values) is cheaper than scaling the N x N logits; mathematically equal.
        let q = (qkv.get(0)?.reshape((b * h, n, d))? * scale)?;
        let k = qkv.get(1)?.reshape((b * h, n, d))?;
        let v = qkv.get(2)?.reshape((b * h, n, d))?;
        let fused = !(q.track_op() || k.track_op() || v.track_op())
            && q.dtype() == DType::F32
            && q.device().is_cpu();
        let y = if fused && self.bf16 {
            vit::attention_bf16(&q, &k, &v)?
        } else if fused {
            vit::attention(&q, &k, &v)?
        } else {
            attend(&q, &k, &v, (LOGITS_PER_CHUNK / (n * n)).max(1))?
        };
        y.reshape((b, h, n, d))?
            .transpose(1, 2)?
            .contiguous()?
            .reshape((b * n, c))
    }
}

/// Whether `x` takes the fused f32 inference kernels (no gradients, on the CPU).
fn fused_path(x: &Tensor) -> bool {
    !x.track_op() && x.dtype() == DType::F32 && x.device().is_cpu()
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
            vit::softmax_in_place(&logits)?;
            logits
        };
        chunks.push(weights.matmul(&v.narrow(0, start, len)?)?);
    }
    Tensor::cat(&chunks, 0)
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
                bf16: false,
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
        let a = self.attn.heads(&self.norm1.forward(x)?)?;
        let x = self
            .attn
            .proj
            .forward_then(
                &a,
                After::LayerScale {
                    ls: &self.ls1,
                    residual: x,
                },
            )?
            .reshape((b, n, c))?;
        let h = self.norm2.forward(&x)?.reshape((b * n, c))?;
        let m = self.fc1.forward_then(&h, After::Gelu)?;
        self.fc2
            .forward_then(
                &m,
                After::LayerScale {
                    ls: &self.ls2,
                    residual: &x,
                },
            )?
            .reshape((b, n, c))
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
    vit::gelu_erf(x)
}

/// Softmax over the last dim from ops with a backward. The row maximum is detached: subtracting
/// any per-row constant leaves the softmax and its gradient unchanged, and a detached one keeps
/// the max's own (zero-sum) gradient out of the graph.
fn softmax_tracked(x: &Tensor) -> Result<Tensor> {
    let max = x.max_keepdim(D::Minus1)?.detach();
    let e = x.broadcast_sub(&max)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
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

    /// Switches the products (patch embedding, qkv, attention, projection, MLP) between f32 and
    /// bf16; bf16 packs each weight once (an error on a CPU without AVX512-BF16).
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        precision.check().map_err(candle_core::Error::wrap)?;
        self.patch_embed.set_precision(precision)?;
        for block in &mut self.blocks {
            block.attn.qkv.set_precision(precision)?;
            block.attn.bf16 = precision == Precision::Bf16;
            block.attn.proj.set_precision(precision)?;
            block.fc1.set_precision(precision)?;
            block.fc2.set_precision(precision)?;
        }
        Ok(())
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

    /// The fused inference attention (row blocks of [`vit::ATTN_ROWS`], the last one partial) equals
    /// the plain ops, and refuses mismatched operands with an error.
    #[test]
    fn fused_attention_equals_plain_ops() -> Result<()> {
        // f32 sums of 300 products, computed in different orders by the two GEMM paths.
        const FUSED_ATTENTION_TOL: f32 = 1e-5;
        let (heads, n, d) = (3, vit::ATTN_ROWS * 2 + 44, 16);
        let dev = Device::Cpu;
        let q = (Tensor::randn(0f32, 1.0, (heads, n, d), &dev)? * 0.25)?;
        let k = Tensor::randn(0f32, 1.0, (heads, n, d), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (heads, n, d), &dev)?;
        let fused = vit::attention(&q, &k, &v)?;
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
        assert!(vit::attention(&q, &short, &v).is_err());
        let q64 = q.to_dtype(DType::F64)?;
        let (k64, v64) = (k.to_dtype(DType::F64)?, v.to_dtype(DType::F64)?);
        assert!(vit::attention(&q64, &k64, &v64).is_err());
        Ok(())
    }
}
