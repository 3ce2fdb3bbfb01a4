//! Test clips made with ffmpeg at test time (no binary files in the repository), and ffmpeg's
//! own answers to compare with: `ffprobe -show_frames` timestamps and a PNG decode.
//!
//! Without ffmpeg, or without an encoder a test needs, the test skips with a printed reason,
//! unless `GAGAVATAR_REQUIRE_FFMPEG` is set (`.ci/run` sets it), which turns the skip into a
//! failure.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use image::RgbImage;

/// True when ffmpeg and ffprobe are on PATH; otherwise prints why `test` is skipped (or fails
/// it when the run requires ffmpeg).
pub fn ffmpeg_or_skip(test: &str) -> bool {
    gagavatar_testkit::optional_path(
        test,
        gagavatar_video::read::find_ffmpeg(None).is_some(),
        "ffmpeg/ffprobe are not on PATH (apt-get install ffmpeg)",
        gagavatar_testkit::REQUIRE_FFMPEG,
    )
}

pub fn ffmpeg_version() -> (u32, u32) {
    gagavatar_video::read::find_ffmpeg(None)
        .map(|t| t.version)
        .unwrap_or((0, 0))
}

/// Whether this ffmpeg build has the encoder `name` (libx265, libsvtav1, ...).
pub fn has_encoder(name: &str) -> bool {
    static LIST: OnceLock<String> = OnceLock::new();
    let list = LIST.get_or_init(|| {
        Command::new("ffmpeg")
            .args(["-hide_banner", "-encoders"])
            .output()
            .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
            .unwrap_or_default()
    });
    list.lines()
        .any(|l| l.split_whitespace().nth(1) == Some(name))
}

/// Whether this ffmpeg can encode with `name`; prints why `test` is skipped when not, or fails
/// it when the run requires ffmpeg (a required ffmpeg must have every encoder the tests use).
pub fn encoder_or_skip(test: &str, name: &str) -> bool {
    gagavatar_testkit::optional_path(
        test,
        has_encoder(name),
        &format!("this ffmpeg build has no {name} encoder"),
        gagavatar_testkit::REQUIRE_FFMPEG,
    )
}

/// ffmpeg with every one of `encoders`, or a printed reason to skip `test`.
pub fn ffmpeg_with(test: &str, encoders: &[&str]) -> bool {
    ffmpeg_or_skip(test) && encoders.iter().all(|e| encoder_or_skip(test, e))
}

/// The first of `names` this ffmpeg can encode with; `None` (with a printed reason) when it has
/// none of them, or a failure when the run requires ffmpeg.
pub fn first_encoder<'a>(test: &str, names: &[&'a str]) -> Option<&'a str> {
    let found = names.iter().copied().find(|n| has_encoder(n));
    gagavatar_testkit::optional_path(
        test,
        found.is_some(),
        &format!("this ffmpeg build has none of the encoders {names:?}"),
        gagavatar_testkit::REQUIRE_FFMPEG,
    );
    found
}

/// Frame timing passed through untouched (the option's name changed in ffmpeg 5.1).
pub fn passthrough() -> [&'static str; 2] {
    if ffmpeg_version() >= (5, 1) {
        ["-fps_mode", "passthrough"]
    } else {
        ["-vsync", "passthrough"]
    }
}

/// Runs `ffmpeg -y <args>`, failing the test with ffmpeg's message if it fails.
pub fn ffmpeg(args: &[&str]) {
    let out = Command::new("ffmpeg")
        .args(["-hide_banner", "-nostdin", "-loglevel", "error", "-y"])
        .args(args)
        .output()
        .expect("running ffmpeg");
    assert!(
        out.status.success(),
        "ffmpeg {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A moving test pattern as ffmpeg input arguments.
pub fn testsrc(w: u32, h: u32, rate: &str, frames: usize) -> Vec<String> {
    vec![
        "-f".into(),
        "lavfi".into(),
        "-i".into(),
        format!("testsrc2=size={w}x{h}:rate={rate}"),
        "-frames:v".into(),
        frames.to_string(),
    ]
}

/// Encodes a test pattern into `out` with the extra output arguments.
pub fn make_clip(out: &Path, input: &[String], extra: &[&str]) -> PathBuf {
    let mut args: Vec<&str> = input.iter().map(String::as_str).collect();
    args.extend_from_slice(extra);
    let out_s = out.to_str().expect("utf-8 path");
    args.push(out_s);
    ffmpeg(&args);
    out.to_path_buf()
}

fn json(cmd: &mut Command) -> serde_json::Value {
    let out = cmd.output().expect("running ffprobe");
    assert!(
        out.status.success(),
        "ffprobe failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("ffprobe JSON")
}

/// Every decoded frame's `best_effort_timestamp_time` (what ffprobe calls the frame's time).
pub fn probe_frame_times(path: &Path) -> Vec<f64> {
    let v = json(
        Command::new("ffprobe")
            .args([
                "-v",
                "error",
                "-select_streams",
                "v:0",
                "-show_entries",
                "frame=best_effort_timestamp_time,pts_time",
                "-of",
                "json",
            ])
            .arg(path),
    );
    v["frames"]
        .as_array()
        .expect("frames")
        .iter()
        .map(|f| {
            let t = f["best_effort_timestamp_time"]
                .as_str()
                .or(f["pts_time"].as_str())
                .expect("frame time");
            t.parse().expect("a number")
        })
        .collect()
}

/// ffprobe's view of the first video stream.
pub fn probe_stream(path: &Path) -> serde_json::Value {
    let v = json(
        Command::new("ffprobe")
            .args([
                "-v",
                "error",
                "-select_streams",
                "v:0",
                "-show_streams",
                "-of",
                "json",
            ])
            .arg(path),
    );
    v["streams"][0].clone()
}

/// ffmpeg's own decode of every frame to PNG (its default pixel format: 8-bit RGB, or 16-bit
/// for deeper sources), read back as 8-bit RGB (16-bit values rounded to the nearest 8-bit).
pub fn reference_frames(path: &Path, dir: &Path) -> Vec<RgbImage> {
    std::fs::create_dir_all(dir).unwrap();
    let pattern = dir.join("%06d.png");
    let mut args = vec!["-i", path.to_str().unwrap(), "-map", "0:v:0"];
    args.extend(passthrough());
    args.push(pattern.to_str().unwrap());
    ffmpeg(&args);
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    files.sort();
    files
        .iter()
        .map(|f| match image::open(f).unwrap() {
            image::DynamicImage::ImageRgb16(img) => {
                let (w, h) = img.dimensions();
                let data = img
                    .as_raw()
                    .iter()
                    .map(|&v| ((v as f64) / 257.0).round() as u8)
                    .collect();
                RgbImage::from_raw(w, h, data).unwrap()
            }
            other => other.to_rgb8(),
        })
        .collect()
}

/// Mean absolute difference over all RGB samples, in 8-bit code values.
pub fn mean_abs_diff(a: &RgbImage, b: &RgbImage) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions(), "frame sizes differ");
    let sum: u64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| u64::from(x.abs_diff(y)))
        .sum();
    sum as f64 / a.as_raw().len() as f64
}
