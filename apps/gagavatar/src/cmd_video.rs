//! `gagavatar video ...`: what the program sees in a video (metadata, frames), read the way
//! every other command reads it (`gagavatar_video::read`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use gagavatar_video::read::{DecoderChoice, ReadOptions, Start, VideoReader};
use gagavatar_video::FrameFolder;

use crate::animate::{progress, spinner};

#[derive(Debug, Subcommand)]
pub enum VideoCmd {
    /// Print a video's metadata as JSON (size after rotation, fps, frames, duration, codec,
    /// rotation, decoder).
    #[command(
        after_help = "FILE is a video (any format ffmpeg reads; H.264 Baseline mp4 \
without ffmpeg), a folder of images or an image.\n\n\
Example:\n  gagavatar video info clip.mov"
    )]
    Info(InfoArgs),
    /// Write a video's frames as frame_000000.png, frame_000001.png, ... (plus frames.json with
    /// their timestamps): exactly the frames every other command sees.
    #[command(
        after_help = "The folder appears complete or not at all; an existing empty \
folder is reused, a non-empty one refused.\n\n\
Examples:\n  gagavatar video frames clip.mp4 -o frames/\n  \
gagavatar video frames clip.mp4 -o frames/ --start 2.5s --max-frames 100 --fps 10"
    )]
    Frames(FramesArgs),
}

/// Where and how frames are read: shared by every command that reads a video.
#[derive(Debug, Args, Clone)]
pub struct ReadArgs {
    /// First frame: an index (120) or a time (4.5s, 1:02.5).
    #[arg(long, default_value = "0")]
    pub start: Start,
    /// Read at most this many frames.
    #[arg(long)]
    pub max_frames: Option<u64>,
    /// Video: resample to this rate by timestamps (each output time shows the last frame at or
    /// before it). Images: the rate they are shown at (default 25).
    #[arg(long)]
    pub fps: Option<f64>,
    /// ffmpeg decoder threads (default: ffmpeg's choice).
    #[arg(long)]
    pub threads: Option<usize>,
    /// auto (ffmpeg when on PATH, else the built-in H.264 Baseline decoder), ffmpeg or openh264.
    #[arg(long, default_value = "auto")]
    pub decoder: DecoderChoice,
}

impl ReadArgs {
    pub fn options(&self) -> ReadOptions {
        ReadOptions {
            start: self.start,
            max_frames: self.max_frames,
            fps: self.fps,
            threads: self.threads,
            decoder: self.decoder,
        }
    }
}

#[derive(Debug, Args)]
pub struct InfoArgs {
    /// A video file, a folder of images or an image.
    pub file: PathBuf,
    /// Frame rate for images (default 25).
    #[arg(long)]
    pub fps: Option<f64>,
    /// auto, ffmpeg or openh264.
    #[arg(long, default_value = "auto")]
    pub decoder: DecoderChoice,
}

#[derive(Debug, Args)]
pub struct FramesArgs {
    /// A video file, a folder of images or an image.
    pub file: PathBuf,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub read: ReadArgs,
}

pub fn run(cmd: VideoCmd) -> Result<()> {
    match cmd {
        VideoCmd::Info(a) => info(a),
        VideoCmd::Frames(a) => frames(a),
    }
}

fn info(a: InfoArgs) -> Result<()> {
    let opts = ReadOptions {
        fps: a.fps,
        decoder: a.decoder,
        ..ReadOptions::default()
    };
    // The library's errors name the file and say what is wrong.
    let meta = gagavatar_video::read::probe(&a.file, &opts, true)?;
    println!("{}", meta.to_json_string());
    Ok(())
}

fn frames(a: FramesArgs) -> Result<()> {
    let reader = VideoReader::open(&a.file, &a.read.options())?;
    let meta = reader.meta().clone();
    let mut out = FrameFolder::create(&a.output, meta.width, meta.height)
        .with_context(|| format!("creating {}", a.output.display()))?;
    let bar = match reader.expected_frames() {
        Some(n) => progress(n as usize, "frames"),
        None => spinner("frames"),
    };
    let mut index = Vec::new();
    for frame in reader {
        crate::check_interrupt()?;
        let frame = frame?;
        out.push(&frame.rgb)?;
        index.push(serde_json::json!({
            "file": FrameFolder::frame_name(frame.index as usize),
            "pts": frame.pts,
            "source_pts": frame.source_pts,
        }));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let n = out.frames();
    let listing = serde_json::json!({
        "source": a.file.display().to_string(),
        "meta": meta.to_json(),
        "start": a.read.start.to_string(),
        "fps": a.read.fps,
        "frames": index,
    });
    out.add_file(
        "frames.json",
        serde_json::to_string_pretty(&listing)?.as_bytes(),
    )?;
    out.finish()?;
    eprintln!(
        "wrote {} ({n} frames, {}x{}, decoded by {})",
        a.output.display(),
        meta.width,
        meta.height,
        meta.decoder.as_str()
    );
    Ok(())
}
