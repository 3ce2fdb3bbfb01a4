//! The splatting's backward on the GPU: from dL/dimage to the gradients of every Gaussian's
//! features and screen-space quantities (mean x, mean y, conic A, B, C, opacity:
//! [`gagavatar_splat::raster::Grads2D`]'s layout), of the background, and through the
//! projection to its mean, opacity, scale and quaternion (`project_backward.wgsl`,
//! [`gagavatar_splat::project::project_backward`]'s).
//!
//! The training forward is the inference one with the compositing keeping, per pixel, its
//! final transmittance and one past the last Gaussian it took (`raster.wgsl` with `STATE`).
//! The backward has three steps: each Gaussian's pair slots (`splat_pair_info.wgsl`), the
//! compositing's gradient per (tile, Gaussian) pair summed over the tile's pixels
//! (`raster_backward.wgsl`), and each Gaussian's pairs summed in the order of its tiles
//! (`splat_grad_sum.wgsl`): no atomics on floats, the same gradients on every run. A fourth
//! takes each Gaussian's screen-space gradients through the projection.

use gagavatar_splat::Camera;

use crate::device::Gpu;
use crate::error::{input_err, GpuError, Result};
use crate::kernel::{linear_grid, record_all, Bind, Grid, Params, Step};
use crate::splat::{bin, raster, GpuSplat};

const PAIR_INFO: &str = include_str!("../shaders/splat_pair_info.wgsl");
const RASTER_BACKWARD: &str = include_str!("../shaders/raster_backward.wgsl");
const GRAD_SUM: &str = include_str!("../shaders/splat_grad_sum.wgsl");
const PROJECT_BACKWARD: &str = include_str!("../shaders/project_backward.wgsl");

/// Gradients per Gaussian through the projection: mean (3), opacity, scale (3), quaternion (4).
pub const GEOM: usize = 11;

/// Screen-space quantities per Gaussian after its features.
pub const SCREEN: usize = 6;

/// The gradients read back.
#[derive(Debug, Clone)]
pub struct SplatGrads {
    /// `[N, C]`
    pub features: Vec<f32>,
    /// `[N, 6]`: mean x, mean y, conic A, B, C, opacity.
    pub screen: Vec<f32>,
    /// `[C]`
    pub background: Vec<f32>,
    /// `[N, 11]`: mean (3), opacity, scale (3), quaternion (r, x, y, z); zeros for culled
    /// Gaussians.
    pub geom: Vec<f32>,
}

/// The per-pixel state of a training forward, read back (for tests and tools).
#[derive(Debug, Clone)]
pub struct PixelState {
    /// `[H, W]`
    pub final_t: Vec<f32>,
    /// `[H, W]`: one past the position, in the frame's sorted pair list, of the last Gaussian
    /// the pixel took (0: none).
    pub last: Vec<u32>,
}

/// The compositing's backward for one [`GpuSplat`] (built for its current pair capacity).
pub struct GpuSplatGrad {
    n: usize,
    channels: usize,
    width: usize,
    height: usize,
    capacity: usize,
    state_t: wgpu::Buffer,
    state_n: wgpu::Buffer,
    /// dL/dimage `[C, H, W]`, the backward's input.
    pub grad_image: wgpu::Buffer,
    /// `[N, C + 6]`, then the background's `[C]`.
    pub grads: wgpu::Buffer,
    /// `[N, 11]`, see [`SplatGrads::geom`].
    pub geom_grads: wgpu::Buffer,
    raster: Step,
    backward: Vec<Step>,
}

impl GpuSplatGrad {
    /// The training forward's compositing and the backward for `splat`'s buffers.
    pub fn new(gpu: &Gpu, splat: &GpuSplat) -> Result<Self> {
        let (n, c, w, h) = (splat.n, splat.channels, splat.width, splat.height);
        let s = c + SCREEN;
        if s > 256 {
            return Err(GpuError::Unsupported(format!(
                "the splatting backward of {c} channels (at most 250)"
            )));
        }
        let capacity = splat.capacity();
        let (grid_x, grid_y) = (w.div_ceil(16), h.div_ceil(16));
        let tiles = grid_x * grid_y;
        let bg_off = capacity * s;
        if bg_off + tiles * c >= u32::MAX as usize {
            return Err(GpuError::Unsupported(format!(
                "{capacity} pairs of {s} gradients"
            )));
        }
        let state_t = gpu.buffer("splat state: final transmittance", 4 * (w * h) as u64);
        let state_n = gpu.buffer("splat state: last contributor", 4 * (w * h) as u64);
        let grad_image = gpu.buffer("dL/d splatted image", 4 * (c * w * h) as u64);
        let info = gpu.buffer("splat pair slots", 16 * n.max(1) as u64);
        let pairs = gpu.buffer(
            "splat pair gradients",
            4 * (bg_off + tiles * c).max(1) as u64,
        );
        let grads = gpu.buffer("splat gradients", 4 * (n * s + c) as u64);
        let geom_grads = gpu.buffer(
            "splat gradients through the projection",
            4 * (n * GEOM).max(1) as u64,
        );
        let bins: &bin::Bins = &splat.bins;
        let raster = raster::step(
            gpu,
            c,
            w,
            h,
            &bins.ranges,
            &bins.pair_vals,
            &splat.proj.splats,
            &splat.features,
            &splat.background,
            &splat.image,
            Some((&state_t, &state_n)),
        )?;

        let k = gpu.kernel(
            "splat_pair_info",
            PAIR_INFO,
            &[],
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
            ],
        )?;
        let u = gpu.uniform("splat pair info", &Params::new().u(n as u32));
        let info_step = Step::new(
            k.clone(),
            gpu.bind(
                &k,
                &[
                    &u,
                    &bins.depth_vals,
                    &splat.proj.rects,
                    &bins.counts,
                    &bins.offsets,
                    &info,
                ],
            )?,
            linear_grid(n, 256),
        );

        let mut binds = vec![Bind::Uniform];
        binds.extend([Bind::Read; 9]);
        binds.push(Bind::ReadWrite);
        let k = gpu.kernel(
            "raster_backward",
            RASTER_BACKWARD,
            &[("CHANNELS", c.to_string())],
            &binds,
        )?;
        let u = gpu.uniform(
            "raster backward",
            &Params::new()
                .u(w as u32)
                .u(h as u32)
                .u(grid_x as u32)
                .u(bg_off as u32),
        );
        let raster_bwd = Step::new(
            k.clone(),
            gpu.bind(
                &k,
                &[
                    &u,
                    &bins.ranges,
                    &bins.pair_vals,
                    &splat.proj.splats,
                    &splat.features,
                    &splat.background,
                    &state_t,
                    &state_n,
                    &grad_image,
                    &info,
                    &pairs,
                ],
            )?,
            Grid::Fixed([grid_x as u32, grid_y as u32, 1]),
        );

        let k = gpu.kernel(
            "splat_grad_sum",
            GRAD_SUM,
            &[("CHANNELS", c.to_string())],
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let u = gpu.uniform(
            "splat grad sum",
            &Params::new().u(n as u32).u(tiles as u32).u(bg_off as u32),
        );
        let sum = Step::new(
            k.clone(),
            gpu.bind(&k, &[&u, &info, &pairs, &grads])?,
            linear_grid(n + c, 64),
        );
        let mut binds = vec![Bind::Uniform];
        binds.extend([Bind::Read; 6]);
        binds.push(Bind::ReadWrite);
        let k = gpu.kernel(
            "project_backward",
            PROJECT_BACKWARD,
            &[("CHANNELS", c.to_string())],
            &binds,
        )?;
        let project = Step::new(
            k.clone(),
            gpu.bind(
                &k,
                &[
                    &splat.camera,
                    &splat.head,
                    &splat.rest,
                    &splat.scales,
                    &splat.rotations,
                    &splat.proj.rects,
                    &grads,
                    &geom_grads,
                ],
            )?,
            linear_grid(n, 256),
        );
        Ok(Self {
            n,
            channels: c,
            width: w,
            height: h,
            capacity,
            state_t,
            state_n,
            grad_image,
            grads,
            geom_grads,
            raster,
            backward: vec![info_step, raster_bwd, sum, project],
        })
    }

    /// The training forward's compositing (after `splat`'s projection and binning): the
    /// image, and the per-pixel state the backward reads.
    pub fn raster_step(&self) -> &Step {
        &self.raster
    }

    /// The backward, after a training forward and with [`GpuSplatGrad::grad_image`] written.
    pub fn backward_steps(&self) -> &[Step] {
        &self.backward
    }

    /// Whether this backward still fits `splat` (its pair buffers are rebuilt when they grow).
    pub fn fits(&self, splat: &GpuSplat) -> bool {
        splat.capacity() == self.capacity
            && (splat.n, splat.channels, splat.width, splat.height)
                == (self.n, self.channels, self.width, self.height)
    }

    /// Submits the training forward (`splat`'s projection and binning, then the compositing
    /// that keeps the per-pixel state) without waiting. The caller checks the pair count
    /// ([`GpuSplat::sizes`]) before trusting the frame.
    pub fn submit_forward(&self, gpu: &Gpu, splat: &GpuSplat) {
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("splat training forward"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            for s in splat.bin_steps() {
                s.record(&mut pass);
            }
            record_all(&mut pass, std::slice::from_ref(&self.raster));
        }
        gpu.queue.submit([enc.finish()]);
    }

    /// Submits the backward (after a training forward, with dL/dimage written) without
    /// waiting.
    pub fn submit_backward(&self, gpu: &Gpu) {
        gpu.submit(&self.backward);
    }

    /// Writes dL/dimage `[C, H, W]`.
    pub fn set_grad_output(&self, gpu: &Gpu, grad: &[f32]) -> Result<()> {
        let want = self.channels * self.width * self.height;
        if grad.len() != want {
            return Err(input_err(
                "dL/dimage",
                format!("expected {want} values, got {}", grad.len()),
            ));
        }
        if let Some(i) = grad.iter().position(|v| !v.is_finite()) {
            return Err(input_err("dL/dimage", format!("value {i} is not finite")));
        }
        gpu.queue
            .write_buffer(&self.grad_image, 0, bytemuck::cast_slice(grad));
        Ok(())
    }

    /// Reads the gradients of the last backward.
    pub fn read(&self, gpu: &Gpu) -> Result<SplatGrads> {
        let (n, c) = (self.n, self.channels);
        let s = c + SCREEN;
        let all = gpu.read_f32(&self.grads, n * s + c)?;
        let mut features = Vec::with_capacity(n * c);
        let mut screen = Vec::with_capacity(n * SCREEN);
        for row in all[..n * s].chunks_exact(s) {
            features.extend_from_slice(&row[..c]);
            screen.extend_from_slice(&row[c..]);
        }
        Ok(SplatGrads {
            features,
            screen,
            background: all[n * s..].to_vec(),
            geom: gpu.read_f32(&self.geom_grads, n * GEOM)?,
        })
    }

    /// Reads the per-pixel state of the last training forward.
    pub fn read_state(&self, gpu: &Gpu) -> Result<PixelState> {
        let px = self.width * self.height;
        Ok(PixelState {
            final_t: gpu.read_f32(&self.state_t, px)?,
            last: gpu.read_u32(&self.state_n, px)?,
        })
    }

    /// The training forward from `cam`, waited for: the pair buffers grown, and this backward
    /// rebuilt for them, until the frame fits.
    pub fn forward(&mut self, gpu: &Gpu, splat: &mut GpuSplat, cam: &Camera) -> Result<()> {
        splat.set_camera(gpu, cam)?;
        loop {
            if !self.fits(splat) {
                *self = Self::new(gpu, splat)?;
            }
            self.submit_forward(gpu, splat);
            let total = gpu.read_u32(splat.sizes(), 1)?[0] as usize;
            if !splat.grow(gpu, total)? {
                return Ok(());
            }
        }
    }

    /// One image from `cam`: the training forward (the pair buffers grown, and this backward
    /// rebuilt for them, until the frame fits), then the backward of `grad` = dL/dimage.
    /// Returns the splatted image `[C, H, W]` and the gradients.
    pub fn run(
        &mut self,
        gpu: &Gpu,
        splat: &mut GpuSplat,
        cam: &Camera,
        grad: &[f32],
    ) -> Result<(Vec<f32>, SplatGrads)> {
        self.forward(gpu, splat, cam)?;
        self.set_grad_output(gpu, grad)?;
        self.submit_backward(gpu);
        let image = gpu.read_f32(&splat.image, self.channels * self.width * self.height)?;
        Ok((image, self.read(gpu)?))
    }
}
