//! What `reenact`, `orbit` and `export-ply` share: loading the model, FLAME and the source,
//! reconstructing the avatar once, and turning batches of (record, camera) into RGB frames with
//! a per-stage time split.

pub use crate::progress::{progress, spinner};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use clap::Args;
use gagavatar_flame::{FlameIdentity, FlameModel, TrackedFrame};
use gagavatar_net::checkpoint;
use gagavatar_net::model::{Avatar, GagAvatar};
use gagavatar_net::style_unet::Noise;
use gagavatar_video::{VideoOptions, VideoWriter};

use crate::cmd_model::{image_tensor, load_flame, preset, read_image};
use crate::tracking;

/// The inputs every avatar command needs.
#[derive(Debug, Args)]
pub struct SourceArgs {
    /// Weights: the release `GAGAvatar.pt`, or safetensors from `convert` / `init-weights`.
    #[arg(long)]
    pub ckpt: PathBuf,
    /// FLAME asset (`FLAME_with_eye.pt`, or safetensors with the same keys); `synthetic` for the
    /// built-in synthetic asset that synth-data, train and the demo model use.
    #[arg(long)]
    pub flame: PathBuf,
    /// Source: a photo (tracked now, or found in the tracking cache), a tracked folder
    /// (`gagavatar track` output), or with --source-record the model-ready image (resized with a
    /// notice when it is not image_size square).
    #[arg(long)]
    pub source: PathBuf,
    /// Source tracking: a tracked-frame JSON record, or a release `optim.pkl` (with
    /// --source-key); without it the source is tracked.
    #[arg(long)]
    pub source_record: Option<PathBuf>,
    /// Frame name inside a `.pkl` source record or a tracked folder (e.g. `video_000`).
    #[arg(long)]
    pub source_key: Option<String>,
    /// Architecture, when the weights file does not say (the release `.pt` is `release`).
    #[arg(long)]
    pub preset: Option<String>,
    /// Shape components at the start of the FLAME asset's `shapedirs`.
    #[arg(long, default_value_t = 300)]
    pub n_shape: usize,
    /// Expression components after them.
    #[arg(long, default_value_t = 100)]
    pub n_exp: usize,
    /// Draw fresh renderer noise per frame (the release's behaviour) instead of the fixed buffers.
    #[arg(long)]
    pub fresh_noise: bool,
}

/// Wall time per stage, summed over frames.
#[derive(Debug, Default, Clone)]
pub struct Timings {
    pub load: Duration,
    pub reconstruct: Duration,
    pub flame: Duration,
    pub splat: Duration,
    pub renderer: Duration,
    pub encode: Duration,
    /// The whole drive (FLAME, splatting, renderer, read-back) when it runs on a GPU.
    pub gpu: Duration,
    pub frames: usize,
}

impl Timings {
    /// One summary line per stage, per frame where it runs per frame.
    pub fn report(&self, total: Duration) -> String {
        let ms = |d: Duration| 1e3 * d.as_secs_f64();
        let per = |d: Duration| ms(d) / self.frames.max(1) as f64;
        if self.gpu > Duration::ZERO {
            return format!(
                "time: load {:.0} ms, reconstruct {:.0} ms; per frame: GPU drive (FLAME, \
splatting, renderer, read-back) {:.1} ms, video encoding {:.1} ms; {} frames, total wall {:.1} s \
({:.2} frames/s)",
                ms(self.load),
                ms(self.reconstruct),
                per(self.gpu),
                per(self.encode),
                self.frames,
                total.as_secs_f64(),
                self.frames as f64 / total.as_secs_f64().max(1e-9),
            );
        }
        format!(
            "time: load {:.0} ms, reconstruct {:.0} ms; per frame: FLAME {:.1} ms, splatting {:.1} ms, \
neural renderer {:.1} ms, video encoding {:.1} ms; {} frames, total wall {:.1} s ({:.2} frames/s)",
            ms(self.load),
            ms(self.reconstruct),
            per(self.flame),
            per(self.splat),
            per(self.renderer),
            per(self.encode),
            self.frames,
            total.as_secs_f64(),
            self.frames as f64 / total.as_secs_f64().max(1e-9),
        )
    }
}

/// A reconstructed avatar, ready to be driven.
pub struct Session {
    pub model: GagAvatar,
    pub flame: FlameModel,
    pub source: TrackedFrame,
    pub avatar: Avatar,
    identity: FlameIdentity,
    pub noise: Noise,
    pub timings: Timings,
    /// The drive on a GPU, when [`Session::use_device`] found one.
    gpu: Option<gagavatar_gpu::drive::GpuDrive>,
}

/// Reads the source record: JSON, or a frame of a release pickle.
pub fn read_source_record(path: &Path, key: Option<&str>) -> Result<TrackedFrame> {
    // The data crate's errors already name the file and field.
    Ok(gagavatar_data::read_source_record(path, key)?)
}

/// Where the source image comes from.
pub enum SourceImage {
    /// A file given with its record (`--source-record`).
    File(PathBuf),
    /// The 512 crop of a tracked folder.
    Crop(image::RgbImage),
}

/// The source image and record, however they were given.
pub struct ResolvedSource {
    pub image: SourceImage,
    pub record: TrackedFrame,
    /// Names the record in errors.
    pub label: String,
}

/// `--source` with `--source-record` as given; else `--source` is a tracked folder, or a photo
/// tracked now (or found in the tracking cache). A photo without a face fails with "no face
/// found in PATH" before anything is written.
pub fn resolve_source(a: &SourceArgs) -> Result<ResolvedSource> {
    if let Some(rec) = &a.source_record {
        return Ok(ResolvedSource {
            image: SourceImage::File(a.source.clone()),
            record: read_source_record(rec, a.source_key.as_deref())?,
            label: rec.display().to_string(),
        });
    }
    let dir = if tracking::is_tracked_folder(&a.source) {
        a.source.clone()
    } else {
        tracking::tracked_inline(&a.source, &a.flame, "source", true)?.dir
    };
    from_tracked_folder(&dir, a.source_key.as_deref())
}

/// Frame `key` of a tracked folder (its only frame when `key` is `None`): the crop from
/// `img_lmdb/` and the record from `optim.pkl` (else `smoothed.pkl`).
pub fn from_tracked_folder(dir: &Path, key: Option<&str>) -> Result<ResolvedSource> {
    let pkl = [
        gagavatar_track::output::OPTIM_FILE,
        gagavatar_track::output::SMOOTHED_FILE,
    ]
    .iter()
    .map(|f| dir.join(f))
    .find(|p| p.is_file())
    .with_context(|| format!("{} is not a tracked folder (no optim.pkl)", dir.display()))?;
    let mut records = gagavatar_data::read_records(&pkl)?;
    let key = match key {
        Some(k) => k.to_owned(),
        None if records.len() == 1 => records.keys().next().cloned().unwrap_or_default(),
        None => bail!(
            "{} holds {} frames: name one with --source-key (e.g. {})",
            pkl.display(),
            records.len(),
            records.keys().next().cloned().unwrap_or_default()
        ),
    };
    let record = records
        .remove(&key)
        .with_context(|| format!("{} has no frame `{key}`", pkl.display()))?;
    let lmdb_path = dir.join(gagavatar_track::output::IMAGES_DIR);
    let lmdb = gagavatar_data::LmdbReader::open(&lmdb_path)?;
    let bytes = lmdb
        .get(key.as_bytes())?
        .with_context(|| format!("{} has no image `{key}`", lmdb_path.display()))?;
    let image = gagavatar_data::decode_image(&bytes, &lmdb_path, &key)?;
    Ok(ResolvedSource {
        image: SourceImage::Crop(image),
        record,
        label: format!("`{key}` of {}", pkl.display()),
    })
}

/// Reads weights and builds the model; also returns the fingerprint of the FLAME asset the
/// weights were trained with, when they record one.
pub fn load_model_noting_flame(
    ckpt: &Path,
    explicit: Option<&gagavatar_net::ModelConfig>,
) -> Result<(GagAvatar, Option<String>)> {
    let loading = || format!("loading {}", ckpt.display());
    let weights = checkpoint::read_weights(ckpt).with_context(loading)?;
    let trained_with = weights
        .metadata
        .get(checkpoint::FLAME_METADATA_KEY)
        .cloned();
    let cfg = checkpoint::resolve_config(&weights, explicit);
    checkpoint::check_keys(&cfg, &weights.tensors).with_context(loading)?;
    let model =
        checkpoint::build_model(&cfg, weights.tensors, &Device::Cpu).with_context(loading)?;
    Ok((model, trained_with))
}

/// Why a FLAME asset (by fingerprint) does not fit weights, or `None` when it does or cannot be
/// told. Weights written by `gagavatar train` record their asset's fingerprint; for others the
/// architecture tells: the release's weights were trained with the real FLAME, the `tiny` and
/// `small` ones (trained here) with the built-in synthetic asset unless `train --flame` said
/// otherwise.
pub fn flame_mismatch(
    trained_with: Option<&str>,
    architecture: &str,
    asset: u64,
) -> Option<String> {
    let synthetic = synthetic_fingerprint();
    let ours = format!("{asset:016x}");
    match trained_with {
        Some(fp) if fp.eq_ignore_ascii_case(&ours) => None,
        Some(fp) => Some(format!(
            "the weights were trained with another FLAME asset (fingerprint {fp}, this one is \
             {ours}{}); the avatar will be distorted. Pass the asset they were trained with",
            if asset == synthetic { ", the built-in synthetic one" } else { "" }
        )),
        None if architecture == "release" && asset == synthetic => Some(
            "the release weights were trained with the real FLAME asset (FLAME_with_eye.pt), not \
             the built-in synthetic stand-in; the avatar will be distorted"
                .into(),
        ),
        None if architecture != "release" && asset != synthetic => Some(format!(
            "`{architecture}` weights without a recorded FLAME asset were trained with the built-in \
             synthetic one (--flame synthetic); this asset differs (fingerprint {ours}), so the \
             avatar may be distorted"
        )),
        None => None,
    }
}

/// The fingerprint of the built-in synthetic asset (`gagavatar flame synth`, seed 0).
fn synthetic_fingerprint() -> u64 {
    static FP: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *FP.get_or_init(|| gagavatar_flame::synthesize(0).fingerprint())
}

/// The 3x4 transform of a record as `[3, 4]` f32 values, or an error naming the record.
pub fn record_transform(record: &TrackedFrame, what: &str) -> Result<[[f64; 4]; 3]> {
    record
        .transform_matrix
        .with_context(|| format!("{what} has no transform_matrix"))
}

pub fn transforms_tensor(tms: &[[[f64; 4]; 3]]) -> Result<Tensor> {
    let flat: Vec<f32> = tms
        .iter()
        .flat_map(|m| m.iter().flatten().map(|&x| x as f32))
        .collect();
    Ok(Tensor::from_vec(flat, (tms.len(), 3, 4), &Device::Cpu)?)
}

impl Session {
    /// Resolves the source (tracking a raw photo first) and reconstructs the avatar.
    pub fn open(a: &SourceArgs) -> Result<Self> {
        let src = resolve_source(a)?;
        Self::open_resolved(a, src)
    }

    pub fn open_resolved(a: &SourceArgs, src: ResolvedSource) -> Result<Self> {
        let t0 = Instant::now();
        let explicit = a.preset.as_deref().map(preset).transpose()?;
        let source = src.record;
        let source_tm = record_transform(&source, "the source record")?;
        let (model, trained_with) = load_model_noting_flame(&a.ckpt, explicit.as_ref())?;
        let flame = load_flame(&a.flame, a.n_shape, a.n_exp)?;
        if let Some(warning) = flame_mismatch(
            trained_with.as_deref(),
            &model.cfg.name,
            flame.asset_fingerprint,
        ) {
            eprintln!(
                "warning: {} with FLAME asset {}: {warning}",
                a.ckpt.display(),
                a.flame.display()
            );
        }
        if flame.n_vertices != model.cfg.n_vertices {
            bail!(
                "FLAME asset {} has {} vertices, the model expects {}",
                a.flame.display(),
                flame.n_vertices,
                model.cfg.n_vertices
            );
        }
        let image = match &src.image {
            SourceImage::File(path) => read_image(path, model.cfg.image_size)?,
            SourceImage::Crop(img) => image_tensor(img, model.cfg.image_size)?,
        };
        let shape = source
            .params(&flame)
            .with_context(|| format!("source record {}", src.label))?
            .shape;
        let identity = flame.identity(&shape)?;
        let source_transform = transforms_tensor(&[source_tm])?;
        let load = t0.elapsed();
        let t1 = Instant::now();
        let avatar = model.reconstruct(&image, &source_transform)?;
        let reconstruct = t1.elapsed();
        Ok(Self {
            model,
            flame,
            source,

            avatar,
            identity,
            noise: if a.fresh_noise {
                Noise::Fresh
            } else {
                Noise::Fixed
            },
            timings: Timings {
                load,
                reconstruct,
                ..Default::default()
            },
            gpu: None,
        })
    }

    /// Renders frames on a GPU from now on when `device` asks for one (and one is found):
    /// uploads the avatar, FLAME and the renderer once.
    pub fn use_device(&mut self, device: &crate::device_args::DeviceArgs) -> Result<()> {
        let Some(gpu) = device.open()? else {
            return Ok(());
        };
        let t0 = Instant::now();
        let tuning = gagavatar_gpu::Tuning::from_env()?;
        self.gpu = Some(gagavatar_gpu::drive::GpuDrive::from_model(
            gpu,
            &tuning,
            &self.model,
            &self.avatar,
            &self.flame,
            &self.identity,
            self.noise,
        )?);
        self.timings.load += t0.elapsed();
        Ok(())
    }

    pub fn image_size(&self) -> usize {
        self.model.cfg.image_size
    }

    /// FLAME vertices `[B, V, 3]` with the source's identity and each record's expression, jaw
    /// and eyes (spec section 10).
    pub fn vertices(&mut self, records: &[&TrackedFrame], names: &[String]) -> Result<Tensor> {
        let t0 = Instant::now();
        let mut exp = Vec::with_capacity(records.len());
        let mut pose = Vec::with_capacity(records.len());
        let mut eye = Vec::with_capacity(records.len());
        for (r, name) in records.iter().zip(names) {
            let p = r
                .params(&self.flame)
                .with_context(|| format!("driver frame `{name}`"))?;
            exp.push(p.expression);
            pose.push(p.pose);
            eye.push(p.eye);
        }
        let out = self.flame.forward_with_identity(
            &self.identity,
            &Tensor::cat(&exp, 0)?,
            &Tensor::cat(&pose, 0)?,
            &Tensor::cat(&eye, 0)?,
        )?;
        self.timings.flame += t0.elapsed();
        Ok(out.vertices)
    }

    /// Renders a batch: FLAME, splatting and the neural renderer; RGB u8 frames (HWC).
    pub fn render(
        &mut self,
        records: &[&TrackedFrame],
        names: &[String],
        transforms: &[[[f64; 4]; 3]],
    ) -> Result<Vec<Vec<u8>>> {
        if let Some(drive) = &mut self.gpu {
            let t0 = Instant::now();
            let mut out = Vec::with_capacity(records.len());
            for ((r, name), tm) in records.iter().zip(names).zip(transforms) {
                let codes = gagavatar_gpu::flame::FrameCodes::from_record(r, &self.flame)
                    .with_context(|| format!("driver frame `{name}`"))?;
                out.push(drive.frame_rgb8(&codes, tm)?);
            }
            self.timings.gpu += t0.elapsed();
            self.timings.frames += records.len();
            return Ok(out);
        }
        let verts = self.vertices(records, names)?;
        let tm = transforms_tensor(transforms)?;
        let t0 = Instant::now();
        let coarse = self.model.splat_coarse(&self.avatar, &verts, &tm)?;
        let t1 = Instant::now();
        self.timings.splat += t1 - t0;
        let fine = self.model.render(&coarse, self.noise)?;
        self.timings.renderer += t1.elapsed();
        self.timings.frames += records.len();
        to_rgb8(&fine)
    }
}

/// One output frame to render: the expression record, a name for errors, the camera.
pub struct FrameJob<'a> {
    pub record: &'a TrackedFrame,
    pub name: String,
    pub transform: [[f64; 4]; 3],
}

impl Session {
    /// Renders `jobs` in batches into a video at `output` (format by extension), `decorate`
    /// turning frame `i`'s rendered image into the written one (e.g. side by side with its
    /// driver); `width` is the written width. Progress bar, Ctrl-C check between batches,
    /// encode time in the timings.
    #[allow(clippy::too_many_arguments)]
    pub fn render_video(
        &mut self,
        output: &Path,
        width: usize,
        opts: VideoOptions,
        jobs: &[FrameJob],
        batch: usize,
        label: &str,
        mut decorate: impl FnMut(usize, Vec<u8>) -> Result<Vec<u8>>,
    ) -> Result<()> {
        let size = self.image_size();
        let fps = opts.fps;
        let mut writer = VideoWriter::create(output, width, size, opts)
            .with_context(|| format!("creating {}", output.display()))?;
        let bar = progress(jobs.len(), label);
        for (c, chunk) in jobs.chunks(batch.max(1)).enumerate() {
            crate::check_interrupt()?;
            let records: Vec<_> = chunk.iter().map(|j| j.record).collect();
            let names: Vec<String> = chunk.iter().map(|j| j.name.clone()).collect();
            let transforms: Vec<_> = chunk.iter().map(|j| j.transform).collect();
            for (k, img) in self
                .render(&records, &names, &transforms)?
                .into_iter()
                .enumerate()
            {
                let frame = decorate(c * batch.max(1) + k, img)?;
                let t0 = Instant::now();
                writer.push_rgb(&frame)?;
                self.timings.encode += t0.elapsed();
                bar.inc(1);
            }
        }
        let t0 = Instant::now();
        writer.finish()?;
        self.timings.encode += t0.elapsed();
        bar.finish_and_clear();
        eprintln!(
            "wrote {} ({} frames, {width}x{size}, {fps} fps)",
            output.display(),
            jobs.len()
        );
        Ok(())
    }
}

/// `[B, 3, H, W]` in [0, 1] -> B interleaved RGB u8 frames.
pub fn to_rgb8(images: &Tensor) -> Result<Vec<Vec<u8>>> {
    let (b, c, h, w) = images.dims4()?;
    if c != 3 {
        bail!("expected RGB images, got {c} channels");
    }
    let data: Vec<f32> = images
        .to_dtype(candle_core::DType::F32)?
        .flatten_all()?
        .to_vec1()?;
    let plane = h * w;
    Ok((0..b)
        .map(|i| {
            let img = &data[i * 3 * plane..(i + 1) * 3 * plane];
            let mut out = vec![0u8; 3 * plane];
            for p in 0..plane {
                for ch in 0..3 {
                    let v = img[ch * plane + p];
                    // NaN maps to 0 (`as` saturates), so a broken frame is visible, not fatal.
                    out[3 * p + ch] = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
                }
            }
            out
        })
        .collect())
}

/// Places `left` (fitted into `w` x `h` without distortion: black bars where its shape differs)
/// and `right` side by side.
pub fn side_by_side(left: &image::RgbImage, right: &[u8], w: usize, h: usize) -> Vec<u8> {
    let (lw, lh) = (left.width() as usize, left.height() as usize);
    let fitted = if lw == w && lh == h {
        left.clone()
    } else {
        let scale = (w as f64 / lw.max(1) as f64).min(h as f64 / lh.max(1) as f64);
        let nw = ((lw as f64 * scale).round() as u32).clamp(1, w as u32);
        let nh = ((lh as f64 * scale).round() as u32).clamp(1, h as u32);
        let small = image::imageops::resize(left, nw, nh, image::imageops::FilterType::Triangle);
        let mut canvas = image::RgbImage::new(w as u32, h as u32);
        image::imageops::overlay(
            &mut canvas,
            &small,
            i64::from((w as u32 - nw) / 2),
            i64::from((h as u32 - nh) / 2),
        );
        canvas
    };
    let mut out = vec![0u8; 2 * w * h * 3];
    for y in 0..h {
        let row = &mut out[y * 2 * w * 3..(y + 1) * 2 * w * 3];
        row[..w * 3].copy_from_slice(&fitted.as_raw()[y * w * 3..(y + 1) * w * 3]);
        row[w * 3..].copy_from_slice(&right[y * w * 3..(y + 1) * w * 3]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flame_mismatches_are_reported() {
        let synthetic = synthetic_fingerprint();
        let other = synthetic ^ 1;
        let fp = |x: u64| format!("{x:016x}");
        // Recorded fingerprints decide.
        assert!(flame_mismatch(Some(&fp(synthetic)), "tiny", synthetic).is_none());
        assert!(flame_mismatch(Some(&fp(other)), "release", other).is_none());
        let w = flame_mismatch(Some(&fp(other)), "tiny", synthetic).unwrap();
        assert!(
            w.contains("another FLAME asset") && w.contains("synthetic"),
            "{w}"
        );
        // Without one, the architecture: release with the stand-in, tiny with another asset.
        let w = flame_mismatch(None, "release", synthetic).unwrap();
        assert!(w.contains("FLAME_with_eye.pt"), "{w}");
        assert!(flame_mismatch(None, "release", other).is_none());
        assert!(flame_mismatch(None, "tiny", synthetic).is_none());
        assert!(flame_mismatch(None, "small", other).is_some());
    }
}
