//! `gagavatar reenact`: one photo + a driving sequence -> a video.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use gagavatar_data::DriverSequence;
use gagavatar_video::read::{ReadOptions, Start, VideoReader};
use gagavatar_video::VideoOptions;

use crate::animate::{
    record_transform, resolve_source, side_by_side, FrameJob, Session, SourceArgs,
};
use crate::tracking;

#[derive(Debug, Args)]
#[command(
    after_help = "The avatar is reconstructed once from the source; every driver frame \
uses the source's shape code with the driver's expression, jaw, eye pose and camera.\n\n\
Raw inputs are tracked first (gagavatar track) and the result is cached by content (SHA-256 of \
the input's bytes, the tracker version and the FLAME asset) in $GAGAVATAR_CACHE, else \
$XDG_CACHE_HOME/gagavatar, else ~/.cache/gagavatar; a second run with the same inputs uses the \
cache and says so. A source photo without a face fails with \"no face found in PATH\".\n\n\
The driver is a release tracked folder (smoothed.pkl or optim.pkl, optional img_lmdb/ with the \
driver frames), a JSON file {\"fps\": 25, \"frames\": [record, ...]}, or a raw video or folder \
of images. The output format follows the extension: .mp4 (H.264), .gif, or anything else = a \
folder of PNGs.\n\n\
Examples:\n  gagavatar reenact --ckpt GAGAvatar.pt --flame FLAME_with_eye.pt --source me.jpg \\\n    \
--driver video.mp4 --side-by-side -o out.mp4\n  \
gagavatar reenact ... --source me.jpg --driver-video video.mp4 -o out.mp4   (original frames on the left)\n  \
gagavatar reenact ... --source me.png --source-record me.json --driver tracked/video1 -o out.mp4"
)]
pub struct ReenactArgs {
    #[command(flatten)]
    pub src: SourceArgs,
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Driving sequence: a release tracked folder or a JSON sequence, or a raw video (any
    /// video file or a folder of images; tracked now, or found in the tracking cache). Default:
    /// the --driver-video, tracked.
    #[arg(long)]
    pub driver: Option<PathBuf>,
    /// Output: .mp4, .gif, or a folder of PNGs.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Put the driver frame left of the result (needs driver images, or --driver-video).
    #[arg(long)]
    pub side_by_side: bool,
    /// The driving video itself (any video, a folder of images or an image), shown left of the
    /// result instead of the tracked folder's images; implies --side-by-side. Its frame k (from
    /// --start) goes with driver frame k, so it must be read as the tracker read it.
    #[arg(long)]
    pub driver_video: Option<PathBuf>,
    /// Frames per second of the output (default: the driver's, else 25).
    #[arg(long)]
    pub fps: Option<f64>,
    /// First driver frame to render.
    #[arg(long, default_value_t = 0)]
    pub start: usize,
    /// Render at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Frames rendered together (more uses more memory).
    #[arg(long, default_value_t = 1)]
    pub batch: usize,
    /// Do not draw the "AI-generated" watermark.
    #[arg(long)]
    pub no_watermark: bool,
}

/// A tracked folder, a `.pkl` or a `.json`: records to drive with. Anything else (a video, a
/// folder of images, an image) is tracked first.
fn is_driving_sequence(path: &std::path::Path) -> bool {
    if path.is_dir() {
        return tracking::is_tracked_folder(path);
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    matches!(ext.as_str(), "json" | "pkl" | "pickle")
}

pub fn run(a: ReenactArgs) -> Result<()> {
    let start_time = Instant::now();
    if a.batch == 0 {
        bail!("--batch must be at least 1");
    }
    // The model and FLAME first (the tracker uses the FLAME the avatar is driven with), then the
    // source: a photo without a face fails before the driver is tracked.
    let t0 = Instant::now();
    let engine = a.src.open_engine()?;
    let load = t0.elapsed();
    let source = resolve_source(&a.src, &engine)?;
    let driver_path = match (&a.driver, &a.driver_video) {
        (Some(d), _) => d.clone(),
        (None, Some(v)) => v.clone(),
        (None, None) => bail!(
            "give --driver (a tracked folder, a JSON sequence, a video or a folder of images) \
             or --driver-video"
        ),
    };
    // The data crate's errors already name the file, frame and field.
    let driver = if is_driving_sequence(&driver_path) {
        DriverSequence::open(&driver_path)?
    } else {
        let tracked = tracking::tracked_inline(&engine, &driver_path, "driver", false)?;
        let mut d = DriverSequence::open(&tracked.dir)?;
        d.fps = tracked.fps;
        d
    };
    let driver_name = driver_path.display().to_string();
    let total = driver.frames.len();
    if a.start >= total {
        bail!(
            "--start {} is past the end of the driver ({} frames in {})",
            a.start,
            total,
            driver_name
        );
    }
    let end = a.max_frames.map_or(total, |m| (a.start + m).min(total));
    if end == a.start {
        bail!("--max-frames 0 leaves nothing to render");
    }
    let show_driver = a.side_by_side || a.driver_video.is_some();
    if show_driver && a.driver_video.is_none() && !driver.has_images() {
        bail!(
            "--side-by-side needs driver images, and {driver_name} has none (give the video \
             with --driver-video)"
        );
    }
    // Opened before the model loads, so a video that cannot be read fails in a second.
    let mut driver_video = match &a.driver_video {
        Some(path) => {
            let opts = ReadOptions {
                start: Start::Frame(a.start as u64),
                ..ReadOptions::default()
            };
            let reader = VideoReader::open(path, &opts)?;
            if let Some(n) = reader.expected_frames() {
                let needed = (end - a.start) as u64;
                if n < needed {
                    bail!(
                        "--driver-video {} has {n} frames from --start {}, the driver needs {needed}",
                        path.display(),
                        a.start
                    );
                }
            }
            Some(reader)
        }
        None => None,
    };
    // Check every frame's camera before the slow part, so a bad frame fails in a second.
    let mut transforms = Vec::with_capacity(end - a.start);
    for f in &driver.frames[a.start..end] {
        transforms.push(record_transform(
            &f.record,
            &format!("driver frame `{}` in {driver_name}", f.name),
        )?);
    }
    let fps = a.fps.unwrap_or(driver.fps);
    let mut session = Session::with_source(
        &engine,
        source,
        load,
        &a.device,
        "reconstructing and rendering",
    )?;
    let size = session.image_size();
    let width = if show_driver { 2 * size } else { size };
    let jobs: Vec<FrameJob> = driver.frames[a.start..end]
        .iter()
        .zip(transforms)
        .map(|(f, transform)| FrameJob {
            record: &f.record,
            name: format!("{} of {driver_name}", f.name),
            transform,
        })
        .collect();
    let opts = VideoOptions {
        fps,
        watermark: !a.no_watermark,
    };
    session.render_video(
        &a.output,
        width,
        opts,
        &jobs,
        a.batch,
        "reenact",
        |k, img| {
            if !show_driver {
                return Ok(img);
            }
            let i = a.start + k;
            let name = &driver.frames[i].name;
            let left = match (&mut driver_video, &a.driver_video) {
                (Some(reader), Some(path)) => {
                    let frame = reader.next().with_context(|| {
                        format!(
                            "--driver-video {} ends before driver frame `{name}`",
                            path.display()
                        )
                    })??;
                    frame.rgb
                }
                _ => driver
                    .image(i)
                    .with_context(|| format!("reading the image of driver frame `{name}`"))?
                    .with_context(|| format!("driver frame `{name}` has no image"))?,
            };
            Ok(side_by_side(&left, &img, size, size))
        },
    )?;
    eprintln!("{}", session.timings.report(start_time.elapsed()));
    Ok(())
}
