//! DINOv2 ViT (spec section 3, `base_model.dino_model.*`) on the GPU: the 14x14 patch
//! embedding as im2col + a 1x1 convolution, the class token and position embedding, then per
//! block LayerNorm, qkv, attention, the projection with LayerScale and the residual fused into
//! its epilogue, LayerNorm, fc1 with GELU fused, fc2 like the projection; the last four blocks'
//! patch tokens through the final LayerNorm.
//!
//! Activations are channel-major `[C, N]` (a token per column, the class token last), so every
//! linear layer is the renderer's convolution kernel at `h = 1, w = N`. Exact rearrangements
//! (rounding only): LayerScale is applied as `gamma acc + gamma b + x` instead of
//! `x + gamma (acc + b)`; the class token sits after the patches (attention does not depend on
//! the order of tokens).

use gagavatar_net::ModelConfig;

use super::parts::{Ctx, Loader};
use crate::conv::{Act, At, Conv, ConvWeights};
use crate::device::Gpu;
use crate::error::Result;
use crate::kernel::Step;
use crate::reconstruct::ops::NormShape;

const LN_EPS: f32 = 1e-6;
const PREFIX: &str = "base_model.dino_model";

struct BlockW {
    norm1: (u32, u32),
    qkv: ConvWeights,
    proj: ConvWeights,
    ls1: u32,
    norm2: (u32, u32),
    fc1: ConvWeights,
    fc2: ConvWeights,
    ls2: u32,
}

pub(crate) struct DinoWeights {
    patch: ConvWeights,
    /// class token then position embedding.
    emb: wgpu::Buffer,
    blocks: Vec<BlockW>,
    norm: (u32, u32),
}

impl DinoWeights {
    pub fn load(ld: &mut Loader, cfg: &ModelConfig) -> Result<Self> {
        let (c, p, g) = (cfg.vit_dim, cfg.patch, cfg.grid());
        let patch = ld.conv(&format!("{PREFIX}.patch_embed.proj"), 3 * p * p, c, 1, true)?;
        let mut emb = ld.get(&format!("{PREFIX}.cls_token"), c)?;
        emb.extend(ld.get(&format!("{PREFIX}.pos_embed"), (1 + g * g) * c)?);
        let emb = ld.gpu.buffer_with("cls + pos embed", &emb);
        let norm = |ld: &mut Loader, key: &str| -> Result<(u32, u32)> {
            let w = ld.get(&format!("{key}.weight"), c)?;
            let b = ld.get(&format!("{key}.bias"), c)?;
            Ok((ld.push(&w), ld.push(&b)))
        };
        // A layer followed by LayerScale: the bias scaled by gamma, gamma as the output scale.
        let scaled =
            |ld: &mut Loader, key: &str, cin: usize, gamma: &[f32]| -> Result<(ConvWeights, u32)> {
                let w = ld.get(&format!("{key}.weight"), c * cin)?;
                let b = ld.get(&format!("{key}.bias"), c)?;
                let b: Vec<f32> = b.iter().zip(gamma).map(|(b, g)| b * g).collect();
                let lw = ConvWeights {
                    weight: ld.gpu.buffer_with(key, &w),
                    bias: Some(ld.push(&b)),
                    cin,
                    cout: c,
                    k: 1,
                };
                Ok((lw, ld.push(gamma)))
            };
        let mut blocks = Vec::with_capacity(cfg.vit_depth);
        for i in 0..cfg.vit_depth {
            let b = format!("{PREFIX}.blocks.{i}");
            let norm1 = norm(ld, &format!("{b}.norm1"))?;
            let qkv = ld.conv(&format!("{b}.attn.qkv"), c, 3 * c, 1, true)?;
            let g1 = ld.get(&format!("{b}.ls1.gamma"), c)?;
            let (proj, ls1) = scaled(ld, &format!("{b}.attn.proj"), c, &g1)?;
            let norm2 = norm(ld, &format!("{b}.norm2"))?;
            let fc1 = ld.conv(&format!("{b}.mlp.fc1"), c, cfg.vit_mlp, 1, true)?;
            let g2 = ld.get(&format!("{b}.ls2.gamma"), c)?;
            let (fc2, ls2) = scaled(ld, &format!("{b}.mlp.fc2"), cfg.vit_mlp, &g2)?;
            blocks.push(BlockW {
                norm1,
                qkv,
                proj,
                ls1,
                norm2,
                fc1,
                fc2,
                ls2,
            });
        }
        let norm = norm(ld, &format!("{PREFIX}.norm"))?;
        Ok(Self {
            patch,
            emb,
            blocks,
            norm,
        })
    }
}

/// The ViT's activations; `outs` are the four `[C, G]` outputs DPT reads (and, column 0 of
/// the last, F_id).
pub struct GpuDino {
    pub c: usize,
    pub g: usize,
    pub n: usize,
    cols: wgpu::Buffer,
    patches: wgpu::Buffer,
    x: [wgpu::Buffer; 2],
    ln: wgpu::Buffer,
    qkv: wgpu::Buffer,
    att: wgpu::Buffer,
    mlp: wgpu::Buffer,
    pub outs: [wgpu::Buffer; 4],
    heads: usize,
    patch: usize,
    size: usize,
}

impl GpuDino {
    pub fn new(gpu: &Gpu, cfg: &ModelConfig) -> Self {
        let (c, p) = (cfg.vit_dim, cfg.patch);
        let g = cfg.grid() * cfg.grid();
        let n = g + 1;
        let f = |label: &str, len: usize| gpu.buffer(label, 4 * len as u64);
        Self {
            c,
            g,
            n,
            cols: f("vit patches (im2col)", 3 * p * p * g),
            patches: f("vit embedded patches", c * g),
            x: [f("vit tokens a", c * n), f("vit tokens b", c * n)],
            ln: f("vit layer norm", c * n),
            qkv: f("vit qkv", 3 * c * n),
            att: f("vit attention", c * n),
            mlp: f("vit mlp", cfg.vit_mlp * n),
            outs: [0, 1, 2, 3].map(|k| f(&format!("vit output {k}"), c * g)),
            heads: cfg.vit_heads,
            patch: p,
            size: cfg.dino_size,
        }
    }

    pub(crate) fn record(
        &self,
        ctx: &Ctx,
        w: &DinoWeights,
        image: &wgpu::Buffer,
    ) -> Result<Vec<Step>> {
        let ops = ctx.ops();
        let (c, g, n, p) = (self.c, self.g, self.n, self.patch);
        let mut steps = Vec::new();
        let (im2col, _, _) = ops.im2col(
            (3, self.size, self.size),
            p,
            p,
            0,
            At::new(image),
            At::new(&self.cols),
        )?;
        steps.push(im2col);
        steps.extend(ctx.conv(&Conv::plain(
            &w.patch,
            (1, g),
            At::new(&self.cols),
            At::new(&self.patches),
        ))?);
        steps.push(ops.tokens(c, g, &self.patches, (&w.emb, 0, c as u32), &self.x[0])?);
        let all = NormShape {
            c,
            n,
            in_stride: n,
            out_stride: n,
        };
        let first_out = w.blocks.len() - 4;
        let [xa, xb] = &self.x;
        for (i, b) in w.blocks.iter().enumerate() {
            steps.push(ops.layer_norm(all, b.norm1, LN_EPS, At::new(xa), At::new(&self.ln))?);
            steps.extend(ctx.conv(&Conv::plain(
                &b.qkv,
                (1, n),
                At::new(&self.ln),
                At::new(&self.qkv),
            ))?);
            steps.push(ops.attention(
                self.heads,
                c / self.heads,
                n,
                At::new(&self.qkv),
                At::new(&self.att),
            )?);
            steps.extend(ctx.conv(&Conv {
                out_scale: Some(b.ls1),
                residual: Some(At::new(xa)),
                ..Conv::plain(&b.proj, (1, n), At::new(&self.att), At::new(xb))
            })?);
            steps.push(ops.layer_norm(all, b.norm2, LN_EPS, At::new(xb), At::new(&self.ln))?);
            steps.extend(ctx.conv(&Conv {
                act: Act::Gelu,
                ..Conv::plain(&b.fc1, (1, n), At::new(&self.ln), At::new(&self.mlp))
            })?);
            steps.extend(ctx.conv(&Conv {
                out_scale: Some(b.ls2),
                residual: Some(At::new(xb)),
                ..Conv::plain(&b.fc2, (1, n), At::new(&self.mlp), At::new(xa))
            })?);
            if i >= first_out {
                steps.push(ops.layer_norm(
                    NormShape {
                        c,
                        n: g,
                        in_stride: n,
                        out_stride: g,
                    },
                    w.norm,
                    LN_EPS,
                    At::new(xa),
                    At::new(&self.outs[i - first_out]),
                )?);
            }
        }
        Ok(steps)
    }

    /// The four outputs `[C, G]` (channel-major) read back.
    pub fn download(&self, gpu: &Gpu) -> Result<Vec<Vec<f32>>> {
        self.outs
            .iter()
            .map(|b| gpu.read_f32(b, self.c * self.g))
            .collect()
    }
}
