//! The networks and the input sampling against MediaPipe 0.10.21 itself (goldens from
//! `tools/reference/face_reference.py`: MediaPipe's own crops and model outputs).

mod common;

use common::*;
use gagavatar_face::detection::{DetectorModel, FaceDetector};
use gagavatar_face::warp::{self, Border};

/// Crops are OpenCV's 8-bit fixed-point sampling; a pixel may differ by one level where a
/// coordinate lands on a rounding tie (never seen in these cases).
const CROP_TOL: i32 = 1;
/// Detector logits: f32 networks of ~20 layers, XNNPACK's summation order against ours.
const LOGIT_TOL: f32 = 2e-3;
/// Detector regressors are in input pixels (0..192).
const REGRESSOR_TOL: f32 = 5e-3;

#[test]
fn crops_match_mediapipe() {
    let g = json("models.json");
    for c in g["crops"].as_array().unwrap() {
        let name = c["name"].as_str().unwrap();
        let img = picture(c["image"].as_str().unwrap());
        let roi = roi_pixels(&c["roi"], img.width(), img.height());
        let (w, h) = (c["width"].as_u64().unwrap() as usize, c["height"].as_u64().unwrap() as usize);
        let border = match c["border"].as_str().unwrap() {
            "zero" => Border::Zero,
            _ => Border::Replicate,
        };
        let got = warp::warp_u8(&img, &roi, w, h, border);
        let want = png(&format!("crops/{name}.png"));
        let mut bad = 0;
        let mut max = 0;
        for (i, (a, b)) in got.iter().zip(want.as_raw()).enumerate() {
            let d = (*a as i32 - *b as i32).abs();
            max = max.max(d);
            if d > 0 {
                bad += 1;
                if bad < 4 {
                    eprintln!("{name}: pixel {} channel {}: {a} vs {b}", i / 3, i % 3);
                }
            }
        }
        eprintln!("{name}: {bad} of {} values differ, max {max}", got.len());
        assert!(max <= CROP_TOL, "{name}: max difference {max}");
    }
}

fn check_detector(model: DetectorModel, key: &str) {
    let g = json("models.json");
    let m = &g["models"][key];
    let img = picture(m["image"].as_str().unwrap());
    let det = FaceDetector::new(model).unwrap();
    let n = det.input_size();
    let (x, _) = warp::letterbox(&img, n, -1.0, 1.0);
    let raw = det.raw(&x);
    let want = floats(&m["logits"]);
    let (i, d) = worst(&raw.logits, &want);
    eprintln!("{key}: worst logit difference {d} at anchor {i}");
    assert!(d < LOGIT_TOL, "{key}: anchor {i}: logit {} vs {}", raw.logits[i], want[i]);
    for (a, r) in m["best_anchors"].as_array().unwrap().iter().zip(m["best_regressors"].as_array().unwrap()) {
        let a = a.as_u64().unwrap() as usize;
        let want = floats(r);
        let got = &raw.regressors[a * 16..(a + 1) * 16];
        let (i, d) = worst(got, &want);
        assert!(d < REGRESSOR_TOL, "{key}: anchor {a} value {i}: {} vs {}", got[i], want[i]);
    }
}

#[test]
fn short_range_detector_matches_mediapipe() {
    check_detector(DetectorModel::ShortRange, "short_range");
}

#[test]
fn full_range_detector_matches_mediapipe() {
    check_detector(DetectorModel::FullRange, "full_range");
}
