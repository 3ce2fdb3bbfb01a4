//! The whole pipelines against MediaPipe 0.10.21's Python solutions on the same pictures
//! (goldens from `tools/reference/face_reference.py`): FaceDetection with both models,
//! FaceMesh with refined landmarks in static mode and in video (tracking) mode, and
//! SelfieSegmentation. Tolerances are the parity targets.

mod common;

use common::*;
use gagavatar_face::detection::{Detection, DetectorModel, FaceDetector};
use gagavatar_face::face_mesh::{FaceMesh, FaceTracker};
use gagavatar_face::matte::SelfieSegmenter;
use gagavatar_face::warp::{self, Border};
use serde_json::Value;

/// Boxes and keypoints: within 0.5% of the image size (normalised coordinates).
const BOX_TOL: f32 = 0.005;
/// Detection scores.
const SCORE_TOL: f32 = 1e-3;
/// Landmarks: mean distance within 0.25% of the face's size (the side of the landmarks'
/// bounding box in pixels), about half a pixel of the 192-px crop.
const LANDMARK_MEAN_TOL: f32 = 0.0025;
/// Matte: intersection over union of the 0.5 threshold at least this...
const MATTE_IOU_MIN: f32 = 0.99;
/// ...and mean absolute difference at most this (the golden is stored in 8 bits: 0.002).
const MATTE_MAD_TOL: f32 = 0.01;

fn pictures() -> Vec<(String, Value)> {
    let g = json("pipeline.json");
    g["pictures"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect()
}

/// Worst box/keypoint and score differences seen (for the printed summary).
static WORST: std::sync::Mutex<(f32, f32)> = std::sync::Mutex::new((0.0, 0.0));

fn check_detections(name: &str, got: &[Detection], want: &Value) {
    let want = want.as_array().unwrap();
    assert_eq!(
        got.len(),
        want.len(),
        "{name}: {} faces vs MediaPipe's {}",
        got.len(),
        want.len()
    );
    for (i, (d, w)) in got.iter().zip(want).enumerate() {
        let score = f(&w["score"]);
        assert!(
            (d.score - score).abs() < SCORE_TOL,
            "{name} face {i}: score {} vs {score}",
            d.score
        );
        let b = floats(&w["box"]);
        let mine = [d.xmin, d.ymin, d.width, d.height];
        let (k, e) = worst(&mine, &b);
        if let Ok(mut w) = WORST.lock() {
            w.0 = w.0.max(e);
            w.1 = w.1.max((d.score - score).abs());
        }
        assert!(
            e < BOX_TOL,
            "{name} face {i}: box value {k}: {} vs {}",
            mine[k],
            b[k]
        );
        for (j, kp) in w["keypoints"].as_array().unwrap().iter().enumerate() {
            let kp = floats(kp);
            let (k, e) = worst(&d.keypoints[j], &kp);
            if let Ok(mut w) = WORST.lock() {
                w.0 = w.0.max(e);
            }
            assert!(
                e < BOX_TOL,
                "{name} face {i} keypoint {j}[{k}]: {:?} vs {kp:?}",
                d.keypoints[j]
            );
        }
    }
}

#[test]
fn detections_match_mediapipe() {
    let short = FaceDetector::new(DetectorModel::ShortRange).unwrap();
    let full = FaceDetector::new(DetectorModel::FullRange).unwrap();
    for (name, p) in pictures() {
        let img = picture(&name);
        check_detections(
            &format!("{name} (short range)"),
            &short.detect(&img).unwrap(),
            &p["short_range"],
        );
        check_detections(
            &format!("{name} (full range)"),
            &full.detect(&img).unwrap(),
            &p["full_range"],
        );
    }
    if let Ok(w) = WORST.lock() {
        eprintln!(
            "worst box/keypoint difference {:.3e} (normalised), worst score difference {:.3e}",
            w.0, w.1
        );
    }
}

/// Mean landmark distance over the face size, and the face size in pixels.
fn landmark_error(got: &[[f32; 3]], want: &Value, w: u32, h: u32) -> (f32, f32) {
    let want: Vec<Vec<f32>> = want.as_array().unwrap().iter().map(floats).collect();
    assert_eq!(got.len(), want.len(), "landmark count");
    let (w, h) = (w as f32, h as f32);
    let (mut x0, mut x1, mut y0, mut y1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for p in &want {
        x0 = x0.min(p[0] * w);
        x1 = x1.max(p[0] * w);
        y0 = y0.min(p[1] * h);
        y1 = y1.max(p[1] * h);
    }
    let side = (x1 - x0).max(y1 - y0);
    let mut sum = 0.0;
    for (g, q) in got.iter().zip(&want) {
        sum += (((g[0] - q[0]) * w).powi(2) + ((g[1] - q[1]) * h).powi(2)).sqrt();
    }
    (sum / got.len() as f32 / side, side)
}

#[test]
fn static_landmarks_match_mediapipe() {
    let mesh = FaceMesh::new().unwrap();
    let max_faces = json("pipeline.json")["max_faces"].as_u64().unwrap() as usize;
    for (name, p) in pictures() {
        let img = picture(&name);
        let faces = mesh.process(&img, max_faces).unwrap();
        let want = p["mesh"].as_array().unwrap();
        assert_eq!(
            faces.len(),
            want.len(),
            "{name}: {} faces vs MediaPipe's {}",
            faces.len(),
            want.len()
        );
        for (i, (face, w)) in faces.iter().zip(want).enumerate() {
            let (e, side) = landmark_error(&face.landmarks, w, img.width(), img.height());
            eprintln!(
                "{name} face {i}: mean landmark error {:.5} of a {side:.0} px face",
                e
            );
            assert!(
                e < LANDMARK_MEAN_TOL,
                "{name} face {i}: mean landmark error {e} of the face size"
            );
        }
    }
}

#[test]
fn tracking_matches_mediapipe_video_mode() {
    let g = json("video.json");
    let img = picture(g["image"].as_str().unwrap());
    let (fw, fh) = (
        g["width"].as_u64().unwrap() as usize,
        g["height"].as_u64().unwrap() as usize,
    );
    let mut tracker = FaceTracker::new().unwrap();
    let mut tracked = 0;
    for (t, (r, want)) in g["rects"]
        .as_array()
        .unwrap()
        .iter()
        .zip(g["landmarks"].as_array().unwrap())
        .enumerate()
    {
        let roi = roi_pixels(r, img.width(), img.height());
        let frame = image::RgbImage::from_raw(
            fw as u32,
            fh as u32,
            warp::warp_u8(&img, &roi, fw, fh, Border::Zero),
        )
        .unwrap();
        let was_tracking = tracker.is_tracking();
        let face = tracker.process(&frame).unwrap();
        match (face, want.is_null()) {
            (None, true) => {}
            (Some(face), false) => {
                assert_eq!(face.detection.is_none(), was_tracking, "frame {t}");
                tracked += was_tracking as usize;
                let (e, side) = landmark_error(&face.landmarks, want, fw as u32, fh as u32);
                eprintln!("frame {t}: tracking {was_tracking}, mean landmark error {e:.5} of {side:.0} px");
                assert!(e < LANDMARK_MEAN_TOL, "frame {t}: mean landmark error {e}");
            }
            (got, _) => panic!(
                "frame {t}: face {} vs MediaPipe's {}",
                got.is_some(),
                !want.is_null()
            ),
        }
    }
    assert!(
        tracked >= 8,
        "only {tracked} frames reused the previous landmarks"
    );
}

#[test]
fn mattes_match_mediapipe() {
    let seg = SelfieSegmenter::new().unwrap();
    for (name, _) in pictures() {
        let img = picture(&name);
        let m = seg.matte(&img).unwrap();
        let want = image::open(golden_dir().join(format!("masks/{name}.png")))
            .unwrap()
            .into_luma8();
        assert_eq!((m.width, m.height), want.dimensions());
        let (mut inter, mut union, mut mad) = (0usize, 0usize, 0.0f64);
        for (a, b) in m.data.iter().zip(want.as_raw()) {
            let b = *b as f32 / 255.0;
            mad += (a - b).abs() as f64;
            let (pa, pb) = (*a >= 0.5, b >= 0.5);
            inter += (pa && pb) as usize;
            union += (pa || pb) as usize;
        }
        let mad = (mad / m.data.len() as f64) as f32;
        let iou = if union == 0 {
            1.0
        } else {
            inter as f32 / union as f32
        };
        eprintln!("{name}: matte IoU {iou:.5}, mean abs difference {mad:.5}");
        assert!(iou >= MATTE_IOU_MIN, "{name}: matte IoU {iou}");
        assert!(mad <= MATTE_MAD_TOL, "{name}: matte mean difference {mad}");
    }
}
