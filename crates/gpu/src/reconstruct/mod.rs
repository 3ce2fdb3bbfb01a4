//! `reconstruct` on the GPU (spec section 1, phase 1): the source photo and its camera in, the
//! avatar's Gaussians out, written straight into the buffers the drive's splatting reads.
//!
//! What runs where: the photo is uploaded as it is and resized on the GPU (the antialiased
//! resizes to the ViT's input and to DPT's four level sizes with the CPU path's own tap tables,
//! the ImageNet normalisation); the camera's point plane and direction encoding (S^2 x 3 + 30
//! values) are computed on the CPU and uploaded; every network layer runs on the GPU: DINOv2
//! ([`dino`]), the DPT head ([`dpt`]) and the three Gaussian generators ([`generators`]). The ViT keeps its tokens as the columns of
//! channel-major activations, so its linear layers are the renderer's 1x1 convolution kernel
//! (tensor cores included) with LayerScale and the residual in the epilogue.

pub mod dino;
pub mod dpt;
pub mod generators;
pub mod ops;
pub mod parts;

pub use parts::GpuAvatar;

use std::cell::Cell;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use candle_core::{DType, Tensor};
use gagavatar_net::config::{DIR_ENCODING_DIM, FOCAL};
use gagavatar_net::model::{Avatar, GagAvatar};
use gagavatar_net::ModelConfig;

use crate::device::Gpu;
use crate::error::{input_err, GpuError, Result};
use crate::kernel::{record_all, DispatchTime, Step};
use crate::tuning::Tuning;
use parts::{Ctx, Loader};

/// Names of the stages [`GpuReconstruct::profile`] times, in order.
pub const STAGES: [&str; 6] = [
    "upload (photo, camera plane)",
    "preprocess (resizes)",
    "dino",
    "dpt head",
    "gs_generator_g",
    "gs_generator_l0 + l1",
];

/// The inputs of one photo as they are uploaded.
struct HostInputs {
    photo: Vec<f32>,
    plane: Vec<f32>,
    encoding: Vec<f32>,
}

fn host(t: &Tensor, what: &str) -> Result<Vec<f32>> {
    crate::kernel::tensor_f32(t).map_err(|e| input_err(what, e.to_string()))
}

/// `reconstruct` on the GPU for one model: weights uploaded and every buffer and kernel built
/// once; [`GpuReconstruct::run`] then takes a photo and its camera to the Gaussians in
/// [`GpuReconstruct::avatar`].
pub struct GpuReconstruct {
    gpu: Arc<Gpu>,
    cfg: ModelConfig,
    /// `[3, S, S]`, the photo in [0, 1].
    photo: wgpu::Buffer,
    /// The plane's points `[S S, 3]` then the view direction `[3]`.
    plane: wgpu::Buffer,
    /// The direction encoding `[DIR_ENCODING_DIM]`.
    encoding: wgpu::Buffer,
    stages: Vec<Vec<Step>>,
    pub dino: dino::GpuDino,
    pub dpt: dpt::GpuDpt,
    pub avatar: GpuAvatar,
    /// Held from a run's upload until its avatar is read or copied: runs from several threads
    /// would otherwise overwrite each other's inputs and outputs.
    lock: std::sync::Mutex<()>,
    /// Kept alive for the recorded steps.
    _keep: Vec<wgpu::Buffer>,
}

impl GpuReconstruct {
    /// Uploads `model`'s weights and builds the pass (batch 1).
    pub fn new(gpu: Arc<Gpu>, tuning: &Tuning, model: &GagAvatar) -> Result<Self> {
        let weights: HashMap<String, Tensor> = model
            .named_weights()
            .map_err(|e| GpuError::Weights(e.to_string()))?
            .into_iter()
            .collect();
        Self::from_weights(gpu, tuning, &model.cfg, &weights)
    }

    /// [`GpuReconstruct::new`] from weights by checkpoint key.
    pub fn from_weights(
        gpu: Arc<Gpu>,
        tuning: &Tuning,
        cfg: &ModelConfig,
        weights: &HashMap<String, Tensor>,
    ) -> Result<Self> {
        cfg.validate().map_err(GpuError::Unsupported)?;
        let tuning = &tuning.for_device(&gpu);
        tuning.check(&gpu.limits)?;
        let g: &Gpu = &gpu;
        let mut ld = Loader {
            gpu: g,
            weights,
            vecs: Vec::new(),
        };
        let dino_w = dino::DinoWeights::load(&mut ld, cfg)?;
        let dpt_w = dpt::DptWeights::load(&mut ld, cfg)?;
        let gen_w = generators::GenWeights::load(&mut ld, cfg)?;
        let vecs = g.buffer_with("reconstruct vectors", &ld.vecs);
        let dummy = g.buffer("unused", 16);
        let spare = g.buffer("unused (written)", 16);

        let d = cfg.dino_size;
        let size = cfg.image_size;
        let photo = g.buffer("photo", 4 * (3 * size * size) as u64);
        let image = g.buffer("dino input", 4 * (3 * d * d) as u64);
        let level_sizes = [0, 1, 2, 3].map(|k| cfg.dpt_level_size(k));
        let mut resizes = vec![(size, d)];
        resizes.extend(level_sizes.map(|s| (d, s)));
        let taps = ops::TapTables::new(g, &resizes, gagavatar_ops::ResizeMode::Antialias);
        let normalize: ops::Normalize = (
            gagavatar_net::dino::IMAGENET_MEAN.map(|m| m as f32),
            gagavatar_net::dino::IMAGENET_STD.map(|s| (1.0 / s) as f32),
        );
        let dino = dino::GpuDino::new(g, cfg);
        let dpt = dpt::GpuDpt::new(g, cfg);
        let s = cfg.plane_size();
        let plane = g.buffer("plane", 4 * (3 * s * s + 3) as u64);
        let encoding = g.buffer("direction encoding", 4 * DIR_ENCODING_DIM as u64);
        let gens = generators::GenBuffers::new(g, cfg);
        let avatar = GpuAvatar::new(g, cfg);

        let record = |scratch: &wgpu::Buffer, measure: Option<&Cell<usize>>| {
            let ctx = Ctx {
                gpu: g,
                tuning,
                vecs: &vecs,
                dummy: &dummy,
                spare: &spare,
                scratch,
                measure,
            };
            let o = ctx.ops();
            let mut pre = vec![o.resize_taps(
                &taps,
                0,
                (3, size, d),
                Some(normalize),
                parts::At::new(&photo),
                parts::At::new(&image),
            )?];
            for (k, &s) in level_sizes.iter().enumerate() {
                pre.push(o.resize_taps(
                    &taps,
                    k + 1,
                    (3, d, s),
                    None,
                    parts::At::new(&image),
                    parts::At::new(&dpt.levels[k]),
                )?);
            }
            let dino_steps = dino.record(&ctx, &dino_w, &image)?;
            let dpt_steps = dpt.record(&ctx, &dpt_w, &dino.outs)?;
            let [gs, ls] = gens.record(
                &ctx,
                &gen_w,
                &dino,
                &dpt.f_local,
                (&plane, &encoding),
                &avatar,
            )?;
            Ok::<_, GpuError>(vec![pre, dino_steps, dpt_steps, gs, ls])
        };
        let need = Cell::new(0);
        record(&dummy, Some(&need))?;
        let scratch = g.buffer("split-K partial sums", 4 * need.get().max(1) as u64);
        let stages = record(&scratch, None)?;
        Ok(Self {
            gpu: gpu.clone(),
            cfg: cfg.clone(),
            photo,
            plane,
            encoding,
            stages,
            dino,
            dpt,
            avatar,
            lock: std::sync::Mutex::new(()),
            _keep: vec![
                vecs,
                dummy,
                spare,
                scratch,
                image,
                taps.starts,
                taps.weights,
            ],
        })
    }

    pub fn gpu(&self) -> &Gpu {
        &self.gpu
    }

    /// The device, shared.
    pub fn gpu_arc(&self) -> Arc<Gpu> {
        self.gpu.clone()
    }

    /// The CPU's part for a photo `[1, 3, H, W]` in [0, 1] and its camera `[1, 3, 4]`.
    fn host_inputs(&self, image: &Tensor, transform: &Tensor) -> Result<HostInputs> {
        let size = self.cfg.image_size;
        match image.dims() {
            [1, 3, h, w] if *h == size && *w == size => {}
            other => {
                return Err(input_err(
                    "source image",
                    format!("expected [1, 3, {size}, {size}], got {other:?}"),
                ))
            }
        }
        if transform.dims() != [1, 3, 4] {
            return Err(input_err(
                "source transform",
                format!("expected [1, 3, 4], got {:?}", transform.dims()),
            ));
        }
        let img = host(image, "source image")?;
        if let Some(i) = img.iter().position(|v| !v.is_finite()) {
            return Err(input_err(
                "source image",
                format!("value {i} is not finite"),
            ));
        }
        let tm = host(transform, "source transform")?;
        if tm.iter().any(|v| !v.is_finite()) {
            return Err(input_err(
                "source transform",
                "contains NaN or infinite values",
            ));
        }
        let cpu = |e: candle_core::Error| input_err("source", e.to_string());
        let transform = transform.to_dtype(DType::F32).map_err(cpu)?;
        let s = self.cfg.plane_size();
        let (points, dir) = gagavatar_net::plane::point_plane(&transform, s, FOCAL).map_err(cpu)?;
        let enc = gagavatar_net::plane::dir_encoding(&dir).map_err(cpu)?;
        let mut plane = host(&points, "plane")?;
        plane.extend(host(&dir, "view direction")?);
        Ok(HostInputs {
            photo: img,
            plane,
            encoding: host(&enc, "direction encoding")?,
        })
    }

    fn upload(&self, inputs: &HostInputs) {
        let q = &self.gpu.queue;
        q.write_buffer(&self.photo, 0, bytemuck::cast_slice(&inputs.photo));
        q.write_buffer(&self.plane, 0, bytemuck::cast_slice(&inputs.plane));
        q.write_buffer(&self.encoding, 0, bytemuck::cast_slice(&inputs.encoding));
    }

    fn submit(&self, stages: &[Vec<Step>]) {
        let mut enc = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("reconstruct"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            for s in stages {
                record_all(&mut pass, s);
            }
        }
        self.gpu.queue.submit([enc.finish()]);
    }

    fn locked(&self) -> std::sync::MutexGuard<'_, ()> {
        // The guard protects no data of its own: a panic while held leaves nothing broken.
        self.lock.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn run_locked(&self, image: &Tensor, transform: &Tensor) -> Result<()> {
        let inputs = self.host_inputs(image, transform)?;
        self.upload(&inputs);
        self.submit(&self.stages);
        self.gpu.wait()
    }

    /// Reconstructs the photo `[1, 3, H, W]` (values in [0, 1]) seen from `transform`
    /// `[1, 3, 4]` into [`GpuReconstruct::avatar`], and waits for the GPU.
    pub fn run(&self, image: &Tensor, transform: &Tensor) -> Result<()> {
        let _guard = self.locked();
        self.run_locked(image, transform)
    }

    /// The frozen backbone alone for a trainer that runs the rest of the reconstruction
    /// elsewhere: the photo `[1, 3, H, W]` preprocessed and through DINOv2, the four outputs
    /// DPT reads read back as `gagavatar_net::dino::Dinov2::forward` returns them
    /// (`[grid^2, vit_dim]` each, patches row-major). `transform` only fills the buffers the
    /// other stages would read.
    pub fn backbone(&self, image: &Tensor, transform: &Tensor) -> Result<[Vec<f32>; 4]> {
        let _guard = self.locked();
        let inputs = self.host_inputs(image, transform)?;
        self.upload(&inputs);
        self.submit(&self.stages[..2]);
        let (c, g) = (self.dino.c, self.dino.g);
        let mut out: [Vec<f32>; 4] = Default::default();
        for (o, buf) in out.iter_mut().zip(&self.dino.outs) {
            let cm = self.gpu.read_f32(buf, c * g)?;
            let mut t = vec![0f32; g * c];
            for ch in 0..c {
                for tok in 0..g {
                    t[tok * c + ch] = cm[ch * g + tok];
                }
            }
            *o = t;
        }
        Ok(out)
    }

    /// [`GpuReconstruct::run`] into an avatar of its own on the device (the pass's buffers
    /// are overwritten by the next run).
    pub fn run_owned(&self, image: &Tensor, transform: &Tensor) -> Result<GpuAvatar> {
        let _guard = self.locked();
        self.run_locked(image, transform)?;
        Ok(self.avatar.duplicate(&self.gpu))
    }

    /// [`GpuReconstruct::run`] with each of [`STAGES`] submitted and waited for alone:
    /// milliseconds of wall time per stage (a stage's time includes one submission).
    pub fn profile(&self, image: &Tensor, transform: &Tensor) -> Result<[f64; 6]> {
        let _guard = self.locked();
        let mut ms = [0f64; 6];
        let t0 = Instant::now();
        let inputs = self.host_inputs(image, transform)?;
        self.upload(&inputs);
        self.gpu.wait()?;
        ms[0] = 1e3 * t0.elapsed().as_secs_f64();
        for (i, stage) in self.stages.iter().enumerate() {
            let t = Instant::now();
            self.submit(std::slice::from_ref(stage));
            self.gpu.wait()?;
            ms[i + 1] = 1e3 * t.elapsed().as_secs_f64();
        }
        Ok(ms)
    }

    /// Every dispatch of a run timed alone on the device (after a whole run, so each reads
    /// real inputs), with its stage of [`STAGES`]; `None` where the adapter has no timestamp
    /// queries.
    pub fn profile_dispatches(
        &self,
        image: &Tensor,
        transform: &Tensor,
    ) -> Result<Option<Vec<DispatchTime>>> {
        let _guard = self.locked();
        self.run_locked(image, transform)?;
        let steps: Vec<(&'static str, &Step)> = self
            .stages
            .iter()
            .enumerate()
            .flat_map(|(i, st)| st.iter().map(move |s| (STAGES[i + 1], s)))
            .collect();
        crate::kernel::time_dispatches(&self.gpu, &steps)
    }

    /// Every dispatch of the pass in order with its kernel's name and note (for profiles).
    pub fn steps(&self) -> impl Iterator<Item = &Step> {
        self.stages.iter().flatten()
    }

    /// [`GpuReconstruct::run`], then the Gaussians read back as an [`Avatar`].
    pub fn reconstruct(&self, image: &Tensor, transform: &Tensor) -> Result<Avatar> {
        let _guard = self.locked();
        self.run_locked(image, transform)?;
        self.avatar.download(&self.gpu)
    }
}

#[cfg(test)]
mod tests;
