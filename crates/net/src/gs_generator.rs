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
    /// The last feature layer folded into the heads (see [`FoldedHeads`]), made on the first
    /// f32 inference call.
    folded: std::sync::Arc<std::sync::OnceLock<FoldedHeads>>,
    precision: Precision,
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
            folded: Default::default(),
            precision: Precision::F32,
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
        let lock = || {
            self.vertex_term
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner())
        };
        if let Some((id, t)) = lock().as_ref() {
            if *id == head_base.id() {
                return Ok(t.clone());
            }
        }
        // Computed without the lock: the product runs parallel tasks, and a worker waiting on
        // them must not be able to reach this lock again from another call.
        let t = head_base.matmul(&wa.t()?)?;
        *lock() = Some((head_base.id(), t.clone()));
        Ok(t)
    }

    /// Switches the linear layers between f32 and bf16 products.
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.precision = precision;
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
        let tracked = x.track_op()
            || encoding.track_op()
            || self
                .weights()
                .iter()
                .any(|w| w.track_op() || w.is_variable());
        if self.precision == Precision::F32 && !tracked {
            for l in &self.feature_layers[1..3] {
                x = l.forward(&x)?.relu()?;
            }
            let folded = match self.folded.get() {
                Some(f) => f,
                None => {
                    let f = FoldedHeads::new(self)?;
                    self.folded.get_or_init(|| f)
                }
            };
            return folded.forward(&x, encoding);
        }
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
        activate(
            self.color.forward(&x)?,
            self.opacity.forward(&x)?,
            self.scale.forward(&x)?,
            self.rotation.forward(&x)?,
        )
    }

    /// Every weight under its key relative to `gs_generator_g.`.
    pub fn named_weights(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        for (i, l) in self.feature_layers.iter().enumerate() {
            l.named(&format!("feature_layers.{}", 2 * i), &mut out);
        }
        for (name, h) in ["color", "opacity", "scale", "rotation"]
            .iter()
            .zip(self.heads())
        {
            h.l0.named(&format!("{name}_layers.0"), &mut out);
            h.l2.named(&format!("{name}_layers.2"), &mut out);
        }
        out
    }

    fn heads(&self) -> [&Head; 4] {
        [&self.color, &self.opacity, &self.scale, &self.rotation]
    }

    fn weights(&self) -> Vec<&Tensor> {
        let mut out = Vec::new();
        let layers = self
            .feature_layers
            .iter()
            .chain(self.heads().into_iter().flat_map(|h| [&h.l0, &h.l2]));
        for l in layers {
            out.push(l.inner().weight());
            out.extend(l.inner().bias());
        }
        out
    }
}

/// The heads' raw outputs `[B, V, k]` -> activated attributes.
fn activate(
    colors: Tensor,
    opacities: Tensor,
    scales: Tensor,
    rotations: Tensor,
) -> Result<GaussianAttributes> {
    let colors = Tensor::cat(
        &[
            candle_nn::ops::sigmoid(&colors.narrow(2, 0, 3)?)?,
            colors.narrow(2, 3, colors.dim(2)? - 3)?,
        ],
        2,
    )?;
    let opacities = candle_nn::ops::sigmoid(&opacities)?;
    let scales = (candle_nn::ops::sigmoid(&scales)? * SCALE_MAX)?;
    // Release quirk (spec 5): the norm is taken over the points (dim 1 of [B, V, 4]), not
    // over the quaternion, so these quaternions are tiny.
    let rotations = l2_normalize(&rotations, 1)?;
    Ok(GaussianAttributes {
        colors,
        opacities,
        scales,
        rotations,
    })
}

/// `gs_generator_g`'s tail for fixed weights, with the same outputs and fewer multiplies.
/// The last feature layer has no activation, so it composes with the heads' first layers:
/// `W_h [x W_6^T + b_6 | enc] + b_h = x (W_hx W_6)^T + enc W_he^T + (W_hx b_6 + b_h)`. The
/// four heads' first layers run as one [4 * 128, 256] product, the direction encoding (one row
/// per photo, the same for every vertex) becomes a per-photo bias instead of 27 more columns,
/// and the four second layers run as one block-diagonal product. Per vertex that is 267k
/// multiplies instead of 346k, in two large products instead of nine.
#[derive(Debug)]
struct FoldedHeads {
    /// `(W_hx W_6)^T` [hidden, heads * head_hidden], composed in f64, stored in the model's dtype.
    first_t: Tensor,
    /// `W_hx b_6 + b_h` [heads * head_hidden].
    first_bias: Tensor,
    /// `W_he^T` [27, heads * head_hidden].
    encoding_t: Tensor,
    /// The second layers block-diagonally, transposed: [heads * head_hidden, sum of outs].
    second_t: Tensor,
    second_bias: Tensor,
    /// Output widths of the colour, opacity, scale and rotation heads.
    outs: [usize; 4],
}

impl FoldedHeads {
    fn new(g: &LinearGsGenerator) -> Result<Self> {
        use candle_core::DType;
        let f64 = |t: &Tensor| t.to_dtype(DType::F64);
        let last = g.feature_layers[3].inner();
        let w6 = f64(last.weight())?;
        let hidden = w6.dim(0)?;
        let b6 = match last.bias() {
            Some(b) => f64(b)?,
            None => Tensor::zeros(hidden, DType::F64, w6.device())?,
        };
        let heads = g.heads();
        let mut firsts = Vec::new();
        let mut first_biases = Vec::new();
        let mut encodings = Vec::new();
        let mut seconds = Vec::new();
        let mut second_biases = Vec::new();
        let mut outs = [0; 4];
        let head_hidden = heads[0].l0.inner().weight().dim(0)?;
        for h in &heads {
            let l0 = h.l0.inner();
            let wh = f64(l0.weight())?;
            let whx = wh.narrow(1, 0, hidden)?;
            firsts.push(whx.matmul(&w6)?);
            let mut bias = whx.matmul(&b6.unsqueeze(1)?)?.squeeze(1)?;
            if let Some(b) = l0.bias() {
                bias = (bias + f64(b)?)?;
            }
            first_biases.push(bias);
            encodings.push(wh.narrow(1, hidden, wh.dim(1)? - hidden)?);
        }
        for (k, h) in heads.iter().enumerate() {
            let l2 = h.l2.inner();
            let w2 = f64(l2.weight())?;
            let out = w2.dim(0)?;
            outs[k] = out;
            // Row block k of the block-diagonal [sum of outs, heads * head_hidden].
            let after = (heads.len() - 1 - k) * head_hidden;
            seconds.push(w2.pad_with_zeros(1, k * head_hidden, after)?);
            second_biases.push(match l2.bias() {
                Some(b) => f64(b)?,
                None => Tensor::zeros(out, DType::F64, w6.device())?,
            });
        }
        // Back to the model's own dtype.
        let dtype = last.weight().dtype();
        let own = |t: Tensor| t.to_dtype(dtype);
        Ok(Self {
            first_t: own(Tensor::cat(&firsts, 0)?.t()?.contiguous()?)?,
            first_bias: own(Tensor::cat(&first_biases, 0)?)?,
            encoding_t: own(Tensor::cat(&encodings, 0)?.t()?.contiguous()?)?,
            second_t: own(Tensor::cat(&seconds, 0)?.t()?.contiguous()?)?,
            second_bias: own(Tensor::cat(&second_biases, 0)?)?,
            outs,
        })
    }

    /// `x` [B, V, hidden] (after the third feature layer's ReLU), `encoding` [B, 27].
    fn forward(&self, x: &Tensor, encoding: &Tensor) -> Result<GaussianAttributes> {
        let (b, v, hidden) = x.dims3()?;
        let per_photo = encoding
            .to_dtype(self.first_t.dtype())?
            .matmul(&self.encoding_t)?
            .broadcast_add(&self.first_bias)?;
        let h = x
            .reshape((b * v, hidden))?
            .matmul(&self.first_t)?
            .reshape((b, v, ()))?
            .broadcast_add(&per_photo.unsqueeze(1)?)?
            .relu()?;
        let width = h.dim(2)?;
        let out = h
            .reshape((b * v, width))?
            .matmul(&self.second_t)?
            .broadcast_add(&self.second_bias)?
            .reshape((b, v, ()))?;
        let mut parts = Vec::with_capacity(4);
        let mut at = 0;
        for n in self.outs {
            parts.push(out.narrow(2, at, n)?.contiguous()?);
            at += n;
        }
        let [c, o, s, r]: [Tensor; 4] = parts
            .try_into()
            .map_err(|_| candle_core::Error::Msg("four heads".into()))?;
        activate(c, o, s, r)
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

    /// Every weight under its key relative to `gs_generator_l0.` (or `_l1.`).
    pub fn named_weights(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        for (i, c) in self.convs.iter().enumerate() {
            c.named(&format!("gaussian_conv.{}", 2 * i), &mut out);
        }
        out
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

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::{VarBuilder, VarMap};
    use std::collections::HashMap;

    /// The folded tail (fixed weights) against the layer-by-layer tail (the same values as
    /// trainable variables), in f64 where only the composition's rounding differs and in f32.
    #[test]
    fn folded_heads_equal_the_layers() {
        let cfg = ModelConfig::tiny();
        let dev = Device::Cpu;
        for (dtype, tol) in [(DType::F64, 1e-12), (DType::F32, 1e-5)] {
            let map = VarMap::new();
            let layered =
                LinearGsGenerator::new(&cfg, VarBuilder::from_varmap(&map, dtype, &dev)).unwrap();
            let values: HashMap<String, Tensor> = map
                .data()
                .lock()
                .unwrap()
                .iter()
                .map(|(k, v)| (k.clone(), v.as_tensor().copy().unwrap().detach()))
                .collect();
            let fixed = LinearGsGenerator::new(&cfg, VarBuilder::from_tensors(values, dtype, &dev))
                .unwrap();
            let (v, b) = (37, 2);
            let head_base = Tensor::randn(0f64, 1.0, (v, cfg.head_base_dim), &dev)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let f_id = Tensor::randn(0f64, 1.0, (b, cfg.vit_dim), &dev)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let enc = Tensor::randn(0f64, 1.0, (b, DIR_ENCODING_DIM), &dev)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let a = fixed.forward(&head_base, &f_id, &enc).unwrap();
            let e = layered.forward(&head_base, &f_id, &enc).unwrap();
            assert!(fixed.folded.get().is_some(), "the fixed weights fold");
            assert!(layered.folded.get().is_none(), "variables never fold");
            for (name, a, e) in [
                ("colors", &a.colors, &e.colors),
                ("opacities", &a.opacities, &e.opacities),
                ("scales", &a.scales, &e.scales),
                ("rotations", &a.rotations, &e.rotations),
            ] {
                assert_eq!(a.dims(), e.dims(), "{name}");
                let flat = |t: &Tensor| -> Vec<f64> {
                    t.to_dtype(DType::F64)
                        .unwrap()
                        .flatten_all()
                        .unwrap()
                        .to_vec1()
                        .unwrap()
                };
                // Rotations are normalised over all points: compare them relative to their size.
                let (av, ev) = (flat(a), flat(e));
                let scale = ev.iter().fold(0f64, |m, x| m.max(x.abs())).max(1e-30);
                for (i, (x, y)) in av.iter().zip(&ev).enumerate() {
                    let err = (x - y).abs() / scale;
                    assert!(
                        err <= tol,
                        "{dtype:?} {name} index {i}: expected {y}, actual {x}, error {err:e} > {tol:e}"
                    );
                }
            }
        }
    }
}
