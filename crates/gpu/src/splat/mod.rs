//! 32-channel 3D Gaussian splatting on the GPU (spec section 7, forward only): projection,
//! depth sort, tile binning and per-tile compositing, with the CPU path's semantics (16x16
//! tiles, per-tile depth order with index ties, the early-stop rule) and arithmetic.
//!
//! The Gaussians' constant attributes are uploaded once; per frame only the camera (and, in
//! the drive, the FLAME vertices, which a kernel writes) change. The (tile, Gaussian) pair
//! buffers have a capacity: a frame that needs more reports it (`pairs_total`) and is redone
//! after [`GpuSplat::grow`].

pub mod bin;
pub mod project;
pub mod raster;

use gagavatar_splat::Camera;

use crate::device::Gpu;
use crate::error::{input_err, GpuError, Result};
use crate::kernel::{record_all, Step};
use crate::tuning::Tuning;

/// Host-side Gaussian attributes (activated, row-major), as `GaussianScene` holds them.
#[derive(Debug, Clone, Copy)]
pub struct SplatInputs<'a> {
    /// `[N - n_vertices, 3]`: positions of the Gaussians after the FLAME vertices.
    pub means: &'a [f32],
    /// `[N, C]`
    pub features: &'a [f32],
    pub channels: usize,
    /// `[N]`
    pub opacities: &'a [f32],
    /// `[N, 3]`
    pub scales: &'a [f32],
    /// `[N, 4]` as (r, x, y, z), unnormalised
    pub rotations: &'a [f32],
    /// `[C]`
    pub background: &'a [f32],
}

impl<'a> SplatInputs<'a> {
    /// A scene's Gaussians (all of them, no head vertices) with `background`.
    pub fn from_scene(scene: &'a gagavatar_splat::GaussianScene, background: &'a [f32]) -> Self {
        Self {
            means: &scene.means,
            features: &scene.features,
            channels: scene.channels,
            opacities: &scene.opacities,
            scales: &scene.scales,
            rotations: &scene.rotations,
            background,
        }
    }
}

/// Gaussian attributes in GPU buffers, in [`SplatInputs`]' layouts (`n` Gaussians, `channels`
/// features; `means` holds the positions after the head vertices).
pub struct SplatBuffers {
    pub n: usize,
    pub channels: usize,
    pub means: wgpu::Buffer,
    pub features: wgpu::Buffer,
    pub opacities: wgpu::Buffer,
    pub scales: wgpu::Buffer,
    pub rotations: wgpu::Buffer,
}

/// The splatting pipeline for one set of Gaussians and one image size.
pub struct GpuSplat {
    pub n: usize,
    pub n_vertices: usize,
    pub channels: usize,
    pub width: usize,
    pub height: usize,
    tuning: Tuning,
    pub(crate) camera: wgpu::Buffer,
    pub(crate) head: wgpu::Buffer,
    pub(crate) rest: wgpu::Buffer,
    opacities: wgpu::Buffer,
    pub(crate) scales: wgpu::Buffer,
    pub(crate) rotations: wgpu::Buffer,
    pub(crate) features: wgpu::Buffer,
    pub(crate) background: wgpu::Buffer,
    pub(crate) proj: project::Projected,
    pub(crate) bins: bin::Bins,
    project: Step,
    raster: Step,
    /// `[C, H, W]` f32, the splatted feature image.
    pub image: wgpu::Buffer,
}

fn check_len(name: &str, v: &[f32], want: usize) -> Result<()> {
    if v.len() != want {
        return Err(input_err(
            name,
            format!("expected {want} values, got {}", v.len()),
        ));
    }
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(input_err(
            name,
            format!("value {i} is not finite ({})", v[i]),
        ));
    }
    Ok(())
}

impl GpuSplat {
    /// Uploads the Gaussians. With `n_vertices > 0`, the first `n_vertices` positions are read
    /// each frame from `head` (`[n_vertices, 3]` f32, e.g. the FLAME output buffer) and
    /// `inputs.means` holds the others.
    pub fn new(
        gpu: &Gpu,
        tuning: &Tuning,
        inputs: &SplatInputs,
        head: Option<&wgpu::Buffer>,
        n_vertices: usize,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let n = inputs.opacities.len();
        let c = inputs.channels;
        if n_vertices > n {
            return Err(input_err(
                "gaussians",
                format!("{n_vertices} head vertices but only {n} Gaussians"),
            ));
        }
        check_len("means", inputs.means, 3 * (n - n_vertices))?;
        check_len("features", inputs.features, n * c)?;
        check_len("opacities", inputs.opacities, n)?;
        check_len("scales", inputs.scales, 3 * n)?;
        check_len("rotations", inputs.rotations, 4 * n)?;
        let buffers = SplatBuffers {
            n,
            channels: c,
            means: gpu.buffer_with("means", inputs.means),
            opacities: gpu.buffer_with("opacities", inputs.opacities),
            scales: gpu.buffer_with("scales", inputs.scales),
            rotations: gpu.buffer_with("rotations", inputs.rotations),
            features: gpu.buffer_with("features", inputs.features),
        };
        Self::from_buffers(
            gpu,
            tuning,
            buffers,
            inputs.background,
            head,
            n_vertices,
            (width, height),
        )
    }

    /// [`GpuSplat::new`] for Gaussians already on the GPU (e.g. written by
    /// [`crate::reconstruct::GpuReconstruct`]): nothing is copied.
    pub fn from_buffers(
        gpu: &Gpu,
        tuning: &Tuning,
        buffers: SplatBuffers,
        background: &[f32],
        head: Option<&wgpu::Buffer>,
        n_vertices: usize,
        (width, height): (usize, usize),
    ) -> Result<Self> {
        tuning.check(&gpu.limits)?;
        let SplatBuffers {
            n,
            channels: c,
            means: rest,
            features,
            opacities,
            scales,
            rotations,
        } = buffers;
        if n_vertices > n {
            return Err(input_err(
                "gaussians",
                format!("{n_vertices} head vertices but only {n} Gaussians"),
            ));
        }
        if n >= (1 << 31) {
            return Err(GpuError::Unsupported(format!("{n} Gaussians")));
        }
        if c == 0 {
            return Err(input_err("features", "no channels"));
        }
        if width == 0 || height == 0 || width.div_ceil(16) > 0xffff || height.div_ceil(16) > 0xffff
        {
            return Err(input_err("image", format!("size {width}x{height}")));
        }
        check_len("background", background, c)?;
        for (name, buf, len) in [
            ("means", &rest, 3 * (n - n_vertices)),
            ("features", &features, n * c),
            ("opacities", &opacities, n),
            ("scales", &scales, 3 * n),
            ("rotations", &rotations, 4 * n),
        ] {
            if buf.size() < 4 * len as u64 {
                return Err(input_err(
                    name,
                    format!("a {}-byte buffer for {len} values", buf.size()),
                ));
            }
        }
        let head = match (head, n_vertices) {
            (Some(h), _) => h.clone(),
            (None, 0) => gpu.buffer("no head", 16),
            (None, _) => {
                return Err(input_err(
                    "gaussians",
                    "head vertices announced but no buffer given",
                ))
            }
        };
        let grid_x = width.div_ceil(16);
        let grid_y = height.div_ceil(16);
        let camera = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("splat camera"),
            size: 96,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let background = gpu.buffer_with("background", background);
        let image = gpu.buffer("coarse image", 4 * (c * width * height) as u64);
        let proj = project::Projected::new(gpu, n);
        let project = project::step(
            gpu, &camera, &head, &rest, &opacities, &scales, &rotations, &proj, n,
        )?;
        let capacity = ((n as f64 * tuning.pairs_per_gaussian) as usize).max(1024);
        let bins = bin::build(gpu, tuning, &proj, n, grid_x, grid_y, capacity)?;
        let raster = raster::step(
            gpu,
            c,
            width,
            height,
            &bins.ranges,
            &bins.pair_vals,
            &proj.splats,
            &features,
            &background,
            &image,
            None,
        )?;
        Ok(Self {
            n,
            n_vertices,
            channels: c,
            width,
            height,
            tuning: tuning.clone(),
            camera,
            head,
            rest,
            opacities,
            scales,
            rotations,
            features,
            background,
            proj,
            bins,
            project,
            raster,
            image,
        })
    }

    /// Sets the camera of the next frame.
    pub fn set_camera(&self, gpu: &Gpu, cam: &Camera) -> Result<()> {
        if cam.width != self.width || cam.height != self.height {
            return Err(input_err(
                "camera",
                format!(
                    "renders {}x{}, the pipeline was built for {}x{}",
                    cam.width, cam.height, self.width, self.height
                ),
            ));
        }
        let p = project::camera_params(cam, self.n, self.n_vertices);
        gpu.queue
            .write_buffer(&self.camera, 0, bytemuck::cast_slice(&p.words()));
        Ok(())
    }

    /// Projection, depth sort and binning.
    pub fn bin_steps(&self) -> impl Iterator<Item = &Step> {
        std::iter::once(&self.project).chain(self.bins.steps.iter())
    }

    pub fn raster_step(&self) -> &Step {
        &self.raster
    }

    /// The buffer whose word [`bin::SLOT_PAIRS_TOTAL`] holds the frame's pair count.
    pub fn sizes(&self) -> &wgpu::Buffer {
        &self.bins.sizes
    }

    pub fn capacity(&self) -> usize {
        self.bins.capacity
    }

    /// Makes room for `pairs` (tile, Gaussian) pairs (with a margin) if there is less; returns
    /// whether it did, in which case the frame that needed them must be rendered again.
    pub fn grow(&mut self, gpu: &Gpu, pairs: usize) -> Result<bool> {
        if pairs <= self.bins.capacity {
            return Ok(false);
        }
        let cap = pairs + pairs / 4;
        // A dispatch covers at most 65535 blocks of the radix sort.
        let max = 65535 * crate::sort::radix_block(&self.tuning) as usize;
        if cap > max.min(u32::MAX as usize) {
            return Err(GpuError::Unsupported(format!(
                "{pairs} (tile, Gaussian) pairs in one frame (at most {max})"
            )));
        }
        let grid_x = self.width.div_ceil(16);
        let grid_y = self.height.div_ceil(16);
        self.bins = bin::build(gpu, &self.tuning, &self.proj, self.n, grid_x, grid_y, cap)?;
        self.raster = raster::step(
            gpu,
            self.channels,
            self.width,
            self.height,
            &self.bins.ranges,
            &self.bins.pair_vals,
            &self.proj.splats,
            &self.features,
            &self.background,
            &self.image,
            None,
        )?;
        Ok(true)
    }

    /// Renders one image on its own (for tests and tools): `[C, H, W]` values.
    pub fn render(&mut self, gpu: &Gpu, cam: &Camera) -> Result<Vec<f32>> {
        self.set_camera(gpu, cam)?;
        loop {
            let mut enc = gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
                for s in self.bin_steps() {
                    s.record(&mut pass);
                }
                record_all(&mut pass, std::slice::from_ref(&self.raster));
            }
            gpu.queue.submit([enc.finish()]);
            let total = gpu.read_u32(&self.bins.sizes, 1)?[0] as usize;
            if !self.grow(gpu, total)? {
                break;
            }
        }
        gpu.read_f32(&self.image, self.channels * self.width * self.height)
    }

    /// Replaces the Gaussians (as many, with as many channels, and no head vertices read from
    /// another buffer) for the next frames: a trainer's next sample reuses the buffers.
    pub fn set_gaussians(&self, gpu: &Gpu, inputs: &SplatInputs) -> Result<()> {
        let (n, c) = (self.n, self.channels);
        if self.n_vertices != 0 || inputs.channels != c || inputs.opacities.len() != n {
            return Err(input_err(
                "gaussians",
                format!(
                    "{} Gaussians of {} channels for a splat of {n} of {c} ({} head vertices)",
                    inputs.opacities.len(),
                    inputs.channels,
                    self.n_vertices
                ),
            ));
        }
        let all = [
            ("means", inputs.means, 3 * n, &self.rest),
            ("features", inputs.features, n * c, &self.features),
            ("opacities", inputs.opacities, n, &self.opacities),
            ("scales", inputs.scales, 3 * n, &self.scales),
            ("rotations", inputs.rotations, 4 * n, &self.rotations),
        ];
        for (name, v, want, _) in &all {
            check_len(name, v, *want)?;
        }
        for (_, v, _, buf) in all {
            gpu.queue.write_buffer(buf, 0, bytemuck::cast_slice(v));
        }
        Ok(())
    }

    /// The buffers holding the Gaussians' constants (for reuse by other stages).
    pub fn features(&self) -> &wgpu::Buffer {
        &self.features
    }

    #[doc(hidden)]
    pub fn head(&self) -> &wgpu::Buffer {
        &self.head
    }

    #[doc(hidden)]
    pub fn constants(&self) -> [&wgpu::Buffer; 4] {
        [&self.rest, &self.opacities, &self.scales, &self.rotations]
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::testutil::{assert_close, assert_close_but_flips, gpu};
    use candle_core::{Device, Tensor};
    use gagavatar_splat::testscene::{avatar_scene, Regime, Rng};
    use gagavatar_splat::{splat, GaussianScene, Gaussians};

    /// The coarse image's parity bound (the issue's): both sides run the same f32 operations,
    /// except that a GPU may fuse multiply-adds the CPU rounds twice and its division and
    /// square root may be off by an ulp or two.
    const COARSE_TOL: f64 = 1e-4;

    fn cpu_render(scene: &GaussianScene, bg: &[f32], cam: &Camera) -> Vec<f32> {
        let t = scene.to_tensors(&Device::Cpu).unwrap();
        let bg = Tensor::from_slice(bg, bg.len(), &Device::Cpu).unwrap();
        let out = splat(&Gaussians::from_tensors(&t), &bg, std::slice::from_ref(cam)).unwrap();
        out.image.flatten_all().unwrap().to_vec1().unwrap()
    }

    fn gpu_render(
        g: &Gpu,
        scene: &GaussianScene,
        bg: &[f32],
        cam: &Camera,
        tuning: &Tuning,
    ) -> Vec<f32> {
        gpu_frame(g, scene, bg, cam, tuning).image
    }

    /// End to end at release size. Each half of the GPU's splatting is also compared on its
    /// own below (projection within rounding, compositing of its own projection exactly as
    /// the CPU composites), since end to end a real driver's rounding of the projection may
    /// flip a few near-1/255 decisions ([`assert_close_but_flips`]).
    #[test]
    fn benchmark_scene_matches_the_cpu() {
        let Some(g) = gpu() else { return };
        for regime in [Regime::Small, Regime::Large] {
            let (scene, cam) = avatar_scene(296, 5023, 32, regime, 1);
            let bg = vec![0f32; 32];
            let want = cpu_render(&scene, &bg, &cam);
            let got = gpu_render(g, &scene, &bg, &cam, &Tuning::default());
            let plane = cam.width * cam.height;
            assert_close_but_flips(
                &format!("splat {regime:?}"),
                &want,
                &got,
                plane,
                COARSE_TOL,
                flip_tol(&scene.features, &bg),
                max_flipped_pixels(plane),
            );
        }
    }

    /// What a pixel may move by where up to [`FLIPS`] decisions flipped. A Gaussian taken on
    /// one side and skipped on the other adds or removes alpha T f and scales what lies
    /// behind it by (1 - alpha): at most 2 alpha T max|f|, where either alpha ~ 1/255 (the
    /// alpha test flipped) or T (1 - alpha) ~ 1e-4 (the transmittance test flipped, so
    /// alpha T <= 1e-4 / (1 - 0.99) = 0.01).
    pub(crate) fn flip_tol(features: &[f32], bg: &[f32]) -> f64 {
        use gagavatar_splat::raster::{MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE};
        let fmax = features
            .iter()
            .chain(bg)
            .fold(0f64, |m, &f| m.max(f64::from(f).abs()));
        let alpha_t = MIN_ALPHA.max(MIN_TRANSMITTANCE / (1.0 - MAX_ALPHA));
        COARSE_TOL + FLIPS * 2.0 * alpha_t * fmax
    }

    /// Flips per pixel allowed by [`flip_tol`].
    const FLIPS: f64 = 2.0;
    /// Pixels that may show a flip: 0.1% (on lavapipe, with positions an ulp apart, 77 values of
    /// 8.4M differed).
    pub(crate) fn max_flipped_pixels(plane: usize) -> usize {
        plane / 1000
    }

    /// Splats (2 x vec4 per Gaussian), tile ranges, tile lists and the image, as the GPU
    /// left them after one frame.
    struct GpuFrame {
        splats: Vec<f32>,
        ranges: Vec<u32>,
        ids: Vec<u32>,
        image: Vec<f32>,
    }

    fn gpu_frame(
        g: &Gpu,
        scene: &GaussianScene,
        bg: &[f32],
        cam: &Camera,
        tuning: &Tuning,
    ) -> GpuFrame {
        let inputs = SplatInputs::from_scene(scene, bg);
        let mut s = GpuSplat::new(g, tuning, &inputs, None, 0, cam.width, cam.height).unwrap();
        let image = s.render(g, cam).unwrap();
        let n = scene.len();
        let tiles = cam.width.div_ceil(16) * cam.height.div_ceil(16);
        let ranges = g.read_u32(&s.bins.ranges, 2 * tiles).unwrap();
        let pairs = ranges.iter().copied().max().unwrap_or(0) as usize;
        GpuFrame {
            splats: g.read_f32(&s.proj.splats, 8 * n).unwrap(),
            ids: g.read_u32(&s.bins.pair_vals, pairs).unwrap(),
            ranges,
            image,
        }
    }

    /// raster.wgsl's operations in its order, in scalar f32 on the CPU (the exp is the CPU
    /// splatting's own), on given splats and tile lists.
    fn reference_raster(
        f: &GpuFrame,
        features: &[f32],
        bg: &[f32],
        w: usize,
        h: usize,
    ) -> Vec<f32> {
        use gagavatar_splat::raster::{MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE};
        use gagavatar_splat::real::exp_f32;
        let c = bg.len();
        let grid_x = w.div_ceil(16);
        let plane = w * h;
        let mut out = vec![0f32; c * plane];
        let mut acc = vec![0f32; c];
        for y in 0..h {
            for x in 0..w {
                let t = (y / 16) * grid_x + x / 16;
                let (px, py) = (x as f32, y as f32);
                acc.fill(0.0);
                let mut tr = 1f32;
                for &id in &f.ids[f.ranges[2 * t] as usize..f.ranges[2 * t + 1] as usize] {
                    let s = &f.splats[8 * id as usize..8 * id as usize + 6];
                    let (dx, dy) = (s[0] - px, s[1] - py);
                    let inner = s[2].mul_add(dx, s[3] * dy);
                    let cdy = (s[4] * dy) * dy;
                    let power = dx.mul_add(inner, cdy);
                    let alpha = (s[5] * exp_f32(power)).min(MAX_ALPHA as f32);
                    // (NaN skips, as in the shader.)
                    let keep = power <= 0.0 && alpha >= MIN_ALPHA as f32;
                    if !keep {
                        continue;
                    }
                    let test = tr * (1.0 - alpha);
                    if test < MIN_TRANSMITTANCE as f32 {
                        break;
                    }
                    let wgt = alpha * tr;
                    for (k, a) in acc.iter_mut().enumerate() {
                        *a += wgt * features[id as usize * c + k];
                    }
                    tr = test;
                }
                for k in 0..c {
                    out[k * plane + y * w + x] = acc[k] + tr * bg[k];
                }
            }
        }
        out
    }

    /// The compositing alone: the GPU's image against raster.wgsl's operations run on the
    /// CPU over the GPU's own splats and tile lists. No decision can flip here, so the bound
    /// is rounding of the sums (a driver may fuse `acc + w f`).
    #[test]
    fn raster_of_the_gpus_own_projection_matches_the_cpu() {
        let Some(g) = gpu() else { return };
        for regime in [Regime::Small, Regime::Large] {
            let (scene, cam) = avatar_scene(296, 5023, 32, regime, 1);
            let bg: Vec<f32> = (0..32).map(|c| 0.05 * c as f32 - 0.5).collect();
            let f = gpu_frame(g, &scene, &bg, &cam, &Tuning::default());
            let want = reference_raster(&f, &scene.features, &bg, cam.width, cam.height);
            let plane = cam.width * cam.height;
            assert_close_but_flips(
                &format!("raster of the GPU's projection, {regime:?}"),
                &want,
                &f.image,
                plane,
                RASTER_TOL,
                flip_tol(&scene.features, &bg),
                max_flipped_pixels(plane),
            );
        }
    }

    /// Rounding of 32 weighted sums, with or without fused multiply-adds. The transmittance
    /// test can still flip: a driver may evaluate `T (1 - alpha)` as `T - T alpha` in one
    /// rounding (lavapipe does: one pixel of the small regime stops one Gaussian later than
    /// the CPU, 1.3e-5 apart).
    const RASTER_TOL: f64 = 1e-5;

    /// The projection alone: the GPU's splats against the CPU path's f32 projection. Culling
    /// must agree; centres within [`CENTRE_TOL`] pixels; conics within
    /// [`CONIC_RTOL`] of their largest entry (a thin Gaussian's 2x2 inverse amplifies an ulp
    /// of its covariance by its condition number, up to ~1e3 after the 0.3 px^2 low-pass).
    #[test]
    fn projection_matches_the_cpu_within_rounding() {
        use gagavatar_splat::project::{project, CamK};
        let Some(g) = gpu() else { return };
        for regime in [Regime::Small, Regime::Large] {
            let (scene, cam) = avatar_scene(296, 5023, 32, regime, 1);
            let geom: Vec<f32> = [
                &scene.means,
                &scene.opacities,
                &scene.scales,
                &scene.rotations,
            ]
            .iter()
            .flat_map(|v| v.iter().copied())
            .collect();
            let cp = project(&CamK::<f32>::new(&cam), &geom);
            let f = gpu_frame(g, &scene, &[0f32; 32], &cam, &Tuning::default());
            let (mut centre, mut conic, mut culled) = ((0f64, 0), (0f64, 0), 0usize);
            for (i, s) in cp.g.iter().enumerate() {
                let gs = &f.splats[8 * i..8 * i + 6];
                let gpu_culled = gs.iter().all(|&v| v == 0.0);
                if (cp.radius[i] == 0) != gpu_culled {
                    culled += 1;
                    continue;
                }
                if gpu_culled {
                    continue;
                }
                let d = (f64::from(s.mx - gs[0]).abs()).max(f64::from(s.my - gs[1]).abs());
                if d > centre.0 {
                    centre = (d, i);
                }
                let want = [s.qa, s.qb, s.qc];
                let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
                let d = want
                    .iter()
                    .zip(&gs[2..5])
                    .map(|(a, b)| f64::from((a - b).abs() / scale))
                    .fold(0f64, f64::max);
                if d > conic.0 {
                    conic = (d, i);
                }
                assert_eq!(s.opacity, gs[5], "Gaussian {i}: opacity");
            }
            eprintln!(
                "projection {regime:?}: centres within {:e} px (Gaussian {}), conics within \
                 {:e} relative (Gaussian {}), {culled} culling decisions differ",
                centre.0, centre.1, conic.0, conic.1
            );
            assert_eq!(culled, 0, "{regime:?}: culling decisions differ");
            assert!(
                centre.0 <= CENTRE_TOL,
                "{regime:?}: Gaussian {}: centre off by {:e} px > {CENTRE_TOL:e}",
                centre.1,
                centre.0
            );
            assert!(
                conic.0 <= CONIC_RTOL,
                "{regime:?}: Gaussian {}: conic off by {:e} of its largest entry > {CONIC_RTOL:e}",
                conic.1,
                conic.0
            );
        }
    }

    /// A few ulps of a 512-pixel coordinate.
    const CENTRE_TOL: f64 = 1e-3;
    const CONIC_RTOL: f64 = 1e-3;

    /// A scene of every awkward case: behind the camera and at the near plane, off-screen,
    /// huge (covering the whole image), tiny, many at exactly the same depth overlapping
    /// (ties broken by index), unnormalised quaternions, opacities at the 1/255 edge, an image
    /// size that is not a multiple of 16, a non-zero background.
    fn edge_scene(seed: u64, channels: usize) -> (GaussianScene, Camera) {
        let mut rng = Rng::new(seed);
        let tm = Camera::look_at_origin_matrix(4.0, 0.3, -0.2);
        let cam = Camera::from_transform_matrix(&tm, 3.0, 100, 72).unwrap();
        let mut s = GaussianScene {
            channels,
            ..Default::default()
        };
        let mut push = |p: [f64; 3], scale: [f64; 3], o: f64, q: [f64; 4], rng: &mut Rng| {
            s.means.extend(p.map(|v| v as f32));
            s.scales.extend(scale.map(|v| v as f32));
            s.opacities.push(o as f32);
            s.rotations.extend(q.map(|v| v as f32));
            for _ in 0..channels {
                s.features.push(rng.range(-1.0, 2.0) as f32);
            }
        };
        for i in 0..1500 {
            let p = [
                rng.range(-2.0, 2.0),
                rng.range(-2.0, 2.0),
                rng.range(-2.0, 2.0),
            ];
            let kind = i % 6;
            let scale = match kind {
                0 => [1.5, 2.0, 1.0],    // huge
                1 => [1e-4, 2e-4, 1e-4], // tiny
                _ => [
                    rng.range(0.01, 0.2),
                    rng.range(0.01, 0.2),
                    rng.range(0.01, 0.2),
                ],
            };
            let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
            let o = match kind {
                3 => 1.0 / 255.0 + rng.range(-1e-4, 1e-4),
                _ => rng.range(0.05, 1.0),
            };
            push(p, scale, o, q, &mut rng);
        }
        // Behind the camera (the camera is at distance 4), at the near plane, far off-screen.
        for z in [-5.0, -4.0, -3.8, -3.81, 10.0] {
            push(
                [0.0, 0.0, z],
                [0.3, 0.3, 0.3],
                0.8,
                [1.0, 0.0, 0.0, 0.0],
                &mut rng,
            );
        }
        push(
            [40.0, 0.0, 0.0],
            [0.3, 0.3, 0.3],
            0.8,
            [1.0, 0.0, 0.0, 0.0],
            &mut rng,
        );
        // Depth ties: a column of Gaussians at one point, and a row at one depth.
        for k in 0..40 {
            push(
                [0.1, 0.1, 0.5],
                [0.1, 0.05, 0.02],
                0.3,
                [1.0, 0.0, 0.0, 0.0],
                &mut rng,
            );
            let x = -1.0 + 0.05 * k as f64;
            push(
                [x, -0.3, 0.0],
                [0.08, 0.08, 0.0],
                0.6,
                [0.9, 0.1, 0.0, 0.0],
                &mut rng,
            );
        }
        let _ = &mut push;
        (s, cam)
    }

    #[test]
    fn edge_cases_and_random_scenes_match_the_cpu() {
        let Some(g) = gpu() else { return };
        for seed in 0..3 {
            let channels = [32, 5, 1][seed as usize];
            let (scene, cam) = edge_scene(seed, channels);
            let bg: Vec<f32> = (0..channels).map(|c| 0.25 * c as f32 - 0.5).collect();
            let want = cpu_render(&scene, &bg, &cam);
            let got = gpu_render(g, &scene, &bg, &cam, &Tuning::default());
            assert_close(&format!("edge scene {seed}"), &want, &got, COARSE_TOL);
        }
    }

    /// The pair buffers start too small for this scene: the frame is redone after growing
    /// them, and other sort parameters give the same image.
    #[test]
    fn pair_overflow_and_other_tunings_give_the_same_image() {
        let Some(g) = gpu() else { return };
        let (scene, cam) = edge_scene(7, 4);
        let bg = vec![0f32; 4];
        let want = cpu_render(&scene, &bg, &cam);
        let t = Tuning {
            pairs_per_gaussian: 0.01,
            radix_bits: 3,
            radix_items: 2,
            scan_items: 1,
            ..Default::default()
        };
        let got = gpu_render(g, &scene, &bg, &cam, &t);
        assert_close("grown pairs", &want, &got, COARSE_TOL);
    }

    /// Projection and tile lists against the CPU path's own: the same tile rectangles, and
    /// every tile lists the same Gaussians in the same order (depth ties included).
    #[test]
    fn tile_lists_match_the_cpu_binning() {
        use gagavatar_splat::binning::bin;
        use gagavatar_splat::project::{project, CamK};
        let Some(g) = gpu() else { return };
        for (scene, cam) in [edge_scene(4, 2), avatar_scene(40, 500, 2, Regime::Large, 1)] {
            let n = scene.len();
            let geom: Vec<f32> = [
                &scene.means,
                &scene.opacities,
                &scene.scales,
                &scene.rotations,
            ]
            .iter()
            .flat_map(|v| v.iter().copied())
            .collect();
            let k = CamK::<f32>::new(&cam);
            let cp = project(&k, &geom);
            let cb = bin(&cp, k.grid_x, k.grid_y);
            let bg = vec![0f32; 2];
            let inputs = SplatInputs {
                means: &scene.means,
                features: &scene.features,
                channels: 2,
                opacities: &scene.opacities,
                scales: &scene.scales,
                rotations: &scene.rotations,
                background: &bg,
            };
            let mut s = GpuSplat::new(
                g,
                &Tuning::default(),
                &inputs,
                None,
                0,
                cam.width,
                cam.height,
            )
            .unwrap();
            s.render(g, &cam).unwrap();
            let rects = g.read_u32(&s.proj.rects, 2 * n).unwrap();
            for i in 0..n {
                let r = cp.rect[i].map(u32::from);
                let got = [
                    rects[2 * i] & 0xffff,
                    rects[2 * i] >> 16,
                    rects[2 * i + 1] & 0xffff,
                    rects[2 * i + 1] >> 16,
                ];
                assert_eq!(got, r, "Gaussian {i}: tile rectangle");
            }
            let sizes = g.read_u32(&s.bins.sizes, 2).unwrap();
            assert_eq!(sizes[0] as usize, cb.pairs, "pair count");
            let tiles = k.grid_x * k.grid_y;
            let ranges = g.read_u32(&s.bins.ranges, 2 * tiles).unwrap();
            let ids = g.read_u32(&s.bins.pair_vals, cb.pairs).unwrap();
            for ty in 0..k.grid_y {
                for tx in 0..k.grid_x {
                    let t = ty * k.grid_x + tx;
                    let got = &ids[ranges[2 * t] as usize..ranges[2 * t + 1] as usize];
                    assert_eq!(got, cb.bands[ty].tile(tx), "tile ({tx}, {ty})");
                }
            }
        }
    }

    #[test]
    fn empty_and_all_culled_scenes_give_the_background() {
        let Some(g) = gpu() else { return };
        let (mut scene, cam) = edge_scene(3, 2);
        // Everything behind the camera.
        for m in scene.means.chunks_mut(3) {
            m[2] = -10.0;
        }
        let bg = [0.5f32, -2.0];
        let got = gpu_render(g, &scene, &bg, &cam, &Tuning::default());
        let plane = cam.width * cam.height;
        assert!(got[..plane].iter().all(|&v| v == 0.5));
        assert!(got[plane..].iter().all(|&v| v == -2.0));
    }

    #[test]
    fn bad_inputs_are_errors() {
        let Some(g) = gpu() else { return };
        let (scene, cam) = edge_scene(1, 3);
        let mut means = scene.means.clone();
        means[5] = f32::NAN;
        let inputs = SplatInputs {
            means: &means,
            features: &scene.features,
            channels: 3,
            opacities: &scene.opacities,
            scales: &scene.scales,
            rotations: &scene.rotations,
            background: &[0.0; 3],
        };
        let t = Tuning::default();
        let e = GpuSplat::new(g, &t, &inputs, None, 0, 100, 72)
            .err()
            .unwrap();
        assert!(e.to_string().contains("not finite"), "{e}");
        let short = SplatInputs {
            means: &scene.means,
            background: &[0.0; 2],
            ..inputs
        };
        assert!(GpuSplat::new(g, &t, &short, None, 0, 100, 72).is_err());
        let ok = SplatInputs {
            means: &scene.means,
            ..inputs
        };
        let s = GpuSplat::new(g, &t, &ok, None, 0, 100, 72).unwrap();
        let other = Camera { width: 64, ..cam };
        assert!(s.set_camera(g, &other).is_err());
    }
}
