//! `gagavatar orbit`: novel views around the reconstructed head (the view control the release
//! left commented out) and `gagavatar export-ply`: the avatar as a 3DGS `.ply`.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use gagavatar_flame::TrackedFrame;
use gagavatar_video::VideoOptions;

use crate::animate::{read_source_record, record_transform, FrameJob, Session, SourceArgs};

#[derive(Debug, Args)]
#[command(
    after_help = "The camera starts at the source view and circles the head on a \
figure-eight: yaw = Y sin(2 pi t), pitch = P sin(4 pi t), rotating about the head's centre. \
The expression is the source's own unless --expression gives a record. The output format \
follows the extension: .mp4 (H.264), .gif, or anything else = a folder of PNGs.\n\n\
Example:\n  gagavatar orbit --ckpt GAGAvatar.pt --flame FLAME_with_eye.pt --source me.png \\\n    \
--source-record me.json --yaw 35 --pitch 12 --frames 90 -o orbit.mp4"
)]
pub struct OrbitArgs {
    #[command(flatten)]
    pub src: SourceArgs,
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Output: .mp4, .gif, or a folder of PNGs.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub expression: ExpressionArgs,
    /// Largest yaw, degrees.
    #[arg(long, default_value_t = 30.0)]
    pub yaw: f64,
    /// Largest pitch, degrees.
    #[arg(long, default_value_t = 10.0)]
    pub pitch: f64,
    /// Number of frames in the loop.
    #[arg(long, default_value_t = 60)]
    pub frames: usize,
    /// Frames per second of the output.
    #[arg(long, default_value_t = 25.0)]
    pub fps: f64,
    /// Frames rendered together (more uses more memory).
    #[arg(long, default_value_t = 1)]
    pub batch: usize,
    /// Do not draw the "AI-generated" watermark.
    #[arg(long)]
    pub no_watermark: bool,
}

use gagavatar_avatar::orbit::orbit_cameras;

/// The expression (with jaw and eyes) an orbit or export uses.
#[derive(Debug, Default, Args)]
pub struct ExpressionArgs {
    /// Expression, jaw and eyes from this record (JSON, or a `.pkl` with --expression-key);
    /// default: the source's own.
    #[arg(long)]
    pub expression: Option<PathBuf>,
    /// Frame name inside a `.pkl` expression record.
    #[arg(long)]
    pub expression_key: Option<String>,
}

impl ExpressionArgs {
    fn record(&self, source: &TrackedFrame) -> Result<TrackedFrame> {
        match &self.expression {
            Some(p) => read_source_record(p, self.expression_key.as_deref()),
            None => Ok(source.clone()),
        }
    }
}

pub fn run_orbit(a: OrbitArgs) -> Result<()> {
    let start_time = Instant::now();
    if a.frames == 0 || a.batch == 0 {
        bail!("--frames and --batch must be at least 1");
    }
    if !a.yaw.is_finite() || !a.pitch.is_finite() || a.yaw.abs() > 90.0 || a.pitch.abs() > 90.0 {
        bail!("--yaw and --pitch must be finite angles within +-90 degrees");
    }
    let mut session = Session::open(&a.src, &a.device, "reconstructing and rendering")?;
    let expr = a.expression.record(session.source())?;
    let base = record_transform(session.source(), "the source record")?;
    let transforms = orbit_cameras(&base, a.yaw, a.pitch, a.frames);
    let jobs: Vec<FrameJob> = transforms
        .into_iter()
        .enumerate()
        .map(|(k, transform)| FrameJob {
            record: &expr,
            name: format!("orbit view {k}"),
            transform,
        })
        .collect();
    let opts = VideoOptions {
        fps: a.fps,
        watermark: !a.no_watermark,
    };
    let size = session.image_size();
    session.render_video(&a.output, size, opts, &jobs, a.batch, "orbit", |_, img| {
        Ok(img)
    })?;
    eprintln!("{}", session.timings.report(start_time.elapsed()));
    Ok(())
}

#[derive(Debug, Args)]
#[command(
    after_help = "Writes every Gaussian of the avatar (FLAME-vertex Gaussians posed with \
the chosen expression, then both lifted planes) as a binary little-endian 3DGS .ply: x, y, z, \
f_dc_0..2 (from the RGB channels), opacity (logit), scale_0..2 (log), rot_0..3 (unit \
quaternion), plus the raw feature channels feat_0..feat_31. The release's unnormalised \
quaternions are converted to an exactly equivalent unit quaternion and scales, so viewers that \
normalise quaternions show the same covariances. `gagavatar splat --scene a.ply` reads it back.\n\n\
Example:\n  gagavatar export-ply --ckpt GAGAvatar.pt --flame FLAME_with_eye.pt --source me.png \\\n    \
--source-record me.json -o me.ply"
)]
pub struct ExportPlyArgs {
    #[command(flatten)]
    pub src: SourceArgs,
    /// Output .ply.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub expression: ExpressionArgs,
    /// Where the network runs: auto (a GPU if one is found, else the CPU), cpu or gpu.
    #[arg(long, value_enum, default_value_t = crate::device_args::DeviceChoice::Auto)]
    pub device: crate::device_args::DeviceChoice,
}

pub fn run_export_ply(a: ExportPlyArgs) -> Result<()> {
    let device = crate::device_args::DeviceArgs {
        device: a.device,
        gpu_precision: crate::device_args::GpuPrecisionArg::F32,
    };
    let session = Session::open(&a.src, &device, "reconstructing")?;
    let expr = a.expression.record(session.source())?;
    let codes = session.avatar.codes(&expr, "the expression record")?;
    let scene = session.avatar.scene(&codes)?;
    let channels = scene.channels;
    scene
        .save_ply(&a.output)
        .with_context(|| format!("writing {}", a.output.display()))?;
    eprintln!(
        "wrote {} ({} Gaussians, {channels} feature channels)",
        a.output.display(),
        scene.len()
    );
    Ok(())
}
