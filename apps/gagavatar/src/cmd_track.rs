//! `gagavatar track`: a photo, a video or a folder of images -> a tracked folder (FLAME +
//! camera per frame, the release layout) and optionally a picture of the fit.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Result};
use clap::Args;

use crate::cmd_model::SYNTHETIC_FLAME;
use crate::tracking::{input_kind, report_video, tracker_for, Bars, InputKind};

#[derive(Debug, Args)]
#[command(
    after_help = "Writes DIR in the layout of the release's tracker, which reenact, orbit, \
export-ply and the release's own Python code read: img_lmdb/ (<name>_<i> -> the 512 crop, matted \
onto black, JPEG), optim.pkl (per frame shapecode, expcode, posecode, eyecode, transform_matrix, \
bbox; float32), for a video smoothed.pkl (the smoothed records), and track.json (per frame the \
record, the crop window [x0, y0, x1, y1] in the input's pixels, the detected landmarks and the \
fitted FLAME's 70 landmarks reprojected, both in the input's pixels). A video has one shape code; \
frames without a face are filled from their neighbours and flagged in track.json.\n\n\
The overlay draws, over the original input, the fitted FLAME mesh (cyan), the detected landmarks \
(green), the fitted FLAME's landmarks (magenta) joined to them by white lines, and the crop \
window (yellow): a PNG for a photo, a video (.mp4, .gif or a folder of PNGs) for a video.\n\n\
Records are meant for a model that uses the same FLAME: track with the release's \
FLAME_with_eye.pt for the release model (the default, `synthetic`, is the built-in asset of the \
demo model and of synth-data).\n\n\
Examples:\n  gagavatar track me.jpg -o tracked/me --flame FLAME_with_eye.pt --overlay me_fit.png\n  \
gagavatar track video.mp4 -o tracked/video --flame FLAME_with_eye.pt --overlay video_fit.mp4\n  \
gagavatar track frames/ -o tracked/frames"
)]
pub struct TrackArgs {
    /// A photo (PNG, JPEG, WebP, BMP), a video (anything ffmpeg reads; H.264 mp4 without it) or
    /// a folder of images (one video, frames in name order).
    pub input: PathBuf,
    /// Output folder (replaced if it holds a previous tracking and nothing else).
    #[arg(short, long)]
    pub output: PathBuf,
    /// FLAME asset (`FLAME_with_eye.pt`, or safetensors with the same keys); `synthetic` for the
    /// built-in synthetic asset.
    #[arg(long, default_value = SYNTHETIC_FLAME)]
    pub flame: PathBuf,
    /// Also draw the fit over the input: a .png for a photo; .mp4, .gif or a folder for a video.
    #[arg(long)]
    pub overlay: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
}

/// Sets the face networks' pool and rayon's global pool (crops, fits) to `n` threads.
pub fn set_threads(n: Option<usize>) {
    if let Some(n) = n.filter(|&n| n > 0) {
        gagavatar_face::pool::set_threads(n);
        // Fails only if the global pool was already built: then it keeps its size.
        let _ = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global();
    }
}

pub fn run(a: TrackArgs) -> Result<()> {
    let t0 = Instant::now();
    set_threads(a.threads);
    let kind = input_kind(&a.input)?;
    if let Some(o) = &a.overlay {
        let ext = o
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        match kind {
            InputKind::Photo if ext != "png" => {
                bail!("--overlay {}: a photo's overlay is a .png", o.display())
            }
            InputKind::Video if ext == "png" => bail!(
                "--overlay {}: a video's overlay is a video (.mp4, .gif or a folder)",
                o.display()
            ),
            _ => {}
        }
    }
    let tracker = tracker_for(&a.flame)?;
    match kind {
        InputKind::Photo => {
            let photo = tracker
                .track_photo_file(&a.input, &a.output, a.overlay.as_deref())?
                .photo;
            eprintln!(
                "{}: landmark RMS {:.2} px at 512, crop window {:?}",
                a.input.display(),
                photo.frame.fit_rms_px.unwrap_or(f64::NAN),
                photo.frame.window.as_array()
            );
        }
        InputKind::Video => {
            let s = tracker.track_video_file(
                &a.input,
                &a.output,
                a.overlay.as_deref(),
                &Bars::default(),
            )?;
            report_video(&a.input, &s);
        }
    }
    let elapsed = t0.elapsed().as_secs_f64();
    eprintln!("wrote {} in {elapsed:.1} s", a.output.display());
    if let Some(o) = &a.overlay {
        eprintln!("wrote {}", o.display());
    }
    Ok(())
}
