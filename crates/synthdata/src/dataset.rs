//! The generator: identities x frames rendered from a FLAME asset and written as a dataset in
//! the release layout (`img_lmdb/`, `optim.pkl`, `dataset.json`) with
//! `gagavatar_data::write_release_dataset`.
//!
//! Determinism: every identity and frame draws from its own seeded stream, and FLAME runs on
//! fixed blocks of [`FLAME_BLOCK`] consecutive frames of one identity, so the bytes written
//! depend on the seed and the settings only, never on the thread count or the order work is
//! done in.
//!
//! Exactness: the records hold float32 arrays; every drawn value is float32 already, the
//! vertices come from the float32 FLAME model a reader would build, and they are projected with
//! the spec's camera (section 2): camera space `p R + T`, X and Y negated, `ndc = 12 x / z`,
//! `pixel = ((ndc + 1) W - 1) / 2`. `bbox` is the box of all projected vertices, normalised by
//! the image size (`(pixel + 0.5) / W`) and clamped to [0, 1].

use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use candle_core::{DType, Device, Tensor};
use gagavatar_data::{encode_png, write_release_dataset, DatasetSplits, TrackedFrame};
use gagavatar_flame::landmarks::NDC_FOCAL;
use gagavatar_flame::{FlameAsset, FlameModel, FLAME_SCALE};
use gagavatar_formats::atomic::temp_sibling;
use image::RgbImage;
use rayon::prelude::*;

use crate::appearance::{Appearance, HeadAnchors};
use crate::error::{config_err, Result, SynthError};
use crate::rasterizer::{to_rgb8, GBuffer, Rasterizer, MAX_SUPERSAMPLE};
use crate::sample::{appearance_rng, sample_frame, sample_shape, FrameSample, SampleConfig};

/// Image side limits.
pub const MIN_SIZE: usize = 16;
pub const MAX_SIZE: usize = 4096;
/// Frames of one identity that go through FLAME together (fixed, for determinism).
pub const FLAME_BLOCK: usize = 16;
/// FLAME blocks rendered per streaming chunk (bounds the encoded images held in memory).
const CHUNK_BLOCKS: usize = 16;

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct SynthConfig {
    pub identities: usize,
    pub frames: usize,
    /// Image side (square images).
    pub size: usize,
    pub seed: u64,
    /// Identities held out of `train` for `val` / `test`; `None`: 10% (at least 1 when there
    /// are 2 or more identities).
    pub holdout: Option<usize>,
    /// Samples per pixel along each axis; `None`: by image size (4 at 64, 3 at 128, else 2).
    pub supersample: Option<usize>,
    pub sampling: SampleConfig,
}

impl SynthConfig {
    pub fn new(identities: usize, frames: usize, size: usize, seed: u64) -> Self {
        Self {
            identities,
            frames,
            size,
            seed,
            holdout: None,
            supersample: None,
            sampling: SampleConfig::default(),
        }
    }

    /// The number of held-out identities this config resolves to.
    pub fn resolved_holdout(&self) -> usize {
        self.holdout.unwrap_or(if self.identities >= 2 {
            ((self.identities as f64 * 0.1).round() as usize).max(1)
        } else {
            0
        })
    }

    pub fn resolved_supersample(&self) -> usize {
        self.supersample
            .unwrap_or_else(|| ((384.0 / self.size.max(1) as f64).round() as usize).clamp(2, 4))
    }

    pub fn validate(&self) -> Result<()> {
        if self.identities == 0 {
            return Err(config_err("identities", "must be at least 1"));
        }
        if self.frames == 0 {
            return Err(config_err("frames", "must be at least 1"));
        }
        if self.identities.checked_mul(self.frames).is_none() {
            return Err(config_err("frames", "identities x frames overflows"));
        }
        if !(MIN_SIZE..=MAX_SIZE).contains(&self.size) {
            return Err(config_err(
                "size",
                format!("{} is outside {MIN_SIZE}..={MAX_SIZE}", self.size),
            ));
        }
        let k = self.resolved_holdout();
        if k > 0 && k >= self.identities {
            return Err(config_err(
                "holdout",
                format!(
                    "{k} held-out identities leave none of the {} for training",
                    self.identities
                ),
            ));
        }
        let ss = self.resolved_supersample();
        if ss == 0 || ss > MAX_SUPERSAMPLE {
            return Err(config_err(
                "supersample",
                format!("{ss} is outside 1..={MAX_SUPERSAMPLE}"),
            ));
        }
        Ok(())
    }
}

/// Hooks for long runs: progress and cancellation.
pub trait Progress: Sync {
    /// `frames` more images are done.
    fn advance(&self, _frames: usize) {}
    /// Checked between chunks; `true` stops the run (nothing is written).
    fn cancelled(&self) -> bool {
        false
    }
}

/// No progress reporting.
pub struct NoProgress;
impl Progress for NoProgress {}

/// How to treat the output folder.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WriteOptions {
    /// Replace an existing non-empty folder (otherwise that is an error).
    pub overwrite: bool,
}

/// Frames as (name, PNG bytes).
type Encoded = Vec<(String, Vec<u8>)>;

/// One rendered frame.
#[derive(Debug, Clone)]
pub struct RenderedFrame {
    pub name: String,
    pub image: RgbImage,
    pub record: TrackedFrame,
}

/// What [`Generator::write_dataset`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetSummary {
    pub dir: PathBuf,
    pub frames: usize,
    pub splits: DatasetSplits,
}

/// The frame name `id{identity:04}_{frame}`: `<video>_<frame>` grouping puts one identity in one
/// video.
pub fn frame_name(identity: usize, frame: usize) -> String {
    format!("id{identity:04}_{frame}")
}

/// World point (x5 FLAME units) -> `[x_px, y_px, z_view]` with the release camera (spec section
/// 2; `tm` row convention: camera space = `p R + T`, then X and Y negated).
pub fn project(tm: &[[f64; 4]; 3], p: [f64; 3], width: usize, height: usize) -> [f64; 3] {
    let cam = |j: usize| p[0] * tm[0][j] + p[1] * tm[1][j] + p[2] * tm[2][j] + tm[j][3];
    let (x, y, z) = (-cam(0), -cam(1), cam(2));
    let px = ((NDC_FOCAL * x / z + 1.0) * width as f64 - 1.0) / 2.0;
    let py = ((NDC_FOCAL * y / z + 1.0) * height as f64 - 1.0) / 2.0;
    [px, py, z]
}

/// A ready generator: the FLAME model, the face anchors and the settings.
pub struct Generator {
    config: SynthConfig,
    model: FlameModel,
    anchors: HeadAnchors,
    raster: Rasterizer,
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Generator {
    /// Checks the config and builds the float32 FLAME model (all of the asset's components).
    pub fn new(asset: &FlameAsset, config: SynthConfig) -> Result<Self> {
        config.validate()?;
        config
            .sampling
            .validate(asset.layout.shape, asset.layout.expression)?;
        let model = FlameModel::from_asset(asset, &Device::Cpu, DType::F32)?;
        let anchors = HeadAnchors::new(asset)?;
        let raster = Rasterizer::new(config.size, config.size, config.resolved_supersample())?;
        Ok(Self {
            config,
            model,
            anchors,
            raster,
        })
    }

    pub fn config(&self) -> &SynthConfig {
        &self.config
    }

    pub fn model(&self) -> &FlameModel {
        &self.model
    }

    pub fn anchors(&self) -> &HeadAnchors {
        &self.anchors
    }

    pub fn rasterizer(&self) -> Rasterizer {
        self.raster
    }

    pub fn shape(&self, identity: usize) -> Vec<f64> {
        let c = &self.config;
        sample_shape(&c.sampling, c.seed, identity, self.model.config.n_shape)
    }

    pub fn appearance(&self, identity: usize) -> Appearance {
        Appearance::sample(
            &mut appearance_rng(self.config.seed, identity),
            &self.anchors,
        )
    }

    pub fn frame_sample(&self, identity: usize, frame: usize) -> FrameSample {
        let c = &self.config;
        sample_frame(
            &c.sampling,
            c.seed,
            identity,
            frame,
            self.model.config.n_exp,
        )
    }

    /// The splits: the last `holdout` identities are held out, the first half of them (rounded
    /// up) in `val` and the rest in `test`; a single held-out identity serves as both.
    pub fn splits(&self) -> DatasetSplits {
        let n = self.config.identities;
        let k = self.config.resolved_holdout();
        let frames_of = |ids: std::ops::Range<usize>| -> Vec<String> {
            ids.flat_map(|i| (0..self.config.frames).map(move |f| frame_name(i, f)))
                .collect()
        };
        let train = frames_of(0..n - k);
        let (val, test) = match k {
            0 => (Vec::new(), Vec::new()),
            1 => (frames_of(n - 1..n), frames_of(n - 1..n)),
            _ => {
                let mid = n - k + k.div_ceil(2);
                (frames_of(n - k..mid), frames_of(mid..n))
            }
        };
        DatasetSplits { train, val, test }
    }

    /// FLAME vertices (x5, float32) of `count` frames of `identity` starting at `first`, with
    /// their drawn parameters. Callers pass whole [`FLAME_BLOCK`]s (see the module docs).
    fn block_vertices(
        &self,
        identity: usize,
        shape: &[f64],
        first: usize,
        count: usize,
    ) -> Result<Vec<(FrameSample, Vec<[f32; 3]>)>> {
        let samples: Vec<FrameSample> = (first..first + count)
            .map(|f| self.frame_sample(identity, f))
            .collect();
        let verts = self.pose(shape, &samples)?;
        Ok(samples.into_iter().zip(verts).collect())
    }

    /// FLAME vertices (x5, float32, one batch) of frames with one shape code. Codes are
    /// zero-padded to the model's component counts; longer ones are an error.
    pub fn pose(&self, shape: &[f64], frames: &[FrameSample]) -> Result<Vec<Vec<[f32; 3]>>> {
        let (ns, ne) = (self.model.config.n_shape, self.model.config.n_exp);
        if shape.len() > ns {
            return Err(config_err(
                "shape",
                format!("{} values, the model takes {ns}", shape.len()),
            ));
        }
        if let Some(f) = frames.iter().find(|f| f.expression.len() > ne) {
            return Err(config_err(
                "expression",
                format!("{} values, the model takes {ne}", f.expression.len()),
            ));
        }
        if frames.is_empty() {
            return Ok(Vec::new());
        }
        let count = frames.len();
        let dev = &self.model.device;
        let padded = |v: &[f64], n: usize| -> Vec<f32> {
            let mut out: Vec<f32> = v.iter().map(|&x| x as f32).collect();
            out.resize(n, 0.0);
            out
        };
        let shape_t = Tensor::from_vec(padded(shape, ns), (1, ns), dev)?;
        let exp: Vec<f32> = frames
            .iter()
            .flat_map(|s| padded(&s.expression, ne))
            .collect();
        let pose: Vec<f32> = frames
            .iter()
            .flat_map(|s| s.pose.map(|x| x as f32))
            .collect();
        let eye: Vec<f32> = frames
            .iter()
            .flat_map(|s| s.eye.map(|x| x as f32))
            .collect();
        let identity_t = self.model.identity(&shape_t)?;
        let out = self.model.forward_with_identity(
            &identity_t,
            &Tensor::from_vec(exp, (count, ne), dev)?,
            &Tensor::from_vec(pose, (count, 6), dev)?,
            &Tensor::from_vec(eye, (count, 6), dev)?,
        )?;
        let verts = out.vertices.to_vec3::<f32>()?;
        Ok(verts
            .into_iter()
            .map(|v| v.into_iter().map(|p| [p[0], p[1], p[2]]).collect())
            .collect())
    }

    /// The block of frames holding `frame`: `(first, count)`; an error outside the dataset.
    fn block_of(&self, identity: usize, frame: usize) -> Result<(usize, usize)> {
        let c = &self.config;
        if identity >= c.identities || frame >= c.frames {
            return Err(config_err(
                "frame",
                format!(
                    "identity {identity} frame {frame} is outside the dataset's {} x {}",
                    c.identities, c.frames
                ),
            ));
        }
        let first = frame / FLAME_BLOCK * FLAME_BLOCK;
        Ok((first, FLAME_BLOCK.min(c.frames - first)))
    }

    /// The record of a posed frame: its codes, camera and the box of its projected vertices.
    pub fn record(&self, shape: &[f64], s: &FrameSample, verts: &[[f32; 3]]) -> TrackedFrame {
        let (w, h) = (self.config.size, self.config.size);
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for v in verts {
            let p = project(&s.transform, v.map(f64::from), w, h);
            for d in 0..2 {
                lo[d] = lo[d].min(p[d]);
                hi[d] = hi[d].max(p[d]);
            }
        }
        let norm = |v: f64, n: usize| ((v + 0.5) / n as f64).clamp(0.0, 1.0) as f32 as f64;
        TrackedFrame {
            shapecode: shape.to_vec(),
            expcode: s.expression.clone(),
            posecode: s.pose.to_vec(),
            eyecode: s.eye.to_vec(),
            transform_matrix: Some(s.transform),
            bbox: Some([
                norm(lo[0], w),
                norm(lo[1], h),
                norm(hi[0], w),
                norm(hi[1], h),
            ]),
        }
    }

    /// Screen-space vertices and rasterization of one posed head (for custom shaders: tests,
    /// debugging views). Returns the projected vertices and the G-buffer.
    pub fn rasterize(
        &self,
        transform: &[[f64; 4]; 3],
        verts: &[[f32; 3]],
    ) -> Result<(Vec<[f64; 3]>, GBuffer)> {
        let (w, h) = (self.config.size, self.config.size);
        let screen: Vec<[f64; 3]> = verts
            .iter()
            .map(|v| project(transform, v.map(f64::from), w, h))
            .collect();
        let g = self.raster.rasterize(&screen, &self.model.faces)?;
        Ok((screen, g))
    }

    /// Renders one posed head of `identity` with its appearance.
    pub fn shade(
        &self,
        appearance: &Appearance,
        transform: &[[f64; 4]; 3],
        verts: &[[f32; 3]],
    ) -> Result<RgbImage> {
        let faces = &self.model.faces;
        let (_, g) = self.rasterize(transform, verts)?;
        // World-space vertex normals (area weighted) for the light, which is fixed to the head.
        let world: Vec<[f64; 3]> = verts.iter().map(|v| v.map(f64::from)).collect();
        let mut normals = vec![[0f64; 3]; world.len()];
        // Which side of each face the camera sees; view space is right-handed (two axes
        // negated), so the winding carries over from world space.
        let mut front = Vec::with_capacity(faces.len());
        let view = |p: [f64; 3]| -> [f64; 3] {
            let c = |j: usize| {
                p[0] * transform[0][j]
                    + p[1] * transform[1][j]
                    + p[2] * transform[2][j]
                    + transform[j][3]
            };
            [-c(0), -c(1), c(2)]
        };
        for f in faces {
            let [a, b, c] = f.map(|k| world[k as usize]);
            let n = cross(sub(b, a), sub(c, a));
            for k in f {
                let m = &mut normals[*k as usize];
                for d in 0..3 {
                    m[d] += n[d];
                }
            }
            let [va, vb, vc] = [a, b, c].map(view);
            let vn = cross(sub(vb, va), sub(vc, va));
            let centroid = [0, 1, 2].map(|d| (va[d] + vb[d] + vc[d]) / 3.0);
            front.push(dot(vn, centroid) < 0.0);
        }
        let normals: Vec<[f32; 3]> = normals
            .into_iter()
            .map(|n| {
                let l = dot(n, n).sqrt().max(1e-20);
                n.map(|x| (x / l) as f32)
            })
            .collect();
        let anchors = &self.anchors;
        // Face units per pixel at the head's distance (for the texture's level of detail).
        let distance = transform[2][3].abs().max(1e-3);
        let focal_px = 0.5 * NDC_FOCAL * self.config.size as f64;
        let fp = (distance / focal_px * anchors.scale as f64 / FLAME_SCALE) as f32;
        let light = appearance.light;
        let ambient = appearance.ambient;
        let pixels = g.resolve(|fi, b| {
            let fi = fi as usize;
            let f = faces[fi];
            let mut q = [0f32; 3];
            let mut n = [0f32; 3];
            for k in 0..3 {
                let v = f[k] as usize;
                let (cq, cn) = (anchors.canonical[v], normals[v]);
                for d in 0..3 {
                    q[d] += b[k] * cq[d];
                    n[d] += b[k] * cn[d];
                }
            }
            if !front[fi] {
                return appearance.interior(anchors, q);
            }
            let nl = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-12);
            let diffuse = ((n[0] * light[0] + n[1] * light[1] + n[2] * light[2]) / nl).max(0.0);
            let albedo = appearance.albedo(anchors, anchors.face_material[fi], q, fp);
            let s = ambient + (1.0 - ambient) * diffuse;
            albedo.map(|c| c * s)
        });
        Ok(to_rgb8(&pixels, self.config.size, self.config.size))
    }

    /// The FLAME vertices of one frame of the dataset (computed within its block, as the
    /// dataset does, so the result is bit-identical to the written one).
    pub fn frame_vertices(
        &self,
        identity: usize,
        frame: usize,
    ) -> Result<(FrameSample, Vec<[f32; 3]>)> {
        let (first, count) = self.block_of(identity, frame)?;
        let shape = self.shape(identity);
        let mut block = self.block_vertices(identity, &shape, first, count)?;
        Ok(block.swap_remove(frame - first))
    }

    /// Renders one frame exactly as the dataset holds it (an error outside the dataset).
    pub fn render(&self, identity: usize, frame: usize) -> Result<RenderedFrame> {
        let shape = self.shape(identity);
        let (s, verts) = self.frame_vertices(identity, frame)?;
        let app = self.appearance(identity);
        Ok(RenderedFrame {
            name: frame_name(identity, frame),
            image: self.shade(&app, &s.transform, &verts)?,
            record: self.record(&shape, &s, &verts),
        })
    }

    /// Work units: (identity, first frame, frame count) per FLAME block, in name order.
    fn units(&self) -> Vec<(usize, usize, usize)> {
        let m = self.config.frames;
        (0..self.config.identities)
            .flat_map(|i| {
                (0..m)
                    .step_by(FLAME_BLOCK)
                    .map(move |f| (i, f, FLAME_BLOCK.min(m - f)))
            })
            .collect()
    }

    /// Renders one block: names, images and records, in frame order.
    fn render_unit(&self, unit: (usize, usize, usize)) -> Result<Vec<RenderedFrame>> {
        let (identity, first, count) = unit;
        let shape = self.shape(identity);
        let app = self.appearance(identity);
        let block = self.block_vertices(identity, &shape, first, count)?;
        block
            .par_iter()
            .enumerate()
            .map(|(k, (s, verts))| {
                Ok(RenderedFrame {
                    name: frame_name(identity, first + k),
                    image: self.shade(&app, &s.transform, verts)?,
                    record: self.record(&shape, s, verts),
                })
            })
            .collect()
    }

    /// Every frame's record (no rendering).
    pub fn records(&self) -> Result<BTreeMap<String, TrackedFrame>> {
        let per_unit: Vec<Vec<(String, TrackedFrame)>> = self
            .units()
            .into_par_iter()
            .map(|(identity, first, count)| {
                let shape = self.shape(identity);
                let block = self.block_vertices(identity, &shape, first, count)?;
                Ok(block
                    .iter()
                    .enumerate()
                    .map(|(k, (s, v))| (frame_name(identity, first + k), self.record(&shape, s, v)))
                    .collect())
            })
            .collect::<Result<_>>()?;
        Ok(per_unit.into_iter().flatten().collect())
    }

    /// Generates the whole dataset into `dir` in the release layout. The output appears
    /// atomically: everything is written into a temporary sibling folder that is renamed to
    /// `dir` only when complete and verified (by reopening it); on any error or cancellation
    /// nothing is left behind. Missing parent folders are created.
    pub fn write_dataset(
        &self,
        dir: &Path,
        options: WriteOptions,
        progress: &dyn Progress,
    ) -> Result<DatasetSummary> {
        let out_err = |path: &Path, reason: String| SynthError::Output {
            path: path.to_owned(),
            reason,
        };
        if dir.exists() {
            if !dir.is_dir() {
                return Err(out_err(dir, "exists and is not a folder".into()));
            }
            let non_empty = std::fs::read_dir(dir)
                .map_err(|e| out_err(dir, format!("cannot read: {e}")))?
                .next()
                .is_some();
            if non_empty && !options.overwrite {
                return Err(out_err(
                    dir,
                    "exists and is not empty (choose a new folder, or allow overwriting)".into(),
                ));
            }
        }
        if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent)
                .map_err(|e| out_err(parent, format!("cannot create: {e}")))?;
        }
        let tmp = temp_sibling(dir);
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp)
                .map_err(|e| out_err(&tmp, format!("cannot remove a stale temporary: {e}")))?;
        }
        std::fs::create_dir(&tmp).map_err(|e| out_err(&tmp, format!("cannot create: {e}")))?;
        let result = self.write_into(&tmp, progress);
        match result {
            Ok(frames) => {
                if let Err(e) = move_into_place(&tmp, dir) {
                    let _ = std::fs::remove_dir_all(&tmp);
                    return Err(e);
                }
                Ok(DatasetSummary {
                    dir: dir.to_owned(),
                    frames,
                    splits: self.splits(),
                })
            }
            Err(e) => {
                let _ = std::fs::remove_dir_all(&tmp);
                Err(e)
            }
        }
    }

    fn write_into(&self, tmp: &Path, progress: &dyn Progress) -> Result<usize> {
        if progress.cancelled() {
            return Err(SynthError::Interrupted);
        }
        let records = self.records()?;
        let units = self.units();
        let failure: Mutex<Option<SynthError>> = Mutex::new(None);
        let fail = |e: SynthError| {
            if let Ok(mut slot) = failure.lock() {
                slot.get_or_insert(e);
            }
        };
        let mut pending = units.chunks(CHUNK_BLOCKS);
        let mut ready: VecDeque<(String, Vec<u8>)> = VecDeque::new();
        let mut stopped = false;
        // Images stream into the LMDB writer chunk by chunk; a failure stops the stream and is
        // reported below (the writer's own check would only see missing images).
        let images = std::iter::from_fn(|| loop {
            if let Some(item) = ready.pop_front() {
                return Some(item);
            }
            if stopped {
                return None;
            }
            let chunk = pending.next()?;
            if progress.cancelled() {
                fail(SynthError::Interrupted);
                stopped = true;
                return None;
            }
            let rendered: Result<Vec<Encoded>> = chunk
                .par_iter()
                .map(|&unit| {
                    let frames = self.render_unit(unit)?;
                    progress.advance(frames.len());
                    frames
                        .into_iter()
                        .map(|f| Ok((f.name, encode_png(&f.image)?)))
                        .collect()
                })
                .collect();
            match rendered {
                Ok(r) => ready.extend(r.into_iter().flatten()),
                Err(e) => {
                    fail(e);
                    stopped = true;
                    return None;
                }
            }
        });
        let written = write_release_dataset(tmp, &records, images, &self.splits());
        if let Some(e) = failure.lock().ok().and_then(|mut s| s.take()) {
            return Err(e);
        }
        written?;
        Ok(records.len())
    }
}

/// Renames the finished `tmp` folder to `dir`; an existing `dir` is moved aside first and
/// deleted once the new one is in place (moved back if that fails).
fn move_into_place(tmp: &Path, dir: &Path) -> Result<()> {
    gagavatar_formats::atomic::replace_dir(tmp, dir).map_err(|e| SynthError::Output {
        path: dir.to_owned(),
        reason: format!("cannot move the new folder into place: {e}"),
    })
}
