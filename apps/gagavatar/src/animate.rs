//! What `reenact`, `orbit` and `export-ply` share, as a shell over the pipeline library
//! (`gagavatar-avatar`): the source arguments, resolving the source (a tracked folder, a record
//! and image, or a photo tracked now), and writing driven frames to a video with a progress bar
//! and a per-stage time split.

pub use crate::progress::{progress, spinner};
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use gagavatar_avatar::{Avatar, Drive, DriveTimes, Engine, EngineConfig, FlameSource};
use gagavatar_flame::TrackedFrame;
use gagavatar_net::style_unet::Noise;
use gagavatar_video::{VideoOptions, VideoWriter};

use crate::device_args::DeviceArgs;
use crate::tracking;

/// The inputs every avatar command needs.
#[derive(Debug, Args)]
pub struct SourceArgs {
    /// Weights: the release `GAGAvatar.pt`, or safetensors from `convert` / `init-weights`.
    #[arg(long)]
    pub ckpt: PathBuf,
    /// FLAME asset (`FLAME_with_eye.pt`, or safetensors with the same keys); `synthetic` for the
    /// built-in synthetic asset that synth-data, train and the demo model use. Default: the
    /// asset the weights name (the synthetic one for the demo model and weights trained here;
    /// the release's weights need FLAME_with_eye.pt).
    #[arg(long)]
    pub flame: Option<PathBuf>,
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
    /// Arithmetic of the model's products on the CPU: f32 (the release's) or bf16 (bf16
    /// operands, f32 sums; reconstruct ~1.3x faster; needs AVX512-BF16: AMD Zen 4, Intel
    /// Sapphire Rapids).
    #[arg(long, default_value = "f32")]
    pub precision: gagavatar_ops::Precision,
}

impl SourceArgs {
    /// What the library loads for these arguments.
    pub fn engine_config(&self) -> EngineConfig {
        let mut cfg = EngineConfig::new(&self.ckpt);
        cfg.flame = self
            .flame
            .as_deref()
            .map_or(FlameSource::FromWeights, FlameSource::from_arg);
        cfg.preset = self.preset.clone();
        cfg.n_shape = self.n_shape;
        cfg.n_exp = self.n_exp;
        cfg.precision = self.precision;
        cfg.noise = if self.fresh_noise {
            Noise::Fresh
        } else {
            Noise::Fixed
        };
        cfg
    }

    /// Loads the weights and FLAME once, printing the library's warnings.
    pub fn open_engine(&self) -> Result<Engine> {
        let engine =
            Engine::open(&self.engine_config()).map_err(crate::cmd_model::with_flag_hints)?;
        for w in engine.warnings() {
            eprintln!("warning: {w}");
        }
        Ok(engine)
    }
}

/// Wall time per stage, summed over frames.
#[derive(Debug, Default, Clone)]
pub struct Timings {
    pub load: Duration,
    pub reconstruct: Duration,
    pub encode: Duration,
    /// The drive's own split (FLAME, splatting, renderer; or the whole GPU drive).
    pub drive: DriveTimes,
}

impl Timings {
    /// One summary line per stage, per frame where it runs per frame.
    pub fn report(&self, total: Duration) -> String {
        let ms = |d: Duration| 1e3 * d.as_secs_f64();
        let d = &self.drive;
        let per = |t: Duration| ms(t) / d.frames.max(1) as f64;
        if d.gpu > Duration::ZERO {
            return format!(
                "time: load {:.0} ms, reconstruct {:.0} ms; per frame: GPU drive (FLAME, \
splatting, renderer, read-back) {:.1} ms, video encoding {:.1} ms; {} frames, total wall {:.1} s \
({:.2} frames/s)",
                ms(self.load),
                ms(self.reconstruct),
                per(d.gpu),
                per(self.encode),
                d.frames,
                total.as_secs_f64(),
                d.frames as f64 / total.as_secs_f64().max(1e-9),
            );
        }
        format!(
            "time: load {:.0} ms, reconstruct {:.0} ms; per frame: FLAME {:.1} ms, splatting {:.1} ms, \
neural renderer {:.1} ms, video encoding {:.1} ms; {} frames, total wall {:.1} s ({:.2} frames/s)",
            ms(self.load),
            ms(self.reconstruct),
            per(d.flame),
            per(d.splat),
            per(d.renderer),
            per(self.encode),
            d.frames,
            total.as_secs_f64(),
            d.frames as f64 / total.as_secs_f64().max(1e-9),
        )
    }
}

/// A reconstructed avatar (sharing the engine's model and FLAME) and the drive that renders it
/// (on the CPU or a GPU).
pub struct Session {
    pub avatar: Avatar,
    drive: Box<dyn Drive>,
    pub timings: Timings,
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
/// tracked now (or found in the tracking cache) with the engine's FLAME asset. A photo without a
/// face fails with "no face found in PATH" before anything is written.
pub fn resolve_source(a: &SourceArgs, engine: &Engine) -> Result<ResolvedSource> {
    if let Some(rec) = &a.source_record {
        return Ok(ResolvedSource {
            image: SourceImage::File(a.source.clone()),
            record: read_source_record(rec, a.source_key.as_deref())?,
            label: rec.display().to_string(),
        });
    }
    if tracking::is_tracked_folder(&a.source) {
        return from_tracked_folder(&a.source, a.source_key.as_deref());
    }
    // The library hands back the crop and record it wrote (or found in the cache).
    let t = tracking::tracked_inline(engine, &a.source, "source", true)?;
    let label = format!("the tracking of {}", a.source.display());
    match (t.crop, t.records.into_iter().next()) {
        (Some(crop), Some(record)) => Ok(ResolvedSource {
            image: SourceImage::Crop(crop),
            record,
            label,
        }),
        _ => bail!("{label} holds no photo"),
    }
}

/// Frame `key` of a tracked folder (its only frame when `key` is `None`): the crop from
/// `img_lmdb/` and the record from `optim.pkl` (else `smoothed.pkl`).
pub fn from_tracked_folder(dir: &Path, key: Option<&str>) -> Result<ResolvedSource> {
    let (image, record, label) = gagavatar_avatar::cache::read_tracked_frame(dir, key)?;
    Ok(ResolvedSource {
        image: SourceImage::Crop(image),
        record,
        label,
    })
}

/// The 3x4 transform of a record as `[3, 4]` f32 values, or an error naming the record.
pub fn record_transform(record: &TrackedFrame, what: &str) -> Result<[[f64; 4]; 3]> {
    record
        .transform_matrix
        .with_context(|| format!("{what} has no transform_matrix"))
}

impl Session {
    /// Loads the engine, resolves the source (tracking a raw photo first) and reconstructs the
    /// avatar, on the GPU `device` asks for (and renders there) when one is found.
    pub fn open(a: &SourceArgs, device: &DeviceArgs, what: &str) -> Result<Self> {
        let t0 = Instant::now();
        let engine = a.open_engine()?;
        let load = t0.elapsed();
        let src = resolve_source(a, &engine)?;
        Self::with_source(&engine, src, load, device, what)
    }

    /// Reconstructs the avatar of an already resolved source; `load` is the engine's load time.
    /// With a GPU (`device`), the network runs there and the Gaussians stay there for the
    /// drive; `what` says in the device line what runs on it.
    pub fn with_source(
        engine: &Engine,
        src: ResolvedSource,
        load: Duration,
        device: &DeviceArgs,
        what: &str,
    ) -> Result<Self> {
        let size = engine.image_size();
        let image = match src.image {
            SourceImage::File(path) => crate::cmd_model::read_rgb(&path, size)?,
            SourceImage::Crop(img) => img,
        };
        let context = || format!("source record {}", src.label);
        let mut timings = Timings {
            load,
            ..Default::default()
        };
        let (avatar, drive): (Avatar, Box<dyn Drive>) = match device.open_for(what)? {
            Some(gpu) => {
                let t0 = Instant::now();
                let tuning = device.tuning(&gpu)?;
                let rec = engine.gpu_reconstruct(gpu.clone(), &tuning)?;
                timings.load += t0.elapsed();
                let t1 = Instant::now();
                let avatar = engine
                    .avatar_on_gpu(&rec, &image, &src.record)
                    .with_context(context)?;
                timings.reconstruct = t1.elapsed();
                let t2 = Instant::now();
                let drive = Box::new(avatar.gpu_drive(gpu, &tuning)?);
                timings.load += t2.elapsed();
                (avatar, drive)
            }
            None => {
                let t1 = Instant::now();
                let avatar = engine.avatar(&image, &src.record).with_context(context)?;
                timings.reconstruct = t1.elapsed();
                let drive = Box::new(avatar.cpu_drive());
                (avatar, drive)
            }
        };
        Ok(Self {
            avatar,
            drive,
            timings,
        })
    }

    /// The record the avatar was made from.
    pub fn source(&self) -> &TrackedFrame {
        self.avatar.source()
    }

    pub fn image_size(&self) -> usize {
        self.avatar.image_size()
    }
}

/// One output frame to render: the expression record, a name for errors, the camera.
pub struct FrameJob<'a> {
    pub record: &'a TrackedFrame,
    pub name: String,
    pub transform: [[f64; 4]; 3],
}

/// Frames rendered ahead of the encoder at most (memory: a few RGB frames).
const ENCODE_QUEUE: usize = 4;

impl Session {
    /// Renders `jobs` into a video at `output` (format by extension), `decorate` turning frame
    /// `i`'s rendered image into the written one (e.g. side by side with its driver); `width`
    /// is the written width. The CPU renders `batch` frames at a time; a GPU streams them (one
    /// rendering while the last is read back, decorated and queued for the encoder). Progress
    /// bar, Ctrl-C check per frame, encode time in the timings.
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
        // The encoder runs on its own thread, a few frames behind, so encoding overlaps the
        // rendering of the next batch (on a GPU the drive is otherwise idle while it encodes).
        let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<u8>>(ENCODE_QUEUE);
        let (writer, encoded) = std::thread::scope(|scope| -> Result<(VideoWriter, Duration)> {
            let encoder = scope.spawn(move || -> Result<(VideoWriter, Duration)> {
                let mut spent = Duration::ZERO;
                for frame in rx {
                    let t0 = Instant::now();
                    writer.push_rgb(&frame)?;
                    spent += t0.elapsed();
                }
                Ok((writer, spent))
            });
            let rendered = (|| -> Result<()> {
                let mut frames = Vec::with_capacity(jobs.len());
                for j in jobs {
                    let codes = self
                        .avatar
                        .codes(j.record, &format!("driver frame `{}`", j.name))?;
                    frames.push((codes, j.transform));
                }
                // The first error of the per-frame work (Ctrl-C, decorating) stops the stream
                // and is the result.
                let mut failed: Option<anyhow::Error> = None;
                let mut each = |k: usize, img: Vec<u8>| -> ControlFlow<()> {
                    let sent = crate::check_interrupt()
                        .and_then(|()| decorate(k, img))
                        .map(|frame| tx.send(frame).is_ok());
                    match sent {
                        Ok(true) => {
                            bar.inc(1);
                            ControlFlow::Continue(())
                        }
                        // A closed channel means the encoder stopped on an error, which its
                        // join below reports.
                        Ok(false) => ControlFlow::Break(()),
                        Err(e) => {
                            failed = Some(e);
                            ControlFlow::Break(())
                        }
                    }
                };
                let streamed = self.drive.render_stream(&frames, batch, &mut each);
                self.timings.drive = self.drive.times();
                streamed?;
                failed.map_or(Ok(()), Err)
            })();
            drop(tx);
            let encoded = encoder
                .join()
                .map_err(|_| anyhow::anyhow!("the video encoder thread panicked"))?;
            rendered?;
            encoded
        })?;
        // Finished (and so written) only once every frame was rendered and encoded.
        let t0 = Instant::now();
        writer.finish()?;
        self.timings.encode += encoded + t0.elapsed();
        bar.finish_and_clear();
        eprintln!(
            "wrote {} ({} frames, {width}x{size}, {fps} fps)",
            output.display(),
            jobs.len()
        );
        Ok(())
    }
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
