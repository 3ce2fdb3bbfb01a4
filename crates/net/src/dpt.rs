//! The DPT-style head of the encoder (`base_model.{projects, resize_layers, layer_rn, refinenet,
//! output_conv}`, spec section 4): four DINOv2 token maps -> the local feature map `F_local`
//! [B, dpt_features, S, S], S = 8 x grid. Trained in the release, so every op here is
//! differentiable.

use candle_core::{bail, Result, Tensor};
use std::sync::Arc;

use candle_nn::VarBuilder;
use gagavatar_ops::bf16::Bf16Linear;
use gagavatar_ops::{resize, Precision, ResizeMode};

use crate::config::ModelConfig;
use crate::layers::{packed_linear, Conv2d};

/// `x + conv2(relu(conv1(relu(x))))`; the release's ReLUs are not in place, so `x` is kept.
#[derive(Debug, Clone)]
struct ResidualConvUnit {
    conv1: Conv2d,
    conv2: Conv2d,
}

impl ResidualConvUnit {
    fn new(vb: VarBuilder, c: usize) -> Result<Self> {
        Ok(Self {
            conv1: Conv2d::k3(vb.pp("conv1"), c, c)?,
            conv2: Conv2d::k3(vb.pp("conv2"), c, c)?,
        })
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.conv1.set_precision(precision)?;
        self.conv2.set_precision(precision)
    }

    fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        self.conv1.named(&format!("{prefix}.conv1"), out);
        self.conv2.named(&format!("{prefix}.conv2"), out);
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = self.conv1.forward(&x.relu()?)?;
        let y = self.conv2.forward(&y.relu()?)?;
        x + y
    }
}

/// A fusion block `refinenet.k`.
#[derive(Debug, Clone)]
struct FusionBlock {
    /// Only used when a skip input is given; `refinenet.0` has the keys but never runs it.
    res_conf_unit1: ResidualConvUnit,
    res_conf_unit2: ResidualConvUnit,
    out_conv: Conv2d,
}

impl FusionBlock {
    fn new(vb: VarBuilder, c: usize) -> Result<Self> {
        Ok(Self {
            out_conv: Conv2d::k1(vb.pp("out_conv"), c, c)?,
            res_conf_unit1: ResidualConvUnit::new(vb.pp("resConfUnit1"), c)?,
            res_conf_unit2: ResidualConvUnit::new(vb.pp("resConfUnit2"), c)?,
        })
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.res_conf_unit1.set_precision(precision)?;
        self.res_conf_unit2.set_precision(precision)?;
        self.out_conv.set_precision(precision)
    }

    /// `out = a (+ rcu1(skip))`, `rcu2`, align-corners resize to `size` (x2 when `None`),
    /// `out_conv`.
    fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        self.out_conv.named(&format!("{prefix}.out_conv"), out);
        self.res_conf_unit1
            .named(&format!("{prefix}.resConfUnit1"), out);
        self.res_conf_unit2
            .named(&format!("{prefix}.resConfUnit2"), out);
    }

    fn forward(&self, a: &Tensor, skip: Option<&Tensor>, size: Option<usize>) -> Result<Tensor> {
        let mut out = a.clone();
        if let Some(s) = skip {
            out = (out + self.res_conf_unit1.forward(s)?)?;
        }
        let out = self.res_conf_unit2.forward(&out)?;
        let (_, _, h, w) = out.dims4()?;
        let (oh, ow) = match size {
            Some(s) => (s, s),
            None => (2 * h, 2 * w),
        };
        let out = resize(&out, oh, ow, ResizeMode::AlignCorners)?;
        self.out_conv.forward(&out)
    }
}

/// `nn.ConvTranspose2d` with kernel == stride: each input pixel paints its own k x k output
/// block, so it is one GEMM `[pixels, Cin] x [Cin, Cout k k]` and a pixel rearrangement.
#[derive(Debug, Clone)]
struct PatchTransposedConv {
    /// `[Cin, Cout k k]` (the checkpoint's `[Cin, Cout, k, k]` flattened).
    weight: Tensor,
    /// `[Cout, 1]`, broadcast over the k x k block.
    bias: Tensor,
    cout: usize,
    k: usize,
    bf16: Option<Arc<Bf16Linear>>,
}

impl PatchTransposedConv {
    fn new(vb: VarBuilder, cin: usize, cout: usize, k: usize) -> Result<Self> {
        Ok(Self {
            weight: vb
                .get((cin, cout, k, k), "weight")?
                .reshape((cin, cout * k * k))?,
            bias: vb.get(cout, "bias")?.reshape((cout, 1))?,
            cout,
            k,
            bf16: None,
        })
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.bf16 = packed_linear(precision, &self.weight.t()?, None)?;
        Ok(())
    }

    /// `x [B * g * g, Cin]` (pixel-major, row-major pixels) -> `[B, Cout, g k, g k]`.
    fn forward(&self, x: &Tensor, b: usize, g: usize) -> Result<Tensor> {
        let (c, k) = (self.cout, self.k);
        let y = match &self.bf16 {
            Some(packed) if !x.track_op() => packed.forward(x)?,
            _ => x.matmul(&self.weight)?,
        };
        y.reshape((b * g * g, c, k * k))?
            .broadcast_add(&self.bias)?
            .reshape((b, g, g, c, k, k))?
            .permute((0, 3, 1, 4, 2, 5))?
            .contiguous()?
            .reshape((b, c, g * k, g * k))
    }
}

/// How a level's projected map reaches its DPT resolution (`resize_layers.k`).
#[derive(Debug, Clone)]
enum Resize {
    Up(PatchTransposedConv),
    Identity,
    Down(Conv2d),
}

#[derive(Debug, Clone)]
struct Level {
    /// `projects.k`, a 1x1 conv applied to the tokens as a GEMM: `[Cout, Cin]` and `[Cout]`.
    project_weight: Tensor,
    project_bias: Tensor,
    project_bf16: Option<Arc<Bf16Linear>>,
    resize: Resize,
    layer_rn: Conv2d,
    size: usize,
}

/// The DPT head; see the module docs.
#[derive(Debug, Clone)]
pub struct DptHead {
    levels: Vec<Level>,
    refinenet: Vec<FusionBlock>,
    output_conv: Conv2d,
    grid: usize,
    dim: usize,
    dino_size: usize,
    plane_size: usize,
}

impl DptHead {
    /// `vb` at `base_model`.
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        let (c, f) = (cfg.vit_dim, cfg.dpt_features);
        let mut levels = Vec::with_capacity(4);
        for (k, &ck) in cfg.dpt_channels.iter().enumerate() {
            let project = Conv2d::k1(vb.pp(format!("projects.{k}")), c, ck)?;
            let rvb = vb.pp(format!("resize_layers.{k}"));
            let resize = match k {
                0 => Resize::Up(PatchTransposedConv::new(rvb, ck, ck, 4)?),
                1 => Resize::Up(PatchTransposedConv::new(rvb, ck, ck, 2)?),
                2 => Resize::Identity,
                _ => Resize::Down(Conv2d::new(rvb, ck, ck, 3, 2, 1, true)?),
            };
            let project_bias = match &project.bias {
                Some(b) => b.clone(),
                None => bail!("projects.{k}: missing bias"),
            };
            levels.push(Level {
                project_weight: project.weight.reshape((ck, c))?,
                project_bias,
                project_bf16: None,
                resize,
                layer_rn: Conv2d::new(vb.pp(format!("layer_rn.{k}")), 3 + ck, f, 3, 1, 1, false)?,
                size: cfg.dpt_level_size(k),
            });
        }
        let refinenet = (0..4)
            .map(|k| FusionBlock::new(vb.pp(format!("refinenet.{k}")), f))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            levels,
            refinenet,
            output_conv: Conv2d::k3(vb.pp("output_conv"), f, f)?,
            grid: cfg.grid(),
            dim: c,
            dino_size: cfg.dino_size,
            plane_size: cfg.plane_size(),
        })
    }

    /// Switches every product between f32 and bf16 (bf16: fixed weights only, inference).
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        for level in &mut self.levels {
            level.project_bf16 =
                packed_linear(precision, &level.project_weight, Some(&level.project_bias))?;
            match &mut level.resize {
                Resize::Up(t) => t.set_precision(precision)?,
                Resize::Identity => {}
                Resize::Down(conv) => conv.set_precision(precision)?,
            }
            level.layer_rn.set_precision(precision)?;
        }
        for block in &mut self.refinenet {
            block.set_precision(precision)?;
        }
        self.output_conv.set_precision(precision)
    }

    /// `feats`: the four [`crate::dino::Dinov2`] outputs [B, grid^2, vit_dim]; `image`: the
    /// normalised DINO input [B, 3, dino, dino]. Returns `F_local` [B, dpt_features, S, S].
    /// Every weight under its checkpoint key relative to `base_model.` (`projects.0.weight`,
    /// ...), in the checkpoint's shapes.
    pub fn named_weights(&self) -> Result<Vec<(String, Tensor)>> {
        let mut out = Vec::new();
        for (k, level) in self.levels.iter().enumerate() {
            let (ck, c) = level.project_weight.dims2()?;
            out.push((
                format!("projects.{k}.weight"),
                level.project_weight.reshape((ck, c, 1, 1))?,
            ));
            out.push((format!("projects.{k}.bias"), level.project_bias.clone()));
            match &level.resize {
                Resize::Up(t) => {
                    let cin = t.weight.dim(0)?;
                    out.push((
                        format!("resize_layers.{k}.weight"),
                        t.weight.reshape((cin, t.cout, t.k, t.k))?,
                    ));
                    out.push((format!("resize_layers.{k}.bias"), t.bias.reshape(t.cout)?));
                }
                Resize::Identity => {}
                Resize::Down(conv) => conv.named(&format!("resize_layers.{k}"), &mut out),
            }
            level.layer_rn.named(&format!("layer_rn.{k}"), &mut out);
        }
        for (k, block) in self.refinenet.iter().enumerate() {
            block.named(&format!("refinenet.{k}"), &mut out);
        }
        self.output_conv.named("output_conv", &mut out);
        Ok(out)
    }

    pub fn forward(&self, feats: &[Tensor; 4], image: &Tensor) -> Result<Tensor> {
        let (b, ch, h, w) = image.dims4()?;
        if ch != 3 || h != self.dino_size || w != self.dino_size {
            bail!(
                "DPT head expects the [B, 3, {s}, {s}] DINO input image, got {:?}",
                image.dims(),
                s = self.dino_size
            );
        }
        let g = self.grid;
        let mut rn = Vec::with_capacity(4);
        for (k, (level, tokens)) in self.levels.iter().zip(feats).enumerate() {
            if tokens.dims() != [b, g * g, self.dim] {
                bail!(
                    "DPT head: feature {k} must be [{b}, {}, {}], got {:?}",
                    g * g,
                    self.dim,
                    tokens.dims()
                );
            }
            let tokens = tokens.reshape((b * g * g, self.dim))?;
            let p = match &level.project_bf16 {
                Some(packed) if !tokens.track_op() => packed.forward(&tokens)?,
                _ => tokens
                    .matmul(&level.project_weight.t()?)?
                    .broadcast_add(&level.project_bias)?,
            };
            let ck = level.project_bias.dim(0)?;
            let to_nchw = |p: &Tensor| -> Result<Tensor> {
                p.reshape((b, g, g, ck))?
                    .permute((0, 3, 1, 2))?
                    .contiguous()
            };
            let x = match &level.resize {
                Resize::Up(t) => t.forward(&p, b, g)?,
                Resize::Identity => to_nchw(&p)?,
                Resize::Down(conv) => conv.forward(&to_nchw(&p)?)?,
            };
            let (_, _, xh, xw) = x.dims4()?;
            if xh != level.size || xw != level.size {
                bail!(
                    "DPT level {k}: got {xh}x{xw}, expected {s}x{s}",
                    s = level.size
                );
            }
            let img = resize(image, level.size, level.size, ResizeMode::Antialias)?;
            rn.push(level.layer_rn.forward(&Tensor::cat(&[&img, &x], 1)?)?);
        }
        let r = &self.refinenet;
        let p4 = r[0].forward(&rn[3], None, Some(self.levels[2].size))?;
        let p3 = r[1].forward(&p4, Some(&rn[2]), Some(self.levels[1].size))?;
        let p2 = r[2].forward(&p3, Some(&rn[1]), Some(self.levels[0].size))?;
        let p1 = r[3].forward(&p2, Some(&rn[0]), None)?;
        let out = self.output_conv.forward(&p1)?;
        let (_, _, oh, ow) = out.dims4()?;
        if oh != self.plane_size || ow != self.plane_size {
            bail!(
                "DPT head: F_local is {oh}x{ow}, expected {s}x{s}",
                s = self.plane_size
            );
        }
        Ok(out)
    }
}
