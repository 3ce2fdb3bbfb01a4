//! The networks and the input sampling against MediaPipe 0.10.21 itself (goldens from
//! `tools/reference/face_reference.py`: MediaPipe's own crops and model outputs).

mod common;

use common::*;
use gagavatar_face::detection::{DetectorModel, FaceDetector};
use gagavatar_face::warp::{self, Border};

/// Crops reproduce OpenCV's fixed-point sampling and its matrix arithmetic: bit-exact.
const CROP_TOL: i32 = 0;
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
        let (w, h) = (
            c["width"].as_u64().unwrap() as usize,
            c["height"].as_u64().unwrap() as usize,
        );
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
    assert!(
        d < LOGIT_TOL,
        "{key}: anchor {i}: logit {} vs {}",
        raw.logits[i],
        want[i]
    );
    for (a, r) in m["best_anchors"]
        .as_array()
        .unwrap()
        .iter()
        .zip(m["best_regressors"].as_array().unwrap())
    {
        let a = a.as_u64().unwrap() as usize;
        let want = floats(r);
        let got = &raw.regressors[a * 16..(a + 1) * 16];
        let (i, d) = worst(got, &want);
        assert!(
            d < REGRESSOR_TOL,
            "{key}: anchor {a} value {i}: {} vs {}",
            got[i],
            want[i]
        );
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

/// Landmark outputs are in 192-px crop units.
const LANDMARK_TOL: f32 = 2e-3;
/// The face flag logit.
const FLAG_TOL: f32 = 1e-3;

#[test]
fn attention_mesh_matches_mediapipe() {
    use gagavatar_face::mesh_net::AttentionMeshNet;
    use gagavatar_face::weights::{bundled, WeightsFile};
    let g = json("models.json");
    let m = &g["models"]["landmarks"];
    let img = picture(m["image"].as_str().unwrap());
    let roi = roi_pixels(&m["roi"], img.width(), img.height());
    let crop = warp::warp_u8(&img, &roi, 192, 192, Border::Replicate);
    let x = warp::to_tensor(&crop, 192, 192, 0.0, 1.0);
    let file = WeightsFile::from_bytes(bundled::FACE_LANDMARK_WITH_ATTENTION, "attention").unwrap();
    let net = file
        .build("face_landmark_with_attention", AttentionMeshNet::new)
        .unwrap();
    let out = net.forward(&x);
    let o = &m["outputs"];
    for (name, got) in [
        ("mesh", &out.mesh),
        ("lips", &out.lips),
        ("left_eye", &out.left_eye),
        ("right_eye", &out.right_eye),
        ("left_iris", &out.left_iris),
        ("right_iris", &out.right_iris),
    ] {
        let want = floats(&o[name]);
        let (i, d) = worst(got, &want);
        eprintln!("{name}: worst difference {d} at {i}");
        assert!(d < LANDMARK_TOL, "{name}[{i}]: {} vs {}", got[i], want[i]);
    }
    let flag = floats(&o["face_flag"])[0];
    assert!(
        (out.face_flag - flag).abs() < FLAG_TOL,
        "face flag {} vs {flag}",
        out.face_flag
    );
}

/// Person probabilities in [0, 1].
const MASK_TOL: f32 = 1e-4;

#[test]
fn selfie_segmentation_matches_mediapipe() {
    use gagavatar_face::selfie_net::SelfieNet;
    use gagavatar_face::warp::RotatedRect;
    use gagavatar_face::weights::{bundled, WeightsFile};
    let g = json("models.json");
    let m = &g["models"]["selfie"];
    let img = picture(m["image"].as_str().unwrap());
    let (w, h) = (img.width() as f32, img.height() as f32);
    let roi = RotatedRect {
        cx: 0.5 * w,
        cy: 0.5 * h,
        w,
        h,
        rotation: 0.0,
    };
    let crop = warp::warp_u8(&img, &roi, 256, 256, Border::Zero);
    let x = warp::to_tensor(&crop, 256, 256, 0.0, 1.0);
    let file = WeightsFile::from_bytes(bundled::SELFIE_SEGMENTATION, "selfie").unwrap();
    let net = file.build("selfie_segmentation", SelfieNet::new).unwrap();
    let out = net.forward(&x);
    let stride = m["stride"].as_u64().unwrap() as usize;
    let got: Vec<f32> = (0..256 / stride)
        .flat_map(|y| (0..256 / stride).map(move |x| (y, x)))
        .map(|(y, x)| out.data[y * stride * 256 + x * stride])
        .collect();
    let want = floats(&m["mask"]);
    let (i, d) = worst(&got, &want);
    eprintln!("selfie: worst difference {d} at {i}");
    assert!(d < MASK_TOL, "mask sample {i}: {} vs {}", got[i], want[i]);
}
