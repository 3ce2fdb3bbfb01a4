//! The three Gaussian generators (spec section 5) on the GPU, writing the avatar's buffers.
//!
//! `gs_generator_g` (the expression Gaussians, one per FLAME vertex): the first layer's
//! vertex half (`head_base W_a^T`, a model constant computed once at upload) plus the identity
//! row (`W_b F_id + b`, per photo), ReLU, two more layers with ReLU and the last without; the
//! four heads' first layers as one convolution whose bias is the direction encoding's part
//! (`W_e enc + b`, per photo), ReLU, and their second layers as one block-diagonal product.
//! `gs_generator_l0` / `l1` (the lifted Gaussians): four convolutions over F_local with the
//! encoding broadcast as extra planes, then the activation moves each plane point along the
//! view direction.

use candle_core::Tensor;
use gagavatar_net::config::DIR_ENCODING_DIM;
use gagavatar_net::ModelConfig;

use super::dino::GpuDino;
use super::ops::GaussianOut;
use super::parts::{Ctx, GpuAvatar, Loader};
use crate::conv::{Act, At, Conv, ConvWeights};
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::Step;

const HEADS: [&str; 4] = ["color", "opacity", "scale", "rotation"];

struct ExprW {
    /// `[h, V]`: `head_base W_a^T`, transposed.
    vertex: wgpu::Buffer,
    /// The identity half `W_b` `[h, C]` (None: the `no_fid_in_expression` ablation, where
    /// the row is the bias alone) and the first layer's bias.
    id: (Option<wgpu::Buffer>, wgpu::Buffer),
    layers: [ConvWeights; 3],
    /// The heads' first layers, feature part `[4 hh, h]` (bias: `head_bias`).
    heads_x: ConvWeights,
    /// Their encoding part `[4 hh, E]` and biases `[4 hh]`.
    heads_enc: (wgpu::Buffer, wgpu::Buffer),
    /// Block-diagonal second layers `[C + 8, 4 hh]`.
    heads_out: ConvWeights,
}

pub(crate) struct GenWeights {
    expr: ExprW,
    lifts: Vec<[ConvWeights; 4]>,
}

fn to_vec(t: &Tensor, what: &str) -> Result<Vec<f32>> {
    crate::kernel::tensor_f32(t).map_err(|e| GpuError::Weights(format!("{what}: {e}")))
}

impl GenWeights {
    pub fn load(ld: &mut Loader, cfg: &ModelConfig) -> Result<Self> {
        let (h, hd, c) = (cfg.gs_linear_hidden, cfg.head_base_dim, cfg.vit_dim);
        let v = cfg.n_vertices;
        let e = DIR_ENCODING_DIM;
        let p = "gs_generator_g";
        let w0 = ld.get(&format!("{p}.feature_layers.0.weight"), h * (hd + c))?;
        let b0 = ld.get(&format!("{p}.feature_layers.0.bias"), h)?;
        let head_base = ld.tensor("head_base")?;
        let wa: Vec<f32> = (0..h)
            .flat_map(|o| w0[o * (hd + c)..o * (hd + c) + hd].to_vec())
            .collect();
        let wb: Vec<f32> = (0..h)
            .flat_map(|o| w0[o * (hd + c) + hd..(o + 1) * (hd + c)].to_vec())
            .collect();
        // The CPU path's own product (candle, f32), transposed to `[h, V]`.
        let vertex = Tensor::from_vec(wa, (h, hd), head_base.device())
            .and_then(|wa| {
                head_base
                    .to_dtype(candle_core::DType::F32)?
                    .matmul(&wa.t()?)?
                    .t()?
                    .contiguous()
            })
            .map_err(|e| GpuError::Weights(format!("head_base x feature_layers.0: {e}")))?;
        if vertex.dims() != [h, v] {
            return Err(GpuError::Weights(format!(
                "head_base x feature_layers.0 is {:?}, expected [{h}, {v}]",
                vertex.dims()
            )));
        }
        let vertex = ld
            .gpu
            .buffer_with("vertex term", &to_vec(&vertex, "vertex term")?);
        let id = (
            (!cfg.no_fid_in_expression).then(|| ld.gpu.buffer_with("identity weight", &wb)),
            ld.gpu.buffer_with("identity bias", &b0),
        );
        let layers = [2, 4, 6].map(|i| ld.conv(&format!("{p}.feature_layers.{i}"), h, h, 1, true));
        let [l2, l4, l6] = layers;
        let hh = cfg.gs_head_hidden;
        let outs = [cfg.color_dim, 1, 3, 4];
        let total: usize = outs.iter().sum();
        let (mut wx, mut we, mut bh) = (Vec::new(), Vec::new(), Vec::new());
        let mut second = vec![0f32; total * 4 * hh];
        let mut second_b = Vec::new();
        let mut row = 0;
        for (k, name) in HEADS.iter().enumerate() {
            let w = ld.get(&format!("{p}.{name}_layers.0.weight"), hh * (h + e))?;
            for o in 0..hh {
                wx.extend_from_slice(&w[o * (h + e)..o * (h + e) + h]);
                we.extend_from_slice(&w[o * (h + e) + h..(o + 1) * (h + e)]);
            }
            bh.extend(ld.get(&format!("{p}.{name}_layers.0.bias"), hh)?);
            let w2 = ld.get(&format!("{p}.{name}_layers.2.weight"), outs[k] * hh)?;
            for o in 0..outs[k] {
                let dst = (row + o) * 4 * hh + k * hh;
                second[dst..dst + hh].copy_from_slice(&w2[o * hh..(o + 1) * hh]);
            }
            second_b.extend(ld.get(&format!("{p}.{name}_layers.2.bias"), outs[k])?);
            row += outs[k];
        }
        let heads_x = ConvWeights {
            weight: ld.gpu.buffer_with("heads x", &wx),
            bias: Some(0),
            cin: h,
            cout: 4 * hh,
            k: 1,
        };
        let heads_enc = (
            ld.gpu.buffer_with("heads encoding", &we),
            ld.gpu.buffer_with("heads bias", &bh),
        );
        let heads_out = ConvWeights {
            weight: ld.gpu.buffer_with("heads out", &second),
            bias: Some(ld.push(&second_b)),
            cin: 4 * hh,
            cout: total,
            k: 1,
        };
        let expr = ExprW {
            vertex,
            id,
            layers: [l2?, l4?, l6?],
            heads_x,
            heads_enc,
            heads_out,
        };
        let (f, hc) = (cfg.dpt_features, cfg.gs_conv_hidden);
        let out = cfg.color_dim + 9;
        let planes = if cfg.one_plane { 1 } else { 2 };
        let mut lifts = Vec::with_capacity(planes);
        for l in 0..planes {
            let q = format!("gs_generator_l{l}.gaussian_conv");
            lifts.push([
                ld.conv(&format!("{q}.0"), f + e, hc, 3, true)?,
                ld.conv(&format!("{q}.2"), hc, hc, 3, true)?,
                ld.conv(&format!("{q}.4"), hc, hc, 3, true)?,
                ld.conv(&format!("{q}.6"), hc, out, 1, true)?,
            ]);
        }
        Ok(Self { expr, lifts })
    }
}

/// The generators' activations.
pub struct GenBuffers {
    v: usize,
    h: usize,
    hh: usize,
    s: usize,
    f: usize,
    c: usize,
    id_row: wgpu::Buffer,
    x: [wgpu::Buffer; 2],
    head_bias: wgpu::Buffer,
    head_hidden: wgpu::Buffer,
    raw_expr: wgpu::Buffer,
    hidden: [wgpu::Buffer; 2],
    raw_lift: wgpu::Buffer,
}

impl GenBuffers {
    pub fn new(gpu: &Gpu, cfg: &ModelConfig) -> Self {
        let (v, h, hh) = (cfg.n_vertices, cfg.gs_linear_hidden, cfg.gs_head_hidden);
        let s = cfg.plane_size();
        let hc = cfg.gs_conv_hidden;
        let c = cfg.color_dim;
        let buf = |label: &str, len: usize| gpu.buffer(label, 4 * len as u64);
        Self {
            v,
            h,
            hh,
            s,
            f: cfg.dpt_features,
            c,
            id_row: buf("identity row", h),
            x: [buf("expression a", h * v), buf("expression b", h * v)],
            head_bias: buf("heads bias (per photo)", 4 * hh),
            head_hidden: buf("heads hidden", 4 * hh * v),
            raw_expr: buf("expression raw", (c + 8) * v),
            hidden: [buf("lift a", hc * s * s), buf("lift b", hc * s * s)],
            raw_lift: buf("lift raw", (c + 9) * s * s),
        }
    }

    /// The expression generator's steps and the lifting generators' steps.
    pub(crate) fn record(
        &self,
        ctx: &Ctx,
        w: &GenWeights,
        dino: &GpuDino,
        f_local: &wgpu::Buffer,
        (plane, encoding): (&wgpu::Buffer, &wgpu::Buffer),
        avatar: &GpuAvatar,
    ) -> Result<[Vec<Step>; 2]> {
        let ops = ctx.ops();
        let (v, h, hh, s, c) = (self.v, self.h, self.hh, self.s, self.c);
        let e = DIR_ENCODING_DIM;
        let x = &w.expr;
        let mut g = Vec::new();
        let (wb, b0) = &x.id;
        g.push(match wb {
            // F_id: column 0 (the first patch token) of the ViT's last output.
            Some(wb) => ops.linear_strided(
                dino.c,
                h,
                (At::new(&dino.outs[3]), dino.g),
                wb,
                b0,
                false,
                At::new(&self.id_row),
            )?,
            None => ops.rows((h, 1), None, At::new(b0), false, At::new(&self.id_row))?,
        });
        let [xa, xb] = &self.x;
        g.push(ops.rows(
            (h, v),
            Some(At::new(&x.vertex)),
            At::new(&self.id_row),
            true,
            At::new(xa),
        )?);
        let [l2, l4, l6] = &x.layers;
        g.extend(ctx.conv(&Conv {
            act: Act::Relu,
            ..Conv::plain(l2, (1, v), At::new(xa), At::new(xb))
        })?);
        g.extend(ctx.conv(&Conv {
            act: Act::Relu,
            ..Conv::plain(l4, (1, v), At::new(xb), At::new(xa))
        })?);
        g.extend(ctx.conv(&Conv::plain(l6, (1, v), At::new(xa), At::new(xb)))?);
        g.push(ops.linear(
            e,
            4 * hh,
            At::new(encoding),
            &x.heads_enc.0,
            &x.heads_enc.1,
            false,
            At::new(&self.head_bias),
        )?);
        g.extend(ctx.conv_with(
            &Conv {
                act: Act::Relu,
                ..Conv::plain(&x.heads_x, (1, v), At::new(xb), At::new(&self.head_hidden))
            },
            &self.head_bias,
        )?);
        g.extend(ctx.conv(&Conv::plain(
            &x.heads_out,
            (1, v),
            At::new(&self.head_hidden),
            At::new(&self.raw_expr),
        ))?);
        let buffers = [
            &avatar.features,
            &avatar.opacities,
            &avatar.scales,
            &avatar.rotations,
            &avatar.means,
        ];
        g.push(ops.gaussians(
            &GaussianOut {
                m: v,
                c,
                g0: 0,
                lift: None,
                buffers,
            },
            At::new(&self.raw_expr),
            ctx.spare,
        )?);
        g.push(ops.rotations_across((v, c, 0), At::new(&self.raw_expr), &avatar.rotations)?);

        let mut l = Vec::new();
        l.push(ops.rows(
            (e, s * s),
            None,
            At::new(encoding),
            false,
            At::off(f_local, self.f * s * s),
        )?);
        let [ha, hb] = &self.hidden;
        for (i, convs) in w.lifts.iter().enumerate() {
            let [c0, c2, c4, c6] = convs;
            for (cw, input, out) in [(c0, f_local, ha), (c2, ha, hb), (c4, hb, ha)] {
                l.extend(ctx.conv(&Conv {
                    act: Act::Relu,
                    ..Conv::plain(cw, (s, s), At::new(input), At::new(out))
                })?);
            }
            l.extend(ctx.conv(&Conv::plain(
                c6,
                (s, s),
                At::new(ha),
                At::new(&self.raw_lift),
            ))?);
            l.push(ops.gaussians(
                &GaussianOut {
                    m: s * s,
                    c,
                    g0: v + i * s * s,
                    lift: Some((s, plane, 3 * i * s * s, if i == 0 { 1.0 } else { -1.0 })),
                    buffers,
                },
                At::new(&self.raw_lift),
                ctx.spare,
            )?);
        }
        Ok([g, l])
    }
}
