//! The whole network and its two phases (spec section 1): `reconstruct` (once per source
//! image) and `drive` (per frame).

use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;
use gagavatar_ops::Precision;
use gagavatar_splat::{splat, Camera, Gaussians};

use crate::config::{ModelConfig, FOCAL};
use crate::dino::Dinov2;
use crate::dpt::DptHead;
use crate::error::{NetError, Result};
use crate::gs_generator::{
    concat_attributes, ConvGsGenerator, GaussianAttributes, LinearGsGenerator,
};
use crate::plane::{dir_encoding, point_plane};
use crate::style_unet::{Noise, StyleUNet};

/// The GAGAvatar network; parameter names are the release checkpoint's keys.
#[derive(Debug, Clone)]
pub struct GagAvatar {
    pub cfg: ModelConfig,
    pub dino: Dinov2,
    pub dpt: DptHead,
    pub head_base: Tensor,
    pub gen_g: LinearGsGenerator,
    pub gen_l0: ConvGsGenerator,
    pub gen_l1: ConvGsGenerator,
    pub renderer: StyleUNet,
}

/// A reconstructed head: every Gaussian attribute except the expression Gaussians' positions,
/// which each frame supplies. Attributes are `[B, N, k]` in the order
/// `[expression (V), l0 (S*S), l1 (S*S)]` (no l1 with the `one_plane` ablation).
#[derive(Debug, Clone)]
pub struct Avatar {
    /// Positions of the two lifted point sets, `[B, 2 S*S, 3]` (`[B, S*S, 3]` with `one_plane`).
    pub lifted_xyz: Tensor,
    pub colors: Tensor,
    pub opacities: Tensor,
    pub scales: Tensor,
    pub rotations: Tensor,
}

impl Avatar {
    pub fn batch(&self) -> usize {
        self.colors.dims().first().copied().unwrap_or(0)
    }

    /// All positions for the given expression-vertex positions `[B, V, 3]`.
    pub fn positions(&self, vertices: &Tensor) -> Result<Tensor> {
        Ok(Tensor::cat(&[vertices, &self.lifted_xyz], 1)?)
    }
}

/// Intermediate values of `reconstruct`, for parity dumps.
#[derive(Debug, Clone)]
pub struct ReconstructTrace {
    pub input_518: Tensor,
    pub dino: [Tensor; 4],
    pub f_id: Tensor,
    pub f_local: Tensor,
    pub plane_points: Tensor,
    pub plane_dir: Tensor,
    pub dir_encoding: Tensor,
}

/// One driven frame.
#[derive(Debug, Clone)]
pub struct DrivenFrame {
    /// Splatted features `[B, C, H, W]`; channels 0..3 are the coarse RGB.
    pub coarse: Tensor,
    /// The neural renderer's RGB `[B, 3, H, W]` in [0, 1].
    pub fine: Tensor,
}

fn input_err(name: &str, reason: impl Into<String>) -> NetError {
    NetError::Input {
        name: name.to_string(),
        reason: reason.into(),
    }
}

/// Errors on NaN or infinite values: they would silently poison every Gaussian.
fn check_finite(t: &Tensor, name: &str) -> Result<()> {
    let s = t
        .to_dtype(DType::F64)?
        .abs()?
        .flatten_all()?
        .max(0)?
        .to_scalar::<f64>()?;
    if s.is_finite() {
        Ok(())
    } else {
        Err(input_err(name, "contains NaN or infinite values"))
    }
}

fn check_transform(t: &Tensor, name: &str, batch: Option<usize>) -> Result<usize> {
    match t.dims() {
        [b, 3, 4] if *b > 0 && batch.is_none_or(|want| want == *b) => {
            check_finite(t, name)?;
            Ok(*b)
        }
        other => Err(input_err(
            name,
            format!(
                "expected [{}, 3, 4], got {other:?}",
                batch.map_or("B".to_string(), |b| b.to_string())
            ),
        )),
    }
}

/// Cameras of `[B, 3, 4]` transforms at the model resolution.
pub fn cameras(transform: &Tensor, size: usize) -> Result<Vec<Camera>> {
    let m: Vec<Vec<Vec<f64>>> = transform.to_dtype(DType::F64)?.to_vec3()?;
    m.iter()
        .map(|tm| {
            let mut a = [[0.0; 4]; 3];
            for (r, row) in tm.iter().enumerate() {
                a[r].copy_from_slice(row);
            }
            Ok(Camera::from_transform_matrix(&a, FOCAL, size, size)?)
        })
        .collect()
}

impl GagAvatar {
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        cfg.validate().map_err(NetError::Config)?;
        Ok(Self {
            cfg: cfg.clone(),
            dino: Dinov2::new(cfg, vb.pp("base_model").pp("dino_model"))?,
            dpt: DptHead::new(cfg, vb.pp("base_model"))?,
            head_base: vb.get((cfg.n_vertices, cfg.head_base_dim), "head_base")?,
            gen_g: LinearGsGenerator::new(cfg, vb.pp("gs_generator_g"))?,
            gen_l0: ConvGsGenerator::new(cfg, vb.pp("gs_generator_l0"))?,
            gen_l1: ConvGsGenerator::new(cfg, vb.pp("gs_generator_l1"))?,
            renderer: StyleUNet::new(cfg, vb.pp("upsampler"))?,
        })
    }

    /// Runs the products in `precision` from now on: `Precision::Bf16` packs the weights once
    /// for bf16 products with f32 sums (inference only; an error on a CPU without
    /// AVX512-BF16), `Precision::F32` (the default) returns to the release's arithmetic.
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        precision.check()?;
        self.dino.set_precision(precision)?;
        self.dpt.set_precision(precision)?;
        self.gen_g.set_precision(precision)?;
        self.gen_l0.set_precision(precision)?;
        self.gen_l1.set_precision(precision)?;
        self.renderer.set_precision(precision)?;
        Ok(())
    }

    /// Source image `[B, 3, H, W]` in [0, 1] (H = W = image_size) and its camera `[B, 3, 4]`
    /// -> the avatar.
    pub fn reconstruct(&self, image: &Tensor, transform: &Tensor) -> Result<Avatar> {
        Ok(self.reconstruct_traced(image, transform)?.0)
    }

    /// `reconstruct`, also returning the intermediate values.
    pub fn reconstruct_traced(
        &self,
        image: &Tensor,
        transform: &Tensor,
    ) -> Result<(Avatar, ReconstructTrace)> {
        self.reconstruct_staged(image, transform, &mut |_| {})
    }

    /// Names of the stages `reconstruct_staged` reports, in order.
    pub const STAGES: [&'static str; 7] = [
        "preprocess",
        "dino",
        "dpt head",
        "plane+encoding",
        "gs_generator_g",
        "gs_generator_l0",
        "gs_generator_l1",
    ];

    /// `reconstruct_traced`, calling `done(name)` as each of [`Self::STAGES`] finishes (for
    /// per-module timing).
    pub fn reconstruct_staged(
        &self,
        image: &Tensor,
        transform: &Tensor,
        done: &mut dyn FnMut(&'static str),
    ) -> Result<(Avatar, ReconstructTrace)> {
        self.reconstruct_from(image, transform, None, done)
    }

    /// [`Self::reconstruct`] with the backbone's four outputs computed elsewhere (a GPU; as
    /// `Dinov2::forward` returns them, `[B, grid^2, vit_dim]`): only for a frozen backbone,
    /// whose outputs need no gradient.
    pub fn reconstruct_with_backbone(
        &self,
        image: &Tensor,
        transform: &Tensor,
        backbone: [Tensor; 4],
    ) -> Result<Avatar> {
        if !self.cfg.backbone_frozen() {
            return Err(NetError::Config(
                "backbone outputs from elsewhere need a frozen backbone (they carry no gradient)"
                    .into(),
            ));
        }
        Ok(self
            .reconstruct_from(image, transform, Some(backbone), &mut |_| {})?
            .0)
    }

    fn reconstruct_from(
        &self,
        image: &Tensor,
        transform: &Tensor,
        backbone: Option<[Tensor; 4]>,
        done: &mut dyn FnMut(&'static str),
    ) -> Result<(Avatar, ReconstructTrace)> {
        let (expr, trace) = self.features_from(image, transform, backbone, true, done)?;
        let [_, _, _, _, _, s_l0, s_l1] = Self::STAGES;
        let (f_local, enc) = (&trace.f_local, &trace.dir_encoding);
        let l0 = self.gen_l0.forward(f_local, enc)?;
        done(s_l0);
        let dir = trace.plane_dir.unsqueeze(1)?;
        let xyz0 = (&trace.plane_points + l0.distance.broadcast_mul(&dir)?)?;
        let (lifted_xyz, attrs) = if self.cfg.one_plane {
            done(s_l1);
            (xyz0, concat_attributes(&[&expr, &l0.attrs])?)
        } else {
            let l1 = self.gen_l1.forward(f_local, enc)?;
            done(s_l1);
            let xyz1 = (&trace.plane_points - l1.distance.broadcast_mul(&dir)?)?;
            (
                Tensor::cat(&[xyz0, xyz1], 1)?,
                concat_attributes(&[&expr, &l0.attrs, &l1.attrs])?,
            )
        };
        let GaussianAttributes {
            colors,
            opacities,
            scales,
            rotations,
        } = attrs;
        let avatar = Avatar {
            lifted_xyz,
            colors,
            opacities,
            scales,
            rotations,
        };
        Ok((avatar, trace))
    }

    /// The reconstruction up to the lifting generators: the expression Gaussians' attributes
    /// `[B, V, k]` and the values the lifting generators read (`f_local`, the plane and the
    /// direction encoding, in the trace), for a trainer that runs those generators elsewhere
    /// (a GPU) and brings the gradient of `f_local` back. `backbone`: as
    /// [`Self::reconstruct_with_backbone`] takes it (frozen backbones only).
    pub fn reconstruct_features(
        &self,
        image: &Tensor,
        transform: &Tensor,
        backbone: Option<[Tensor; 4]>,
    ) -> Result<(GaussianAttributes, ReconstructTrace)> {
        if backbone.is_some() && !self.cfg.backbone_frozen() {
            return Err(NetError::Config(
                "backbone outputs from elsewhere need a frozen backbone (they carry no gradient)"
                    .into(),
            ));
        }
        self.features_from(image, transform, backbone, true, &mut |_| {})
    }

    /// [`Self::reconstruct_features`] without the DPT head, for a trainer that runs the head
    /// elsewhere too (it reads the trace's `dino` and `input_518`): the trace's `f_local` is
    /// empty, `[B, 0, S, S]`. Frozen backbones only, their outputs given.
    pub fn reconstruct_expression(
        &self,
        image: &Tensor,
        transform: &Tensor,
        backbone: [Tensor; 4],
    ) -> Result<(GaussianAttributes, ReconstructTrace)> {
        if !self.cfg.backbone_frozen() {
            return Err(NetError::Config(
                "a DPT head run elsewhere needs a frozen backbone (its outputs carry no gradient)"
                    .into(),
            ));
        }
        self.features_from(image, transform, Some(backbone), false, &mut |_| {})
    }

    fn features_from(
        &self,
        image: &Tensor,
        transform: &Tensor,
        backbone: Option<[Tensor; 4]>,
        with_dpt: bool,
        done: &mut dyn FnMut(&'static str),
    ) -> Result<(GaussianAttributes, ReconstructTrace)> {
        let size = self.cfg.image_size;
        let b = match image.dims() {
            [b, 3, h, w] if *b > 0 && *h == size && *w == size => *b,
            other => {
                return Err(input_err(
                    "source image",
                    format!("expected [B, 3, {size}, {size}], got {other:?}"),
                ))
            }
        };
        check_finite(image, "source image")?;
        check_transform(transform, "source transform", Some(b))?;
        let dtype = self.head_base.dtype();
        let image = image.to_dtype(dtype)?;
        let transform = transform.to_dtype(dtype)?;

        let [s_pre, s_dino, s_dpt, s_plane, s_g, _, _] = Self::STAGES;
        let input_518 = crate::dino::preprocess(&image, &self.cfg)?;
        done(s_pre);
        let dino = match backbone {
            Some(outs) => {
                let want = [b, self.cfg.grid() * self.cfg.grid(), self.cfg.vit_dim];
                if let Some(t) = outs.iter().find(|t| t.dims() != want) {
                    return Err(input_err(
                        "backbone outputs",
                        format!("expected {want:?}, got {:?}", t.dims()),
                    ));
                }
                let [o0, o1, o2, o3] = outs;
                [
                    o0.to_dtype(dtype)?,
                    o1.to_dtype(dtype)?,
                    o2.to_dtype(dtype)?,
                    o3.to_dtype(dtype)?,
                ]
            }
            None => self.dino.forward(&input_518)?,
        };
        let f_id = crate::dino::f_id(&dino[3])?;
        done(s_dino);
        let s = self.cfg.plane_size();
        let f_local = if with_dpt {
            self.dpt.forward(&dino, &input_518)?
        } else {
            Tensor::zeros((b, 0, s, s), dtype, image.device())?
        };
        done(s_dpt);

        let (plane_points, plane_dir) = point_plane(&transform, s, FOCAL)?;
        let enc = dir_encoding(&plane_dir)?;
        done(s_plane);

        let expr = if self.cfg.no_fid_in_expression {
            self.gen_g
                .forward(&self.head_base, &f_id.zeros_like()?, &enc)?
        } else {
            self.gen_g.forward(&self.head_base, &f_id, &enc)?
        };
        done(s_g);
        let trace = ReconstructTrace {
            input_518,
            dino,
            f_id,
            f_local,
            plane_points,
            plane_dir,
            dir_encoding: enc,
        };
        Ok((expr, trace))
    }

    /// Renders the avatar with target FLAME vertices `[B, V, 3]` (already scaled by 5) from
    /// target cameras `[B, 3, 4]`. An avatar of batch 1 drives any number of frames.
    pub fn drive(
        &self,
        avatar: &Avatar,
        vertices: &Tensor,
        transform: &Tensor,
        noise: Noise,
    ) -> Result<DrivenFrame> {
        let coarse = self.splat_coarse(avatar, vertices, transform)?;
        let fine = self.render(&coarse, noise)?;
        Ok(DrivenFrame { coarse, fine })
    }

    /// The first half of `drive`: the splatted `[B, C, H, W]` feature image.
    pub fn splat_coarse(
        &self,
        avatar: &Avatar,
        vertices: &Tensor,
        transform: &Tensor,
    ) -> Result<Tensor> {
        splat_coarse(&self.cfg, avatar, vertices, transform)
    }

    /// The neural renderer alone (coarse `[B, C, H, W]` -> fine RGB); with the
    /// `no_neural_renderer` ablation, the coarse RGB channels.
    pub fn render(&self, coarse: &Tensor, noise: Noise) -> Result<Tensor> {
        render_fine(&self.cfg, &self.renderer, coarse, noise)
    }

    /// The training pass (spec 1: both phases in one differentiable graph): source `i`
    /// (`[B, 3, H, W]` in [0, 1], camera `[B, 3, 4]`) is reconstructed exactly as
    /// [`Self::reconstruct`] does and drives target `i` (vertices `[B, V, 3]`, already scaled
    /// by 5; camera `[B, 3, 4]`). Gradients reach every weight that is a variable (see
    /// [`crate::train::trainable_model`]); for reproducible runs pass [`Noise::Seeded`].
    pub fn train_forward(
        &self,
        source_image: &Tensor,
        source_transform: &Tensor,
        target_vertices: &Tensor,
        target_transform: &Tensor,
        noise: Noise,
    ) -> Result<TrainOutput> {
        let b = source_image.dims().first().copied().unwrap_or(0);
        let tb = target_vertices.dims().first().copied().unwrap_or(0);
        if b != tb {
            return Err(input_err(
                "target vertices",
                format!("batch {tb} does not match the {b} source images (one target each)"),
            ));
        }
        let avatar = self.reconstruct(source_image, source_transform)?;
        let coarse = self.splat_coarse(&avatar, target_vertices, target_transform)?;
        let fine = self.render(&coarse, noise)?;
        Ok(TrainOutput {
            avatar,
            coarse,
            fine,
        })
    }

    /// Every weight the model computes with, under its checkpoint key: all of
    /// [`crate::checkpoint::expected_keys`] but the renderer's `toRGB.*`, which the release
    /// holds and never uses. Values in the checkpoint's order; a few renderer weights come
    /// without the checkpoint's leading or trailing 1s (`[1, c, 1, 1]` biases as `[c]`).
    pub fn named_weights(&self) -> Result<Vec<(String, Tensor)>> {
        let mut out = Vec::new();
        for (k, t) in self.dino.named_weights()? {
            out.push((format!("{}{k}", crate::config::BACKBONE_PREFIX), t));
        }
        for (k, t) in self.dpt.named_weights()? {
            out.push((format!("base_model.{k}"), t));
        }
        out.push(("head_base".to_string(), self.head_base.clone()));
        let gens = [
            ("gs_generator_g", self.gen_g.named_weights()),
            ("gs_generator_l0", self.gen_l0.named_weights()),
            ("gs_generator_l1", self.gen_l1.named_weights()),
        ];
        for (prefix, list) in gens {
            for (k, t) in list {
                out.push((format!("{prefix}.{k}"), t));
            }
        }
        for (k, t) in self.renderer.named_weights() {
            out.push((format!("upsampler.{k}"), t));
        }
        Ok(out)
    }

    /// Weights the model holds as fixed tensors rather than variables, under their checkpoint
    /// keys in the checkpoint's layout: the DINOv2 backbone when it is not trainable, and the
    /// renderer's noise buffers (buffers in the release, never trained).
    pub fn fixed_weights(&self) -> Result<Vec<(String, Tensor)>> {
        let mut out = Vec::new();
        if !self.dino.is_trainable() {
            for (k, t) in self.dino.named_weights()? {
                out.push((format!("{}{k}", crate::config::BACKBONE_PREFIX), t));
            }
        }
        for (i, t) in self.renderer.decoder().noise_buffers().iter().enumerate() {
            out.push((
                format!("upsampler.stylegan_decoder.noises.noise{i}"),
                t.clone(),
            ));
        }
        Ok(out)
    }
}

/// The outputs of [`GagAvatar::train_forward`], all in one graph.
#[derive(Debug, Clone)]
pub struct TrainOutput {
    /// The reconstructed avatar; `avatar.lifted_xyz` `[B, 2 S^2, 3]` feeds the point loss.
    pub avatar: Avatar,
    /// Splatted features `[B, C, H, W]`; channels 0..3 are the coarse RGB.
    pub coarse: Tensor,
    /// The fine RGB `[B, 3, H, W]`.
    pub fine: Tensor,
}

/// The first half of a drive, which needs only the configuration: the avatar's Gaussians, the
/// expression ones at `vertices` `[B, V, 3]` (already scaled by 5), splatted from the cameras
/// `transform` `[B, 3, 4]` into the `[B, C, H, W]` feature image.
pub fn splat_coarse(
    cfg: &ModelConfig,
    avatar: &Avatar,
    vertices: &Tensor,
    transform: &Tensor,
) -> Result<Tensor> {
    let g = coarse_gaussians(cfg, avatar, vertices, transform)?;
    let background = Tensor::zeros(cfg.color_dim, g.features.dtype(), g.features.device())?;
    let out = splat(
        &Gaussians {
            means: &g.means,
            features: &g.features,
            opacities: &g.opacities,
            scales: &g.scales,
            rotations: &g.rotations,
        },
        &background,
        &g.cameras,
    )?;
    Ok(out.image)
}

/// What the coarse splatting of frames renders: per frame the head vertices followed by both
/// lifted point sets, with the avatar's attributes (batch-expanded) and the frames' cameras.
#[derive(Debug, Clone)]
pub struct CoarseGaussians {
    /// `[B, V + 2 S^2, 3]`
    pub means: Tensor,
    /// `[B, N, color_dim]`
    pub features: Tensor,
    /// `[B, N, 1]`
    pub opacities: Tensor,
    /// `[B, N, 3]`
    pub scales: Tensor,
    /// `[B, N, 4]`
    pub rotations: Tensor,
    pub cameras: Vec<Camera>,
}

/// The Gaussians and cameras [`splat_coarse`] renders, for a trainer that splats them itself
/// (on a GPU) and brings their gradients back.
pub fn coarse_gaussians(
    cfg: &ModelConfig,
    avatar: &Avatar,
    vertices: &Tensor,
    transform: &Tensor,
) -> Result<CoarseGaussians> {
    let v = cfg.n_vertices;
    let b = match vertices.dims() {
        [b, n, 3] if *b > 0 && *n == v => *b,
        other => {
            return Err(input_err(
                "target vertices",
                format!("expected [B, {v}, 3], got {other:?}"),
            ))
        }
    };
    check_finite(vertices, "target vertices")?;
    check_transform(transform, "target transform", Some(b))?;
    let ab = avatar.batch();
    if ab != b && ab != 1 {
        return Err(input_err(
            "avatar",
            format!("batch {ab} does not match {b} frames (use an avatar of batch 1 or {b})"),
        ));
    }
    let dtype = avatar.colors.dtype();
    let expand = |t: &Tensor| -> Result<Tensor> {
        Ok(if ab == b {
            t.clone()
        } else {
            let mut d = t.dims().to_vec();
            d[0] = b;
            t.broadcast_as(d)?.contiguous()?
        })
    };
    let lifted = expand(&avatar.lifted_xyz)?;
    let means = Tensor::cat(&[&vertices.to_dtype(dtype)?, &lifted], 1)?.contiguous()?;
    let features = expand(&avatar.colors)?.contiguous()?;
    let opacities = expand(&avatar.opacities)?.contiguous()?;
    let scales = expand(&avatar.scales)?.contiguous()?;
    let rotations = expand(&avatar.rotations)?.contiguous()?;
    let cams = cameras(transform, cfg.image_size)?;
    Ok(CoarseGaussians {
        means,
        features,
        opacities,
        scales,
        rotations,
        cameras: cams,
    })
}

/// The second half: the neural renderer (coarse `[B, C, H, W]` -> fine RGB); with the
/// `no_neural_renderer` ablation, the coarse RGB channels.
pub fn render_fine(
    cfg: &ModelConfig,
    renderer: &StyleUNet,
    coarse: &Tensor,
    noise: Noise,
) -> Result<Tensor> {
    if cfg.no_neural_renderer {
        return Ok(coarse.narrow(1, 0, 3)?.contiguous()?);
    }
    Ok(renderer.forward(coarse, noise)?)
}
