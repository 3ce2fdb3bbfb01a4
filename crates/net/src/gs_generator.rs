//! The two Gaussian generators (spec section 5): the per-vertex MLP of the expression branch
//! (`gs_generator_g`) and the per-pixel conv net of the dual-lifting branch
//! (`gs_generator_l0`, `gs_generator_l1`).

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use gagavatar_ops::Precision;

use crate::config::{ModelConfig, DIR_ENCODING_DIM};
use crate::layers::{Conv2d, Linear};

/// Scale activation: `SCALE_MAX * sigmoid`, keeping every Gaussian small.
pub const SCALE_MAX: f64 = 0.05;
/// `F.normalize`'s eps: norms are clamped below by it.
pub const NORMALIZE_EPS: f64 = 1e-12;

/// Raw Gaussian attributes of one branch, activated, `[B, N, k]` each.
#[derive(Debug, Clone)]
pub struct GaussianAttributes {
    pub colors: Tensor,
    pub opacities: Tensor,
    pub scales: Tensor,
    pub rotations: Tensor,
}

/// L2-normalise along `dim` with the norm clamped at `NORMALIZE_EPS` (as `F.normalize`).
fn l2_normalize(x: &Tensor, dim: usize) -> Result<Tensor> {
    let n = x
        .sqr()?
        .sum_keepdim(dim)?
        .sqrt()?
        .clamp(NORMALIZE_EPS, f64::INFINITY)?;
    x.broadcast_div(&n)
}

/// Two linear layers with a ReLU between: one attribute head.
#[derive(Debug, Clone)]
struct Head {
    l0: Linear,
    l2: Linear,
}

impl Head {
    fn new(vb: VarBuilder, cin: usize, hidden: usize, out: usize) -> Result<Self> {
        Ok(Self {
            l0: Linear::new(vb.pp("0"), cin, hidden)?,
            l2: Linear::new(vb.pp("2"), hidden, out)?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.l2.forward(&self.l0.forward(x)?.relu()?)
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.l0.set_precision(precision)?;
        self.l2.set_precision(precision)
    }
}

/// `gs_generator_g`: per FLAME vertex `[head_base | F_id]` -> Gaussian attributes.
#[derive(Debug, Clone)]
pub struct LinearGsGenerator {
    feature_layers: [Linear; 4],
    /// `head_base W_a^T` of the first layer (see `forward`) for fixed weights, keyed by the
    /// id of the `head_base` it was computed from: it does not depend on the photo.
    vertex_term: std::sync::Arc<std::sync::Mutex<Option<(candle_core::TensorId, Tensor)>>>,
    color: Head,
    opacity: Head,
    scale: Head,
    rotation: Head,
}

impl LinearGsGenerator {
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        let h = cfg.gs_linear_hidden;
        let f = vb.pp("feature_layers");
        let feature_layers = [
            Linear::new(f.pp("0"), cfg.head_base_dim + cfg.vit_dim, h)?,
            Linear::new(f.pp("2"), h, h)?,
            Linear::new(f.pp("4"), h, h)?,
            Linear::new(f.pp("6"), h, h)?,
        ];
        let cin = h + DIR_ENCODING_DIM;
        let hh = cfg.gs_head_hidden;
        Ok(Self {
            feature_layers,
            vertex_term: Default::default(),
            color: Head::new(vb.pp("color_layers"), cin, hh, cfg.color_dim)?,
            opacity: Head::new(vb.pp("opacity_layers"), cin, hh, 1)?,
            scale: Head::new(vb.pp("scale_layers"), cin, hh, 3)?,
            rotation: Head::new(vb.pp("rotation_layers"), cin, hh, 4)?,
        })
    }

    /// `head_base` [V, hb], `f_id` [B, D], `encoding` [B, 27] -> attributes `[B, V, k]`.
    /// `head_base W_a^T` [V, hidden]: cached when nothing tracks gradients (inference), else
    /// recomputed so gradients reach both.
    fn vertex_term(&self, head_base: &Tensor, wa: &Tensor) -> Result<Tensor> {
        if head_base.track_op() || wa.track_op() {
            return head_base.matmul(&wa.t()?);
        }
        let mut cache = self
            .vertex_term
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some((id, t)) = cache.as_ref() {
            if *id == head_base.id() {
                return Ok(t.clone());
            }
        }
        let t = head_base.matmul(&wa.t()?)?;
        *cache = Some((head_base.id(), t.clone()));
        Ok(t)
    }

    /// Switches the linear layers between f32 and bf16 products.
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        for l in &mut self.feature_layers {
            l.set_precision(precision)?;
        }
        for h in [
            &mut self.color,
            &mut self.opacity,
            &mut self.scale,
            &mut self.rotation,
        ] {
            h.set_precision(precision)?;
        }
        Ok(())
    }

    pub fn forward(
        &self,
        head_base: &Tensor,
        f_id: &Tensor,
        encoding: &Tensor,
    ) -> Result<GaussianAttributes> {
        let (v, hd) = head_base.dims2()?;
        let (b, _) = f_id.dims2()?;
        // The first layer reads `[head_base[v] | f_id]`, so it splits into a per-vertex term
        // `head_base W_a^T` and a per-photo row `f_id W_b^T + bias` added to every vertex: no
        // [B, V, head_base + vit_dim] concatenation, a quarter of the multiplies, and with fixed
        // weights the vertex term is computed once.
        let first = self.feature_layers[0].inner();
        let w = first.weight();
        let vertex = self.vertex_term(head_base, &w.narrow(1, 0, hd)?)?;
        let id_row = f_id.matmul(&w.narrow(1, hd, w.dim(1)? - hd)?.t()?)?;
        let id_row = match first.bias() {
            Some(bias) => id_row.broadcast_add(bias)?,
            None => id_row,
        };
        let mut x = vertex
            .unsqueeze(0)?
            .broadcast_add(&id_row.unsqueeze(1)?)?
            .relu()?;
        debug_assert_eq!(x.dims3()?, (b, v, w.dim(0)?));
        let last = self.feature_layers.len() - 1;
        for (i, l) in self.feature_layers.iter().enumerate().skip(1) {
            x = l.forward(&x)?;
            if i < last {
                x = x.relu()?;
            }
        }
        let enc = encoding
            .unsqueeze(1)?
            .broadcast_as((b, v, encoding.dim(1)?))?;
        let x = Tensor::cat(&[x, enc.contiguous()?], 2)?;
        let colors = self.color.forward(&x)?;
        let colors = Tensor::cat(
            &[
                candle_nn::ops::sigmoid(&colors.narrow(2, 0, 3)?)?,
                colors.narrow(2, 3, colors.dim(2)? - 3)?,
            ],
            2,
        )?;
        let opacities = candle_nn::ops::sigmoid(&self.opacity.forward(&x)?)?;
        let scales = (candle_nn::ops::sigmoid(&self.scale.forward(&x)?)? * SCALE_MAX)?;
        // Release quirk (spec 5): the norm is taken over the points (dim 1 of [B, V, 4]), not
        // over the quaternion, so these quaternions are tiny.
        let rotations = l2_normalize(&self.rotation.forward(&x)?, 1)?;
        Ok(GaussianAttributes {
            colors,
            opacities,
            scales,
            rotations,
        })
    }
}

/// `gs_generator_l*`: `[F_local | encoding]` per pixel -> Gaussian attributes and a lifting
/// distance per pixel.
#[derive(Debug, Clone)]
pub struct ConvGsGenerator {
    convs: [Conv2d; 4],
    color_dim: usize,
}

/// Output of a conv generator: attributes `[B, S*S, k]` and lifting distances `[B, S*S, 1]`.
#[derive(Debug, Clone)]
pub struct LiftedAttributes {
    pub attrs: GaussianAttributes,
    pub distance: Tensor,
}

impl ConvGsGenerator {
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        let h = cfg.gs_conv_hidden;
        let g = vb.pp("gaussian_conv");
        let out = cfg.color_dim + 1 + 3 + 4 + 1;
        Ok(Self {
            convs: [
                Conv2d::k3(g.pp("0"), cfg.dpt_features + DIR_ENCODING_DIM, h)?,
                Conv2d::k3(g.pp("2"), h, h)?,
                Conv2d::k3(g.pp("4"), h, h)?,
                Conv2d::k1(g.pp("6"), h, out)?,
            ],
            color_dim: cfg.color_dim,
        })
    }

    /// `f_local` [B, F, S, S], `encoding` [B, 27].
    /// Switches the convolutions between f32 and bf16 products.
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        for c in &mut self.convs {
            c.set_precision(precision)?;
        }
        Ok(())
    }

    pub fn forward(&self, f_local: &Tensor, encoding: &Tensor) -> Result<LiftedAttributes> {
        let (b, _, h, w) = f_local.dims4()?;
        let e = encoding.dim(1)?;
        let enc = encoding.reshape((b, e, 1, 1))?.broadcast_as((b, e, h, w))?;
        let mut x = Tensor::cat(&[f_local, &enc], 1)?;
        for (i, c) in self.convs.iter().enumerate() {
            x = c.forward(&x)?;
            if i + 1 < self.convs.len() {
                x = x.relu()?;
            }
        }
        let cd = self.color_dim;
        let colors = x.narrow(1, 0, cd)?;
        // Release quirk (spec 5): `colours[..., :3]` of the [B, C, H, W] map hits pixel
        // columns 0..2 of every channel, not channels 0..2.
        let colors = Tensor::cat(
            &[
                candle_nn::ops::sigmoid(&colors.narrow(3, 0, 3.min(w))?)?,
                colors.narrow(3, 3.min(w), w - 3.min(w))?,
            ],
            3,
        )?;
        let opacities = candle_nn::ops::sigmoid(&x.narrow(1, cd, 1)?)?;
        let scales = (candle_nn::ops::sigmoid(&x.narrow(1, cd + 1, 3)?)? * SCALE_MAX)?;
        let rotations = l2_normalize(&x.narrow(1, cd + 4, 4)?, 1)?;
        let distance = candle_nn::ops::sigmoid(&x.narrow(1, cd + 8, 1)?)?;
        let flat = |t: Tensor| -> Result<Tensor> {
            let c = t.dim(1)?;
            t.permute((0, 2, 3, 1))?.reshape((b, h * w, c))
        };
        Ok(LiftedAttributes {
            attrs: GaussianAttributes {
                colors: flat(colors)?,
                opacities: flat(opacities)?,
                scales: flat(scales)?,
                rotations: flat(rotations)?,
            },
            distance: flat(distance)?,
        })
    }
}

/// Concatenates per attribute along the point axis (dim 1).
pub fn concat_attributes(parts: &[&GaussianAttributes]) -> Result<GaussianAttributes> {
    let cat = |f: &dyn Fn(&GaussianAttributes) -> &Tensor| -> Result<Tensor> {
        let v: Vec<&Tensor> = parts.iter().map(|p| f(p)).collect();
        Tensor::cat(&v, 1)
    };
    Ok(GaussianAttributes {
        colors: cat(&|p| &p.colors)?,
        opacities: cat(&|p| &p.opacities)?,
        scales: cat(&|p| &p.scales)?,
        rotations: cat(&|p| &p.rotations)?,
    })
}
