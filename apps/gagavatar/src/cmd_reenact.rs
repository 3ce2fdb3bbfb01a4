//! `gagavatar reenact`: one photo + a driving sequence -> a video.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use gagavatar_data::DriverSequence;
use gagavatar_video::read::{ReadOptions, Start, VideoReader};
use gagavatar_video::VideoOptions;

use crate::animate::{record_transform, side_by_side, FrameJob, Session, SourceArgs};

#[derive(Debug, Args)]
#[command(
    after_help = "The avatar is reconstructed once from the source; every driver frame \
uses the source's shape code with the driver's expression, jaw, eye pose and camera.\n\n\
The driver is a release tracked folder (smoothed.pkl or optim.pkl, optional img_lmdb/ with the \
driver frames) or a JSON file {\"fps\": 25, \"frames\": [record, ...]}. The output format \
follows the extension: .mp4 (H.264), .gif, or anything else = a folder of PNGs.\n\n\
Example:\n  gagavatar reenact --ckpt GAGAvatar.pt --flame FLAME_with_eye.pt --source me.png \\\n    \
--source-record me.json --driver tracked/video1 --side-by-side -o out.mp4\n  \
gagavatar reenact ... --driver tracked/video1 --driver-video video1.mp4 -o out.mp4"
)]
pub struct ReenactArgs {
    #[command(flatten)]
    pub src: SourceArgs,
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Driving sequence: a release tracked folder or a JSON sequence.
    #[arg(long)]
    pub driver: PathBuf,
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

pub fn run(a: ReenactArgs) -> Result<()> {
    let start_time = Instant::now();
    if a.batch == 0 {
        bail!("--batch must be at least 1");
    }
    // The data crate's errors already name the file, frame and field.
    let driver = DriverSequence::open(&a.driver)?;
    let total = driver.frames.len();
    if a.start >= total {
        bail!(
            "--start {} is past the end of the driver ({} frames in {})",
            a.start,
            total,
            a.driver.display()
        );
    }
    let end = a.max_frames.map_or(total, |m| (a.start + m).min(total));
    if end == a.start {
        bail!("--max-frames 0 leaves nothing to render");
    }
    let show_driver = a.side_by_side || a.driver_video.is_some();
    if show_driver && a.driver_video.is_none() && !driver.has_images() {
        bail!(
            "--side-by-side needs driver images, and {} has none (give the video with \
             --driver-video)",
            a.driver.display()
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
            &format!("driver frame `{}` in {}", f.name, a.driver.display()),
        )?);
    }
    let fps = a.fps.unwrap_or(driver.fps);
    let mut session = Session::open(&a.src)?;
    session.use_device(&a.device)?;
    let size = session.image_size();
    let width = if show_driver { 2 * size } else { size };
    let jobs: Vec<FrameJob> = driver.frames[a.start..end]
        .iter()
        .zip(transforms)
        .map(|(f, transform)| FrameJob {
            record: &f.record,
            name: format!("{} of {}", f.name, a.driver.display()),
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
