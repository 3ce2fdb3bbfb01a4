//! `train --device gpu`'s rendering half ([`gagavatar_train::RenderHalf`]) on wgpu: per
//! sample the Gaussians uploaded into one reused splat, the training forward of the splatting
//! and of the renderer with the sample's noise, the image and head-box terms, the perceptual
//! term when built with it ([`GpuPerceptual`]), and on the backward the caller's crop
//! gradients added (a perceptual term computed elsewhere), then the chain of [`super::render_step`]:
//! renderer backward, the two gradients of the splatted image summed, splatting backward.

use std::collections::HashMap;

use candle_core::{Device, Tensor};
use gagavatar_net::model::GagAvatar;
use gagavatar_net::style_unet::noise_resolution;
use gagavatar_net::ModelConfig;
use gagavatar_train::render_half::{
    BackendError, LiftSample, LiftedGaussians, RenderForward, RenderGrads, RenderHalf, RenderSample,
};

use crate::device::Gpu;
use crate::error::{input_err, Result};
use crate::grad::crop::CropBox;
use crate::grad::dpt::GpuDptGrad;
use crate::grad::image_loss::GpuImageLosses;
use crate::grad::lift::{GpuLiftGrad, LiftInput};
use crate::grad::perceptual::{CropBuffers, GpuPerceptual};
use crate::grad::renderer::GpuRendererGrad;
use crate::grad::splat::GpuSplatGrad;
use crate::kernel::{linear_grid, Bind, Params, Step};
use crate::reconstruct::GpuReconstruct;
use crate::splat::{GpuSplat, SplatInputs};
use crate::tuning::Tuning;

const ADD: &str = include_str!("../shaders/add.wgsl");

/// Each renderer gradient buffer's weighted sum over a step's samples: one accumulator per
/// gradient buffer (packed parameters share theirs, at the same offsets), the additions
/// recorded once with a shared scale, read back once per step.
struct Accumulated {
    /// (the module's buffers: 0 the U-Net's, 1 the decoder's; buffer index; accumulator)
    bufs: Vec<(usize, usize, wgpu::Buffer)>,
    scale: wgpu::Buffer,
    steps: Vec<Step>,
    /// Samples added since the last read.
    samples: usize,
}

const ACCUMULATE: &str = include_str!("../shaders/accumulate.wgsl");

impl Accumulated {
    fn new(gpu: &Gpu, r: &GpuRendererGrad) -> Result<Self> {
        let k = gpu.kernel(
            "accumulate",
            ACCUMULATE,
            &[],
            &[Bind::Uniform, Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let scale = gpu.uniform("accumulate scale", &Params::new().f(1.0).u(1).u(0).u(0));
        let mut bufs = Vec::new();
        let mut steps = Vec::new();
        let modules: [(&[wgpu::Buffer], &[crate::grad::params::Param]); 2] = [
            (&r.buffers, &r.params),
            (&r.decoder.buffers, &r.decoder.params),
        ];
        for (m, (buffers, params)) in modules.into_iter().enumerate() {
            let mut seen = std::collections::BTreeSet::new();
            for p in params {
                if !seen.insert(p.grad) {
                    continue;
                }
                let g = &buffers[p.grad];
                let n = (g.size() / 4) as usize;
                let acc = gpu.buffer("accumulated gradient", g.size());
                let u = gpu.uniform("accumulate", &Params::new().u(n as u32).u(0).u(0).u(0));
                let bg = gpu.bind(&k, &[&u, &scale, g, &acc])?;
                steps.push(Step::new(k.clone(), bg, linear_grid(n, 256)));
                bufs.push((m, p.grad, acc));
            }
        }
        Ok(Self {
            bufs,
            scale,
            steps,
            samples: 0,
        })
    }

    /// Adds `scale` times the renderer's current gradients.
    fn add(&mut self, gpu: &Gpu, scale: f32) {
        let first = u32::from(self.samples == 0);
        gpu.queue.write_buffer(
            &self.scale,
            0,
            bytemuck::cast_slice(&Params::new().f(scale).u(first).u(0).u(0).words()),
        );
        gpu.submit(&self.steps);
        self.samples += 1;
    }

    /// The sums by parameter key, and a fresh start.
    fn read(&mut self, gpu: &Gpu, r: &GpuRendererGrad) -> Result<Vec<(String, Vec<f32>)>> {
        if self.samples == 0 {
            return Err(input_err(
                "renderer gradients",
                "no backward since the last read",
            ));
        }
        // Each accumulator read once (packed parameters share one).
        let mut read = std::collections::HashMap::new();
        for (m, i, acc) in &self.bufs {
            read.insert((*m, *i), gpu.read_f32(acc, (acc.size() / 4) as usize)?);
        }
        let mut out = Vec::new();
        let modules: [&[crate::grad::params::Param]; 2] = [&r.params, &r.decoder.params];
        for (m, params) in modules.into_iter().enumerate() {
            for p in params {
                let Some(all) = read.get(&(m, p.grad)) else {
                    return Err(input_err("renderer gradients", "no accumulator"));
                };
                out.push((p.key.clone(), all[p.offset..p.offset + p.len].to_vec()));
            }
        }
        self.samples = 0;
        Ok(out)
    }
}

/// What a forward leaves for its backward.
struct Pending {
    losses: GpuImageLosses,
    d_loss: wgpu::Buffer,
}

/// The rendering half on one GPU (see the module's text).
pub struct GpuRenderHalf {
    gpu: std::sync::Arc<Gpu>,
    tuning: Tuning,
    size: usize,
    channels: usize,
    renderer: GpuRendererGrad,
    /// The head-box crops, kept from sample to sample, and the perceptual term on them.
    crops: CropBuffers,
    percep: Option<GpuPerceptual>,
    /// The frozen backbone (the reconstruction's first stages), when asked for.
    backbone: Option<GpuReconstruct>,
    /// The lifting generators, when asked for.
    lift: Option<GpuLiftGrad>,
    /// The DPT head, when asked for (with the backbone and the lifting generators).
    dpt: Option<GpuDptGrad>,
    /// Whether the last lifting forward read the DPT head's `F_local` (its gradient then goes
    /// on into the head's backward).
    lift_from_dpt: bool,
    /// The step's renderer gradients summed on the device (see [`Accumulated`]).
    acc: Accumulated,
    /// The splat and its backward, rebuilt when the Gaussian count changes.
    splat: Option<(GpuSplat, GpuSplatGrad)>,
    pending: Option<Pending>,
    background: Vec<f32>,
}

impl GpuRenderHalf {
    /// Records the renderer's training forward and backward for `cfg` with `weights` (keys
    /// relative to `upsampler.`; every later step uploads its own with
    /// [`RenderHalf::set_renderer_weights`]), head-box crops of `box_size`, and with `percep`
    /// (the networks' weights by key without `percep_loss.`, and the term's factor) the
    /// perceptual term on them.
    pub fn new(
        gpu: std::sync::Arc<Gpu>,
        tuning: &Tuning,
        cfg: &ModelConfig,
        weights: &HashMap<String, Vec<f32>>,
        box_size: usize,
        percep: Option<(&HashMap<String, Vec<f32>>, f64)>,
    ) -> Result<Self> {
        // The noise maps are buffers, not trained weights: each sample brings its own.
        let mut noise = HashMap::new();
        for i in 0..2 * cfg.renderer_levels() + 1 {
            let r = noise_resolution(i);
            noise.insert(
                format!("stylegan_decoder.noises.noise{i}"),
                vec![0f32; r * r],
            );
        }
        let get = |key: &str| {
            weights
                .get(key)
                .or_else(|| noise.get(key))
                .cloned()
                .ok_or_else(|| crate::GpuError::Weights(format!("no upsampler.{key}")))
        };
        let renderer = GpuRendererGrad::new(&gpu, tuning, cfg, &get)?;
        let crops = CropBuffers::new(&gpu, box_size);
        let acc = Accumulated::new(&gpu, &renderer)?;
        let percep = match percep {
            Some((w, factor)) => Some(GpuPerceptual::new(&gpu, tuning, w, &crops, factor)?),
            None => None,
        };
        Ok(Self {
            tuning: tuning.clone(),
            size: cfg.image_size,
            channels: cfg.color_dim,
            renderer,
            crops,
            percep,
            backbone: None,
            lift: None,
            dpt: None,
            lift_from_dpt: false,
            acc,
            splat: None,
            pending: None,
            background: vec![0.0; cfg.color_dim],
            gpu,
        })
    }

    /// Also runs the frozen backbone (DINOv2) of `model`'s reconstruction for the trainer
    /// (its weights never change; the other stages' copies are not used).
    pub fn with_backbone(mut self, model: &GagAvatar) -> Result<Self> {
        // f32, as the rest of the step (the f16 tensor-core path is for inference).
        let tuning = Tuning {
            mma: false,
            ..self.tuning.clone()
        };
        self.backbone = Some(GpuReconstruct::new(self.gpu.clone(), &tuning, model)?);
        Ok(self)
    }

    /// Also runs the lifting generators (`gs_generator_l0` / `l1`) with `weights` by
    /// checkpoint key (every step uploads its own with [`RenderHalf::set_lifting_weights`]).
    pub fn with_lifting(
        mut self,
        cfg: &ModelConfig,
        weights: &HashMap<String, Vec<f32>>,
    ) -> Result<Self> {
        self.lift = Some(
            GpuLiftGrad::new(&self.gpu, &self.tuning, cfg, weights)?
                .with_lifting_term(&self.gpu, cfg.n_vertices)?,
        );
        Ok(self)
    }

    /// Also runs the DPT head with `weights` by checkpoint key (every step uploads its own
    /// with [`RenderHalf::set_dpt_weights`]): `F_local` then stays on the device between the
    /// head and the lifting generators, both ways. Needs the backbone and the lifting
    /// generators (build with [`GpuRenderHalf::with_backbone`] and
    /// [`GpuRenderHalf::with_lifting`] first).
    pub fn with_dpt(
        mut self,
        cfg: &ModelConfig,
        weights: &HashMap<String, Vec<f32>>,
    ) -> Result<Self> {
        if self.backbone.is_none() || self.lift.is_none() {
            return Err(input_err(
                "render half",
                "the DPT head on the device needs the backbone and the lifting generators there",
            ));
        }
        self.dpt = Some(GpuDptGrad::new(&self.gpu, &self.tuning, cfg, weights)?);
        Ok(self)
    }

    /// The device and the DPT head, or the error of a half built without it.
    fn dpt(&mut self) -> std::result::Result<(&Gpu, &mut GpuDptGrad), BackendError> {
        match &mut self.dpt {
            Some(d) => Ok((&self.gpu, d)),
            None => Err("built without the DPT head".into()),
        }
    }

    /// The device and the lifting generators, or the error of a half built without them.
    fn lifting(&mut self) -> std::result::Result<(&Gpu, &mut GpuLiftGrad), BackendError> {
        match &mut self.lift {
            Some(l) => Ok((&self.gpu, l)),
            None => Err("built without the lifting generators".into()),
        }
    }

    fn forward_sample(
        &mut self,
        s: &RenderSample,
        box_size: usize,
        crops: bool,
    ) -> Result<RenderForward> {
        let gpu = &*self.gpu;
        let (c, size) = (self.channels, self.size);
        if box_size != self.crops.size {
            return Err(input_err(
                "render sample",
                format!(
                    "head-box crops of {box_size}, built for {}",
                    self.crops.size
                ),
            ));
        }
        if s.channels != c || s.target.len() != 3 * size * size {
            return Err(input_err(
                "render sample",
                format!(
                    "{} channels and {} target values for a {c}-channel {size}x{size} renderer",
                    s.channels,
                    s.target.len()
                ),
            ));
        }
        let inputs = SplatInputs {
            means: s.means,
            features: s.features,
            channels: c,
            opacities: s.opacities,
            scales: s.scales,
            rotations: s.rotations,
            background: &self.background,
        };
        let reuse = matches!(&self.splat, Some((sp, _)) if sp.n == s.opacities.len());
        if reuse {
            if let Some((sp, _)) = &self.splat {
                sp.set_gaussians(gpu, &inputs)?;
            }
        } else {
            self.pending = None;
            let sp = GpuSplat::new(gpu, &self.tuning, &inputs, None, 0, size, size)?;
            let sg = GpuSplatGrad::new(gpu, &sp)?;
            self.splat = Some((sp, sg));
        }
        let Some((sp, sg)) = self.splat.as_mut() else {
            return Err(input_err("render sample", "no splat"));
        };
        sg.forward(gpu, sp, s.camera)?;
        self.renderer.set_noise(gpu, s.noise)?;
        let image_bytes = 4 * (c * size * size) as u64;
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("splatted image to the renderer"),
            });
        enc.copy_buffer_to_buffer(&sp.image, 0, &self.renderer.input, 0, image_bytes);
        gpu.queue.submit([enc.finish()]);
        gpu.submit(self.renderer.forward_steps());

        let target = gpu.buffer_with("target", s.target);
        let d_loss = gpu.buffer("dL/dcoarse (loss terms)", image_bytes);
        let hb = s.head_box;
        let losses = GpuImageLosses::with_crops(
            gpu,
            (c, size, size),
            CropBox {
                x0: hb.x0,
                y0: hb.y0,
                x1: hb.x1,
                y1: hb.y1,
            },
            self.crops.clone(),
            &sp.image,
            &self.renderer.output,
            &target,
            &d_loss,
            &self.renderer.grad_output,
        )?;
        gpu.submit(losses.forward_steps());
        // The perceptual term adds its gradients to the box terms' before the crops' backward.
        if let Some(p) = &self.percep {
            gpu.submit(p.steps());
        }
        let terms = losses.read(gpu)?;
        let percep = match &self.percep {
            Some(p) => Some(p.read(gpu)?),
            None => None,
        };
        let crops = if crops {
            Some(losses.read_crops(gpu)?)
        } else {
            None
        };
        self.pending = Some(Pending { losses, d_loss });
        Ok(RenderForward {
            img: terms.img as f64,
            box_l1: terms.box_l1 as f64,
            percep,
            crops,
        })
    }

    fn backward_sample(
        &mut self,
        crop_grads: Option<[&[f32]; 2]>,
        renderer_scale: f32,
    ) -> Result<RenderGrads> {
        let gpu = &*self.gpu;
        let (Some(p), Some((sp, sg))) = (self.pending.take(), self.splat.as_ref()) else {
            return Err(input_err(
                "render backward",
                "no forward to go back through",
            ));
        };
        if let Some([c, f]) = crop_grads {
            p.losses.add_crop_grads(gpu, c, f)?;
        }
        gpu.submit(p.losses.backward_steps());
        gpu.submit(self.renderer.backward_steps());
        let k = gpu.kernel(
            "add",
            ADD,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let n = sp.channels * sp.width * sp.height;
        let u = gpu.uniform("add", &Params::new().u(n as u32));
        let add = Step::new(
            k.clone(),
            gpu.bind(
                &k,
                &[&u, &p.d_loss, &self.renderer.grad_input, &sg.grad_image],
            )?,
            linear_grid(n, 256),
        );
        gpu.submit(std::slice::from_ref(&add));
        sg.submit_backward(gpu);
        self.acc.add(gpu, renderer_scale);
        let g = sg.read(gpu)?;
        let rows = |first: usize, width: usize| -> Vec<f32> {
            g.geom
                .chunks_exact(11)
                .flat_map(|r| r[first..first + width].iter().copied())
                .collect()
        };
        Ok(RenderGrads {
            means: rows(0, 3),
            opacities: rows(3, 1),
            scales: rows(4, 3),
            rotations: rows(7, 4),
            features: g.features,
        })
    }
}

impl RenderHalf for GpuRenderHalf {
    fn describe(&self) -> String {
        self.gpu.describe()
    }

    fn has_percep(&self) -> bool {
        self.percep.is_some()
    }

    fn has_backbone(&self) -> bool {
        self.backbone.is_some()
    }

    fn backbone(
        &mut self,
        image: &[f32],
        transform: &[f32],
    ) -> std::result::Result<[Vec<f32>; 4], BackendError> {
        let Some(r) = &self.backbone else {
            return Err("built without the backbone".into());
        };
        let s = self.size;
        let image = Tensor::from_slice(image, (1, 3, s, s), &Device::Cpu)?;
        let transform = Tensor::from_slice(transform, (1, 3, 4), &Device::Cpu)?;
        Ok(r.backbone(&image, &transform)?)
    }

    fn has_lifting(&self) -> bool {
        self.lift.is_some()
    }

    fn set_lifting_weights(
        &mut self,
        weights: &HashMap<String, Vec<f32>>,
    ) -> std::result::Result<(), BackendError> {
        let (gpu, l) = self.lifting()?;
        let value = |key: &str| weights.get(key).map(|v| v.as_slice());
        Ok(l.set_weights(gpu, &value)?)
    }

    fn lift_forward(
        &mut self,
        s: &LiftSample,
    ) -> std::result::Result<LiftedGaussians, BackendError> {
        let gpu = &*self.gpu;
        let (Some(l), dpt) = (&mut self.lift, &self.dpt) else {
            return Err("built without the lifting generators".into());
        };
        let input = match (s.f_local, dpt) {
            (Some(v), _) => LiftInput::Host(v),
            (None, Some(d)) => LiftInput::Device(d.f_local()),
            (None, None) => return Err("no F_local given, and no DPT head here".into()),
        };
        self.lift_from_dpt = s.f_local.is_none();
        let mut lifted = l.forward(gpu, input, s.encoding, s.plane_points, s.plane_dir)?;
        if let Some(t) = s.targets {
            lifted.point = Some(l.lifting_term(gpu, t, s.term_scale)?);
        }
        Ok(lifted)
    }

    fn lift_backward(
        &mut self,
        grads: &LiftedGaussians,
    ) -> std::result::Result<Vec<f32>, BackendError> {
        if !self.lift_from_dpt {
            let (gpu, l) = self.lifting()?;
            return Ok(l.backward(gpu, grads)?);
        }
        let gpu = &*self.gpu;
        let (Some(l), Some(d)) = (&mut self.lift, &mut self.dpt) else {
            return Err("built without the lifting generators or the DPT head".into());
        };
        l.backward_on_device(gpu, grads)?;
        d.backward_from(gpu, l.grad_f_local())?;
        Ok(Vec::new())
    }

    fn lifting_grads(&mut self) -> std::result::Result<Vec<(String, Vec<f32>)>, BackendError> {
        let (gpu, l) = self.lifting()?;
        Ok(l.read_grads(gpu)?)
    }

    fn has_dpt(&self) -> bool {
        self.dpt.is_some()
    }

    fn set_dpt_weights(
        &mut self,
        weights: &HashMap<String, Vec<f32>>,
    ) -> std::result::Result<(), BackendError> {
        let (gpu, d) = self.dpt()?;
        let value = |key: &str| weights.get(key).map(|v| v.as_slice());
        Ok(d.set_weights(gpu, &value)?)
    }

    fn dpt_forward(
        &mut self,
        tokens: [&[f32]; 4],
        image: &[f32],
    ) -> std::result::Result<(), BackendError> {
        let (gpu, d) = self.dpt()?;
        Ok(d.forward(gpu, tokens, image)?)
    }

    fn dpt_grads(&mut self) -> std::result::Result<Vec<(String, Vec<f32>)>, BackendError> {
        let (gpu, d) = self.dpt()?;
        Ok(d.read_grads(gpu)?)
    }

    fn set_renderer_weights(
        &mut self,
        weights: &HashMap<String, Vec<f32>>,
    ) -> std::result::Result<(), BackendError> {
        let value = |key: &str| weights.get(key).map(|v| v.as_slice());
        // A new step: its sums start from nothing (even after a step that failed midway).
        self.acc.samples = 0;
        Ok(self.renderer.set_weights(&self.gpu, &value)?)
    }

    fn forward(
        &mut self,
        sample: &RenderSample,
        box_size: usize,
        crops: bool,
    ) -> std::result::Result<RenderForward, BackendError> {
        Ok(self.forward_sample(sample, box_size, crops)?)
    }

    fn backward(
        &mut self,
        crop_grads: Option<[&[f32]; 2]>,
        renderer_scale: f32,
    ) -> std::result::Result<RenderGrads, BackendError> {
        Ok(self.backward_sample(crop_grads, renderer_scale)?)
    }

    fn renderer_grads(&mut self) -> std::result::Result<Vec<(String, Vec<f32>)>, BackendError> {
        Ok(self.acc.read(&self.gpu, &self.renderer)?)
    }
}
