//! Photo and video tracking end to end on synthetic heads seen in a larger frame: observations
//! in frame pixels in, records and reprojected landmarks out.

mod common;

use common::*;
use gagavatar_synthdata::sample::{sample_shape, Rng, SampleConfig};
use gagavatar_track::camera::CameraPose;
use gagavatar_track::crop::CropWindow;
use gagavatar_track::fit::FrameState;
use gagavatar_track::pipeline::{track_photo, track_video, TrackOptions};
use gagavatar_track::rig::{LandmarkRig, N_LANDMARKS};
use gagavatar_track::smooth::Smoothing;
use gagavatar_track::Observation;

/// Where the synthetic "camera crop" sits in a 640x480 frame.
const TRUE_WINDOW: CropWindow = CropWindow {
    x0: 120,
    y0: 10,
    x1: 520,
    y1: 410,
};
const W: u32 = 640;
const H: u32 = 480;

/// A head turning and talking: smooth yaw, pitch, expression and jaw over `n` frames.
fn sequence(rig: &LandmarkRig, n: usize) -> (Vec<f64>, Vec<FrameState>) {
    let shape = sample_shape(&SampleConfig::default(), SEED, 7, rig.n_shape);
    let mut rng = Rng::stream(9, &[0]);
    let phases: Vec<(f64, f64)> = (0..10)
        .map(|_| (rng.range(0.1, 0.5), rng.range(0.0, std::f64::consts::TAU)))
        .collect();
    let states = (0..n)
        .map(|f| {
            let t = f as f64;
            let mut cam = CameraPose::frontal(9.2 + 0.2 * (t / 13.0).sin());
            let yaw = 0.35 * (t / 9.0).sin();
            let pitch = 0.12 * (t / 14.0).sin();
            cam.retract(&[pitch, yaw, 0.0], &[0.03 * (t / 11.0).sin(), 0.0, 0.0]);
            let mut expression = vec![0.0; rig.n_exp];
            for (k, &(w, ph)) in phases.iter().enumerate() {
                expression[k] = 0.4 * (w * t + ph).sin();
            }
            FrameState {
                expression,
                jaw: [0.12 * (1.0 + (t / 3.0).sin()), 0.0, 0.0],
                eyes: [
                    0.05 * (t / 7.0).sin(),
                    0.08 * (t / 5.0).cos(),
                    0.0,
                    0.05 * (t / 7.0).sin(),
                    0.08 * (t / 5.0).cos(),
                    0.0,
                ],
                camera: cam,
            }
        })
        .collect();
    (shape, states)
}

fn frame_points(rig: &LandmarkRig, shape: &[f64], s: &FrameState) -> [[f64; 2]; N_LANDMARKS] {
    exact_points(rig, shape, s).map(|p| TRUE_WINDOW.crop_to_frame(p))
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

#[test]
fn photo_is_tracked_in_frame_pixels() {
    let rig = rig();
    let (shape, st) = truth(&rig, 2, 1);
    let clean = frame_points(&rig, &shape, &st);
    let obs = observation(&clean, W, H);
    let t = track_photo(&obs, &rig, &TrackOptions::default(), "photo.png").unwrap();
    let f = &t.frame;
    assert!(f.face_found);
    assert_eq!(f.image_size, [W, H]);
    let worst = (0..N_LANDMARKS)
        .map(|k| dist(f.reprojected[k].unwrap(), clean[k]))
        .fold(0.0, gagavatar_testkit::max_or_nan);
    // 1 px at 512 is about 0.7 frame px here; the exact-landmark fit is within a crop pixel.
    assert!(worst <= 1.0, "reprojection {worst:.3} frame px");
    let det = f.detected.as_ref().unwrap();
    assert!(det.iter().zip(&clean).all(|(d, c)| d.unwrap() == *c));
    // The window holds the face, with room around it (the head box is larger than the face).
    let w = f.window;
    for p in &clean {
        assert!(
            p[0] > w.x0 as f64 && p[0] < w.x1 as f64 && p[1] > w.y0 as f64 && p[1] < w.y1 as f64
        );
    }
    let r = &f.record;
    // The release's 300 / 100 values; components beyond the rig's are zero.
    assert_eq!((r.shapecode.len(), r.expcode.len()), (300, 100));
    assert!(r.shapecode[rig.n_shape..].iter().all(|&v| v == 0.0));
    assert_eq!(&r.posecode[..3], &[0.0; 3]);
    assert!(r.bbox.unwrap().iter().all(|v| (0.0..=1.0).contains(v)));
    println!(
        "photo: reprojection max {worst:.3} frame px, fit rms {:.3} crop px",
        f.fit_rms_px.unwrap()
    );
}

#[test]
fn video_is_steady_and_fills_frames_without_a_face() {
    let rig = rig();
    let n = 40;
    let missing = [12usize, 13];
    let (shape, states) = sequence(&rig, n);
    let mut rng = Rng::stream(4, &[0]);
    let sigma = 1.0;
    let mut clean = vec![];
    let mut noisy = vec![];
    let obs: Vec<Observation> = states
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let c = frame_points(&rig, &shape, s);
            let p = c.map(|q| [q[0] + sigma * rng.normal(), q[1] + sigma * rng.normal()]);
            clean.push(c.to_vec());
            noisy.push(p.to_vec());
            if missing.contains(&i) {
                Observation::no_face(W, H).unwrap()
            } else {
                observation(&p, W, H)
            }
        })
        .collect();
    // Mean error bound per mode, in units of the noise: the two-sided smoother averages noise
    // away; no smoothing keeps what the fit keeps; the causal EMA lags a moving head.
    for (name, smoothing, err_bound) in [
        ("offline (default)", Smoothing::default(), 1.0),
        ("release EMA", Smoothing::ReleaseEma, 2.5),
        ("none", Smoothing::None, 1.5),
    ] {
        let opts = TrackOptions {
            smoothing,
            ..TrackOptions::default()
        };
        let mut calls = 0;
        let v = track_video(obs.clone(), &rig, &opts, "clip.mp4", |done, total| {
            calls += 1;
            assert!(done <= total && total == n);
        })
        .unwrap();
        assert_eq!(calls, n);
        assert_eq!((v.frames.len(), v.raw_records.len()), (n, n));
        for &i in &missing {
            let f = &v.frames[i];
            assert!(!f.face_found && f.detected.is_none() && f.fit_rms_px.is_none());
        }
        // Steadiness over the frames with a face (runs without a gap).
        let seg = |seq: &[Vec<[f64; 2]>]| -> f64 {
            let a = mean_second_difference(&seq[..missing[0]]);
            let b = mean_second_difference(&seq[missing[1] + 1..]);
            (a + b) / 2.0
        };
        let fitted: Vec<Vec<[f64; 2]>> = v
            .frames
            .iter()
            .map(|f| f.reprojected.iter().map(|p| p.unwrap()).collect())
            .collect();
        let (jit_fit, jit_det, jit_clean) = (seg(&fitted), seg(&noisy), seg(&clean));
        let err: Vec<f64> = (0..n)
            .flat_map(|i| (0..N_LANDMARKS).map(move |k| (i, k)))
            .map(|(i, k)| dist(fitted[i][k], clean[i][k]))
            .collect();
        let mut gap_err: f64 = 0.0;
        for &i in &missing {
            for k in 0..N_LANDMARKS {
                gap_err = gap_err.max(dist(fitted[i][k], clean[i][k]));
            }
        }
        let mean_err = err.iter().sum::<f64>() / err.len() as f64;
        println!(
            "video, {sigma} px noise, smoothing {name}: mean second difference fitted {jit_fit:.3} \
             px, detected {jit_det:.3} px (clean motion {jit_clean:.3}); mean error to the clean \
             landmarks {mean_err:.3} px; worst in the filled frames {gap_err:.3} px"
        );
        if name != "none" {
            assert!(
                jit_fit < jit_det,
                "{name}: fitted landmarks jitter {jit_fit:.3} px >= detected {jit_det:.3} px"
            );
        }
        assert!(
            mean_err < err_bound * sigma,
            "{name}: mean error {mean_err:.3} px"
        );
        assert!(
            gap_err < 6.0,
            "{name}: filled frames are {gap_err:.3} px off"
        );
    }
}

/// The records' fitted landmarks in frame pixels, through the record's own crop window.
fn live_fit_rms(
    rig: &LandmarkRig,
    rec: &gagavatar_flame::TrackedFrame,
    want: &[[f64; 2]; N_LANDMARKS],
    window: &CropWindow,
) -> f64 {
    let state = FrameState {
        expression: rec.expcode[..rig.n_exp].to_vec(),
        jaw: [rec.posecode[3], rec.posecode[4], rec.posecode[5]],
        eyes: std::array::from_fn(|k| rec.eyecode[k]),
        camera: CameraPose::from_matrix(&rec.transform_matrix.unwrap()),
    };
    let pts = exact_points(rig, &rec.shapecode[..rig.n_shape], &state);
    let d: f64 = pts
        .iter()
        .zip(want)
        .map(|(p, w)| dist(window.crop_to_frame(*p), *w).powi(2))
        .sum();
    (d / N_LANDMARKS as f64).sqrt()
}

#[test]
fn live_tracking_follows_a_head_frame_by_frame() {
    let rig = rig();
    let n = 12;
    let (shape, states) = sequence(&rig, n);
    let opts = TrackOptions::default();
    let mut live = gagavatar_track::LiveTrack::new();
    let mut first_shape = None;
    for (i, s) in states.iter().enumerate() {
        let pts = frame_points(&rig, &shape, s);
        let obs = if i == 5 {
            Observation::no_face(W, H).unwrap()
        } else {
            observation(&pts, W, H)
        };
        let rec = live.frame(&obs, &rig, &opts).unwrap();
        if i == 5 {
            assert!(rec.is_none(), "a frame without a face gave a record");
            continue;
        }
        let rec = rec.unwrap();
        // One shape for the whole stream, fixed by the first frame.
        let sc = rec.shapecode.clone();
        assert_eq!(
            first_shape.get_or_insert(sc.clone()),
            &sc,
            "frame {i}: the shape changed"
        );
        // The fit reproduces the frame's landmarks through the window its box came from.
        let b = rec.bbox.unwrap();
        assert!(b.iter().all(|v| v.is_finite()), "frame {i}: bbox {b:?}");
        let window = {
            // The record's box is the frame's head box in the crop's normalised coordinates:
            // recover the window from it and the frame's own head box.
            let head = opts
                .framing
                .head_box(obs.landmarks.as_ref().unwrap())
                .unwrap();
            let side = (head.x1 - head.x0) / (b[2] - b[0]);
            let x0 = head.x0 - b[0] * side;
            let y0 = head.y0 - b[1] * side;
            CropWindow {
                x0: x0.round() as i64,
                y0: y0.round() as i64,
                x1: (x0 + side).round() as i64,
                y1: (y0 + side).round() as i64,
            }
        };
        let rms = live_fit_rms(&rig, &rec, &pts, &window);
        assert!(
            rms < 3.0,
            "frame {i}: the live fit is {rms:.2} px RMS off its landmarks"
        );
    }
}
