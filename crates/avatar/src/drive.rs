//! Driving an avatar: FLAME with the source identity and each frame's codes, splatting the
//! Gaussians from the frame's camera, and the neural renderer; one trait, a CPU and a GPU
//! implementation.

use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::{Duration, Instant};

use candle_core::{Device, Tensor};
use gagavatar_flame::{FlameIdentity, FlameModel};
use gagavatar_gpu::flame::FrameCodes;
use gagavatar_gpu::Gpu;
use gagavatar_net::model::{render_fine, splat_coarse, Avatar as Gaussians};
use gagavatar_net::style_unet::{Noise, StyleUNet};
use gagavatar_net::ModelConfig;

use crate::convert::{to_rgb8, transforms_tensor};
use crate::error::{input_err, Result};

/// A camera: the 3x4 world-to-camera transform of a tracked record (`transform_matrix`).
pub type Camera = [[f64; 4]; 3];

/// Time spent per stage, summed over the frames rendered so far.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DriveTimes {
    pub flame: Duration,
    pub splat: Duration,
    pub renderer: Duration,
    /// The whole drive (FLAME, splatting, renderer, read-back) where it runs on a GPU, whose
    /// stages are not timed apart here.
    pub gpu: Duration,
    pub frames: usize,
}

/// Renders frames of one avatar. Frames are RGB u8, row-major, `image_size()` square
/// (`3 * size * size` bytes). With fixed noise the same codes and camera give the same frame
/// again; another batch size may differ by one 8-bit level (the batched sums round otherwise).
pub trait Drive {
    /// The side of the square frames.
    fn image_size(&self) -> usize;

    /// Renders every `(codes, camera)` in order.
    fn render_batch(&mut self, frames: &[(FrameCodes, Camera)]) -> Result<Vec<Vec<u8>>>;

    /// Renders one frame.
    fn render(&mut self, codes: &FrameCodes, camera: &Camera) -> Result<Vec<u8>> {
        let mut out = self.render_batch(&[(codes.clone(), *camera)])?;
        out.pop()
            .ok_or_else(|| input_err("render", "the drive returned no frame"))
    }

    /// Renders every `(codes, camera)` in order, handing each frame to `each` as it is ready
    /// (the CPU drive renders `batch` frames at a time; the GPU drive renders one while the
    /// previous one is read back, whatever `batch` is). `each` returning `Break` stops early.
    /// Returns how many frames `each` received.
    fn render_stream(
        &mut self,
        frames: &[(FrameCodes, Camera)],
        batch: usize,
        each: &mut dyn FnMut(usize, Vec<u8>) -> ControlFlow<()>,
    ) -> Result<usize> {
        let batch = batch.max(1);
        let mut done = 0;
        for (c, chunk) in frames.chunks(batch).enumerate() {
            for (k, img) in self.render_batch(chunk)?.into_iter().enumerate() {
                done += 1;
                if each(c * batch + k, img).is_break() {
                    return Ok(done);
                }
            }
        }
        Ok(done)
    }

    /// The stage times so far.
    fn times(&self) -> DriveTimes;
}

/// Refuses a camera with a non-finite value, naming frame `i`.
pub(crate) fn check_camera(camera: &Camera, i: usize) -> Result<()> {
    if camera.iter().flatten().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(input_err(
            format!("camera of frame {i}"),
            "a value is not finite",
        ))
    }
}

/// The CPU drive: the model's own forward pass (candle + our kernels), the project's one CPU
/// implementation of a frame.
pub struct CpuDrive {
    cfg: ModelConfig,
    renderer: StyleUNet,
    flame: Arc<FlameModel>,
    gaussians: Gaussians,
    identity: FlameIdentity,
    noise: Noise,
    times: DriveTimes,
}

impl CpuDrive {
    /// A drive from its parts alone, without the reconstruction half of a model (benchmarks
    /// drive release-size scenes without building the ViT): the architecture, its neural
    /// renderer, FLAME with the source identity, and the avatar's Gaussians.
    pub fn from_parts(
        cfg: ModelConfig,
        renderer: StyleUNet,
        flame: Arc<FlameModel>,
        gaussians: Gaussians,
        identity: FlameIdentity,
        noise: Noise,
    ) -> Self {
        CpuDrive {
            cfg,
            renderer,
            flame,
            gaussians,
            identity,
            noise,
            times: DriveTimes::default(),
        }
    }

    /// The coarse 32-channel splatted images and the fine RGB images `[B, 3, S, S]` in [0, 1]
    /// (for evaluation and parity checks that need more than 8-bit frames).
    pub fn render_tensors(&mut self, frames: &[(FrameCodes, Camera)]) -> Result<(Tensor, Tensor)> {
        if frames.is_empty() {
            return Err(input_err("render", "no frames"));
        }
        let n_exp = self.flame.config.n_exp;
        let dev = Device::Cpu;
        let mut exp = Vec::with_capacity(frames.len() * n_exp);
        let mut pose = Vec::with_capacity(frames.len() * 6);
        let mut eye = Vec::with_capacity(frames.len() * 6);
        for (i, (c, cam)) in frames.iter().enumerate() {
            if c.expression.len() != n_exp {
                return Err(input_err(
                    format!("codes of frame {i}"),
                    format!(
                        "{} expression values, this FLAME has {n_exp}",
                        c.expression.len()
                    ),
                ));
            }
            check_camera(cam, i)?;
            exp.extend_from_slice(&c.expression);
            pose.extend_from_slice(&c.pose);
            eye.extend_from_slice(&c.eye);
        }
        let b = frames.len();
        let t0 = Instant::now();
        let verts = self
            .flame
            .forward_with_identity(
                &self.identity,
                &Tensor::from_vec(exp, (b, n_exp), &dev)?,
                &Tensor::from_vec(pose, (b, 6), &dev)?,
                &Tensor::from_vec(eye, (b, 6), &dev)?,
            )?
            .vertices;
        let cams: Vec<Camera> = frames.iter().map(|(_, c)| *c).collect();
        let tm = transforms_tensor(&cams)?;
        let t1 = Instant::now();
        let coarse = splat_coarse(&self.cfg, &self.gaussians, &verts, &tm)?;
        let t2 = Instant::now();
        let fine = render_fine(&self.cfg, &self.renderer, &coarse, self.noise)?;
        let t3 = Instant::now();
        self.times.flame += t1 - t0;
        self.times.splat += t2 - t1;
        self.times.renderer += t3 - t2;
        self.times.frames += b;
        Ok((coarse, fine))
    }
}

impl Drive for CpuDrive {
    fn image_size(&self) -> usize {
        self.cfg.image_size
    }

    fn render_batch(&mut self, frames: &[(FrameCodes, Camera)]) -> Result<Vec<Vec<u8>>> {
        let (_, fine) = self.render_tensors(frames)?;
        to_rgb8(&fine)
    }

    fn times(&self) -> DriveTimes {
        self.times
    }
}

/// The GPU drive (wgpu + WGSL kernels): the avatar, FLAME and the renderer stay on the device.
pub struct GpuDrive {
    inner: gagavatar_gpu::drive::GpuDrive,
    times: DriveTimes,
}

impl GpuDrive {
    /// A drive on `gpu` from its parts: the model (its renderer weights are uploaded), the
    /// avatar's Gaussians, FLAME with the source identity; uploads everything once.
    pub fn from_parts(
        gpu: Arc<Gpu>,
        tuning: &gagavatar_gpu::Tuning,
        model: &gagavatar_net::model::GagAvatar,
        gaussians: &Gaussians,
        flame: &FlameModel,
        identity: &FlameIdentity,
        noise: Noise,
    ) -> Result<Self> {
        let inner = gagavatar_gpu::drive::GpuDrive::from_model(
            gpu, tuning, model, gaussians, flame, identity, noise,
        )?;
        Ok(GpuDrive {
            inner,
            times: DriveTimes::default(),
        })
    }

    /// [`GpuDrive::from_parts`] for Gaussians already on `gpu` (made there by reconstruct).
    pub fn from_gpu_avatar(
        gpu: Arc<Gpu>,
        tuning: &gagavatar_gpu::Tuning,
        model: &gagavatar_net::model::GagAvatar,
        avatar: &gagavatar_gpu::reconstruct::GpuAvatar,
        flame: &FlameModel,
        identity: &FlameIdentity,
        noise: Noise,
    ) -> Result<Self> {
        let inner = gagavatar_gpu::drive::GpuDrive::from_gpu_avatar(
            gpu,
            tuning,
            &model.cfg,
            &model.renderer,
            avatar,
            flame,
            identity,
            noise,
        )?;
        Ok(GpuDrive {
            inner,
            times: DriveTimes::default(),
        })
    }

    /// The device drive itself (stage profiles, kernel tuning).
    pub fn device_drive(&mut self) -> &mut gagavatar_gpu::drive::GpuDrive {
        &mut self.inner
    }
}

impl Drive for GpuDrive {
    fn image_size(&self) -> usize {
        self.inner.size
    }

    fn render_batch(&mut self, frames: &[(FrameCodes, Camera)]) -> Result<Vec<Vec<u8>>> {
        let t0 = Instant::now();
        for (i, (_, cam)) in frames.iter().enumerate() {
            check_camera(cam, i)?;
        }
        // Two frames in flight: each read-back overlaps the next frame's kernels.
        let out = self.inner.frames_rgb8(frames)?;
        self.times.gpu += t0.elapsed();
        self.times.frames += frames.len();
        Ok(out)
    }

    fn render_stream(
        &mut self,
        frames: &[(FrameCodes, Camera)],
        _batch: usize,
        each: &mut dyn FnMut(usize, Vec<u8>) -> ControlFlow<()>,
    ) -> Result<usize> {
        for (i, (_, cam)) in frames.iter().enumerate() {
            check_camera(cam, i)?;
        }
        // The drive's time is the wall time less what `each` spends (encoding, sending).
        let t0 = Instant::now();
        let mut outside = Duration::ZERO;
        let done = self.inner.stream_rgb8(frames, |k, img| {
            let t = Instant::now();
            let flow = each(k, img);
            outside += t.elapsed();
            flow
        })?;
        self.times.gpu += t0.elapsed().saturating_sub(outside);
        self.times.frames += done;
        Ok(done)
    }

    fn times(&self) -> DriveTimes {
        self.times
    }
}
