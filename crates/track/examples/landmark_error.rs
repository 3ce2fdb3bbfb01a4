//! Landmark accuracy and steadiness of the tracker on real images: MediaPipe's landmarks
//! (`gagavatar-face`), the fit (`track_photo` / `track_video`), and per frame the mean distance
//! between the fitted FLAME's 68 reprojected landmarks and the detected ones over the detected
//! outer-eye-corner distance (iBUG 36-45). For a video also the steadiness: the mean
//! frame-to-frame second difference of the 68 points, reprojected (default smoother) against
//! detected.
//!
//! Photos (each file on its own):
//!
//!     cargo run -p gagavatar-track --example landmark_error -- OUT.json PHOTO...
//!
//! A video, as frames in order (e.g. `ffmpeg -i obama.mp4 /tmp/obama/%05d.png`):
//!
//!     cargo run -p gagavatar-track --example landmark_error -- --video OUT.json /tmp/obama/*.png
//!
//! `--write DIR` also writes the release layout (`img_lmdb/`, `optim.pkl`, `smoothed.pkl`,
//! `track.json`; crops without a matte) per photo under `DIR/<name>/`, for a video under
//! `DIR/video/`, for `tools/reference/track_loader_check.py`.
//! `--smoothing none|release-ema|offline` picks the video smoother (default: offline).
//! `--flame FLAME.pt` fits the release's FLAME asset instead of the built-in synthetic one.
//! `OUT.json` holds every frame's detected and reprojected 70 points in frame pixels, for
//! `tools/reference/dlib_landmark_check.py`, which scores the same reprojections against dlib's
//! independent 68-point predictor.

use std::path::{Path, PathBuf};

use gagavatar_face::{FaceMesh, FaceTracker};
use gagavatar_flame::asset::{FlameAsset, LoadOptions};
use gagavatar_track::crop::crop_image;
use gagavatar_track::output::{sanitize_name, write_photo, write_video};
use gagavatar_track::pipeline::FrameTrack;
use gagavatar_track::smooth::Smoothing;
use gagavatar_track::{
    track_photo, track_video, FaceLandmarks, LandmarkRig, Observation, TrackOptions,
};
use serde_json::{json, Value};

type Error = Box<dyn std::error::Error>;

fn observation(
    img: &image::RgbImage,
    face: Option<&gagavatar_face::Face>,
) -> Result<Observation, Error> {
    let (w, h) = (img.width(), img.height());
    let lm = match face {
        Some(f) => {
            let pts: Vec<[f64; 2]> = f
                .landmarks
                .iter()
                .map(|p| [p[0] as f64, p[1] as f64])
                .collect();
            Some(FaceLandmarks::from_normalized(&pts, w, h)?)
        }
        None => None,
    };
    Ok(Observation::new(w, h, lm)?)
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

/// Mean distance of the 68 reprojected points to the detected ones over the detected outer eye
/// corners' distance.
fn normalized_error(f: &FrameTrack) -> Option<f64> {
    let det = f.detected.as_ref()?;
    let d: Vec<[f64; 2]> = det[..68]
        .iter()
        .map(|p| p.ok_or(()))
        .collect::<Result<_, _>>()
        .ok()?;
    let r: Vec<[f64; 2]> = f.reprojected[..68]
        .iter()
        .map(|p| p.ok_or(()))
        .collect::<Result<_, _>>()
        .ok()?;
    let iod = dist(d[36], d[45]);
    let mean = d.iter().zip(&r).map(|(a, b)| dist(*a, *b)).sum::<f64>() / 68.0;
    Some(mean / iod)
}

fn points(v: &[Option<[f64; 2]>]) -> Value {
    json!(v
        .iter()
        .map(|p| p.map(|p| [p[0], p[1]]))
        .collect::<Vec<_>>())
}

fn frame_json(path: &Path, f: &FrameTrack) -> Value {
    json!({
        "path": path.to_string_lossy(),
        "width": f.image_size[0],
        "height": f.image_size[1],
        "face_found": f.face_found,
        "window": f.window.as_array(),
        "detected": f.detected.as_ref().map(|d| points(d)),
        "reprojected": points(&f.reprojected),
        "normalized_error": normalized_error(f),
        "fit_rms_px": f.fit_rms_px,
    })
}

fn median(v: &[f64]) -> f64 {
    let mut w = v.to_vec();
    w.sort_by(f64::total_cmp);
    if w.is_empty() {
        return f64::NAN;
    }
    let n = w.len();
    if n % 2 == 1 {
        w[n / 2]
    } else {
        (w[n / 2 - 1] + w[n / 2]) / 2.0
    }
}

/// Mean over frames t (whose neighbours all have the points) and the 68 landmarks of
/// |p[t-1] - 2 p[t] + p[t+1]| in pixels.
fn second_difference(seq: &[Option<Vec<[f64; 2]>>]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for t in 1..seq.len().saturating_sub(1) {
        let (Some(a), Some(b), Some(c)) = (&seq[t - 1], &seq[t], &seq[t + 1]) else {
            continue;
        };
        for k in 0..68 {
            let d = [
                a[k][0] - 2.0 * b[k][0] + c[k][0],
                a[k][1] - 2.0 * b[k][1] + c[k][1],
            ];
            sum += (d[0] * d[0] + d[1] * d[1]).sqrt();
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

fn all68(v: &[Option<[f64; 2]>]) -> Option<Vec<[f64; 2]>> {
    v[..68].iter().copied().collect()
}

fn main() -> Result<(), Error> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let video = if let Some(i) = args.iter().position(|a| a == "--video") {
        args.remove(i);
        true
    } else {
        false
    };
    let flame = if let Some(i) = args.iter().position(|a| a == "--flame") {
        args.remove(i);
        if i >= args.len() {
            return Err("--flame needs a path".into());
        }
        Some(PathBuf::from(args.remove(i)))
    } else {
        None
    };
    let smoothing = if let Some(i) = args.iter().position(|a| a == "--smoothing") {
        args.remove(i);
        if i >= args.len() {
            return Err("--smoothing needs none, release-ema or offline".into());
        }
        match args.remove(i).as_str() {
            "none" => Smoothing::None,
            "release-ema" => Smoothing::ReleaseEma,
            "offline" => Smoothing::default(),
            other => {
                return Err(format!("--smoothing {other}: none, release-ema or offline").into())
            }
        }
    } else {
        Smoothing::default()
    };
    let write = if let Some(i) = args.iter().position(|a| a == "--write") {
        args.remove(i);
        if i >= args.len() {
            return Err("--write needs a folder".into());
        }
        Some(PathBuf::from(args.remove(i)))
    } else {
        None
    };
    if args.len() < 2 {
        return Err("usage: landmark_error [--video] [--smoothing S] [--write DIR] [--flame FLAME.pt] OUT.json IMAGE...".into());
    }
    let out = PathBuf::from(&args[0]);
    let inputs: Vec<PathBuf> = args[1..].iter().map(PathBuf::from).collect();
    let asset = match &flame {
        Some(p) => FlameAsset::load(p, &LoadOptions::default())?,
        None => gagavatar_flame::synthesize(0),
    };
    let rig = LandmarkRig::for_tracking(&asset)?;
    let opts = TrackOptions {
        smoothing,
        ..TrackOptions::default()
    };
    let mut frames = Vec::new();
    let mut errors = Vec::new();
    let mut summary = json!({});
    if video {
        let mut tracker = FaceTracker::new()?;
        let mut obs = Vec::new();
        for p in &inputs {
            let img = image::open(p)?.into_rgb8();
            let face = tracker.process(&img)?;
            obs.push(observation(&img, face.as_ref())?);
        }
        let t = track_video(obs, &rig, &opts, "video", |_, _| {})?;
        if let Some(dir) = &write {
            let crops = inputs.iter().zip(&t.frames).map(|(p, f)| {
                let img = image::open(p)
                    .map_err(|e| gagavatar_track::TrackError::Output {
                        path: p.clone(),
                        reason: e.to_string(),
                    })?
                    .into_rgb8();
                crop_image(&img, &f.window)
            });
            write_video(&dir.join("video"), "video", &t, crops)?;
        }
        let det: Vec<_> = t
            .frames
            .iter()
            .map(|f| f.detected.as_deref().and_then(all68))
            .collect();
        let rep: Vec<_> = t
            .frames
            .iter()
            .zip(&det)
            .map(|(f, d)| d.as_ref().and(all68(&f.reprojected)))
            .collect();
        let (sd_det, sd_rep) = (second_difference(&det), second_difference(&rep));
        println!(
            "steadiness over {} frames: mean second difference of the 68 points: detected {sd_det:.3} px, reprojected {sd_rep:.3} px",
            t.frames.len()
        );
        summary["second_difference_detected_px"] = json!(sd_det);
        summary["second_difference_reprojected_px"] = json!(sd_rep);
        for (p, f) in inputs.iter().zip(&t.frames) {
            errors.extend(normalized_error(f));
            frames.push(frame_json(p, f));
        }
    } else {
        let mesh = FaceMesh::new()?;
        for p in &inputs {
            let img = image::open(p)?.into_rgb8();
            let faces = mesh.process(&img, 1)?;
            let obs = observation(&img, faces.first())?;
            match track_photo(&obs, &rig, &opts, &p.to_string_lossy()) {
                Ok(t) => {
                    if let Some(dir) = &write {
                        let stem = p.file_stem().unwrap_or_default().to_string_lossy();
                        let name = sanitize_name(&stem);
                        let crop = crop_image(&img, &t.frame.window)?;
                        write_photo(&dir.join(&name), &name, &t, &crop)?;
                    }
                    let e = normalized_error(&t.frame);
                    println!(
                        "{}: normalized error {}",
                        p.display(),
                        e.map_or("-".into(), |e| format!("{e:.4}"))
                    );
                    errors.extend(e);
                    frames.push(frame_json(p, &t.frame));
                }
                Err(e) => {
                    println!("{}: {e}", p.display());
                    frames.push(json!({"path": p.to_string_lossy(), "face_found": false}));
                }
            }
        }
    }
    let med = median(&errors);
    let mx = errors.iter().cloned().fold(f64::NAN, f64::max);
    println!(
        "{} frames with a face of {}: normalized error (68 reprojected vs detected, over the outer-eye-corner distance) median {med:.4} max {mx:.4}",
        errors.len(),
        inputs.len()
    );
    summary["normalized_error_median"] = json!(med);
    summary["normalized_error_max"] = json!(mx);
    summary["frames_with_face"] = json!(errors.len());
    let doc =
        json!({"mode": if video {"video"} else {"photo"}, "summary": summary, "frames": frames});
    std::fs::write(&out, serde_json::to_string(&doc)?)?;
    println!("-> {}", out.display());
    Ok(())
}
