//! Bad inputs give clear errors, never panics.

mod common;

use common::*;
use gagavatar_track::fit::{
    fit_frame, fit_sequence, fit_shared_shape, FitOptions, FrameState, LandmarkTargets,
};
use gagavatar_track::pipeline::{track_photo, track_video, TrackOptions};
use gagavatar_track::smooth::{smooth_states, Smoothing};
use gagavatar_track::{CameraPose, FaceLandmarks, Observation, TrackError};

fn msg<T: std::fmt::Debug>(r: Result<T, TrackError>) -> String {
    r.unwrap_err().to_string()
}

#[test]
fn landmarks_and_observations_are_validated() {
    let e = msg(FaceLandmarks::new(vec![[0.0; 2]; 100]));
    assert!(e.contains("100 points") && e.contains("478"), "{e}");
    let mut pts = vec![[1.0; 2]; 478];
    pts[200][1] = f64::NAN;
    let e = msg(FaceLandmarks::new(pts));
    assert!(e.contains("point 200 is not finite"), "{e}");
    let mut pts = vec![[1.0; 2]; 468];
    pts[3][0] = f64::INFINITY;
    assert!(FaceLandmarks::new(pts).is_err());
    assert!(FaceLandmarks::new(vec![[1.0; 2]; 468]).is_ok());
    let e = msg(Observation::new(0, 10, None));
    assert!(e.contains("0x10"), "{e}");
}

#[test]
fn no_face_is_named() {
    let rig = rig();
    let e = msg(track_photo(
        &Observation::no_face(64, 64).unwrap(),
        &rig,
        &TrackOptions::default(),
        "cat.jpg",
    ));
    assert_eq!(e, "no face found in cat.jpg");
    let obs = vec![Observation::no_face(64, 64).unwrap(); 3];
    let e = msg(track_video(
        obs,
        &rig,
        &TrackOptions::default(),
        "cat.mp4",
        |_, _| {},
    ));
    assert_eq!(e, "no face found in cat.mp4");
}

#[test]
fn video_inputs_are_validated() {
    let rig = rig();
    let o = TrackOptions::default();
    let e = msg(track_video(Vec::new(), &rig, &o, "v", |_, _| {}));
    assert!(e.contains("no frames"), "{e}");
    let (shape, st) = truth(&rig, 0, 1);
    let good = observation(&exact_points(&rig, &shape, &st), 512, 512);
    let other = Observation::no_face(640, 480).unwrap();
    let e = msg(track_video(vec![good, other], &rig, &o, "v", |_, _| {}));
    assert!(e.contains("frame 1 is 640x480"), "{e}");
    let bad = TrackOptions {
        window_smoothing: f64::NAN,
        ..TrackOptions::default()
    };
    assert!(track_video(Vec::new(), &rig, &bad, "v", |_, _| {}).is_err());
    let e = msg(fit_sequence(&rig, &[], &FitOptions::default(), |_| {}));
    assert!(e.contains("no frames"), "{e}");
}

#[test]
fn targets_and_options_are_validated() {
    let rig = rig();
    let (shape, st) = truth(&rig, 0, 1);
    let pts = exact_points(&rig, &shape, &st);
    let mut w = [1.0; 70];
    w[4] = -1.0;
    assert!(msg(LandmarkTargets::new(pts, w)).contains("weight 4"));
    let mut p = pts;
    p[9][0] = f64::NAN;
    assert!(msg(LandmarkTargets::new(p, [1.0; 70])).contains("point 9"));
    // A NaN point with weight 0 is simply not used.
    let mut w0 = [1.0; 70];
    w0[9] = 0.0;
    assert!(LandmarkTargets::new(p, w0).is_ok());
    let mut few = [0.0; 70];
    few[..5].fill(1.0);
    assert!(msg(LandmarkTargets::new(pts, few)).contains("at least 6"));

    let t = LandmarkTargets::new(pts, [1.0; 70]).unwrap();
    for o in [
        FitOptions {
            shape_prior: -1.0,
            ..FitOptions::default()
        },
        FitOptions {
            expression_prior: f64::NAN,
            ..FitOptions::default()
        },
        FitOptions {
            jaw_opening_range: (0.5, 0.1),
            ..FitOptions::default()
        },
        FitOptions {
            huber_px: Some(0.0),
            ..FitOptions::default()
        },
        FitOptions {
            frame_iterations: 0,
            ..FitOptions::default()
        },
    ] {
        assert!(fit_frame(&rig, &shape, &t, None, &o).is_err(), "{o:?}");
    }
    let o = FitOptions::default();
    assert!(msg(fit_frame(&rig, &shape[..10], &t, None, &o)).contains("10 values"));
    let mut nan_shape = shape.clone();
    nan_shape[0] = f64::NAN;
    assert!(fit_frame(&rig, &nan_shape, &t, None, &o).is_err());
    let s0 = FrameState::neutral(&rig, CameraPose::frontal(9.0));
    let mut bad = s0.clone();
    bad.jaw[1] = f64::NAN;
    assert!(msg(fit_frame(&rig, &shape, &t, Some(&bad), &o)).contains("start state"));
    bad = s0.clone();
    bad.expression.pop();
    assert!(fit_shared_shape(&rig, &[&t], &shape, &[bad], &o).is_err());
    assert!(fit_shared_shape(&rig, &[&t], &shape, &[s0.clone(), s0.clone()], &o).is_err());
    assert!(fit_shared_shape(&rig, &[], &shape, &[], &o).is_err());
    assert!(smooth_states(&[s0], &[true, false], &Smoothing::default()).is_err());
}

/// Targets far from any face (all on one point) fail cleanly rather than panic.
#[test]
fn degenerate_targets_fail_cleanly() {
    let rig = rig();
    let t = LandmarkTargets::new([[100.0, 100.0]; 70], [1.0; 70]).unwrap();
    let r = fit_frame(
        &rig,
        &vec![0.0; rig.n_shape],
        &t,
        None,
        &FitOptions::default(),
    );
    assert!(matches!(r, Err(TrackError::Numerical { .. })), "{r:?}");
}
