//! Speed of the tracker's fit on the synthetic FLAME (release sizes: 5023 vertices, 100 shape
//! components fitted of 300, 100 expression), landmarks with 1 px noise:
//! `RAYON_NUM_THREADS=2 cargo bench -p gagavatar-track --bench fit [-- FILTER]`.
//!
//! - `photo`: one photo from scratch (closed-form start, rigid LM, joint shape + frame LM);
//! - `video_frame_warm`: one video frame with the shape known, warm-started from the previous
//!   frame (the per-frame cost of a video);
//! - `video_shape_8_keyframes`: the per-video shape solve (8 keyframes, from their fixed-shape
//!   starts);
//! - `track_video_100`: `track_video` on 100 frames of observations (windows, targets, shape,
//!   frame fits, filling, smoothing, reprojection): divide by 100 for the per-frame cost;
//! - `crop_1080p`: one 512 crop (antialiased resize of a ~700 px window of a 1920x1080 frame).

use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use gagavatar_flame::synthesize;
use gagavatar_synthdata::sample::{sample_frame, sample_shape, Rng, SampleConfig};
use gagavatar_track::camera::CameraPose;
use gagavatar_track::crop::{crop_image, CropWindow};
use gagavatar_track::fit::{
    fit_frame, fit_photo, fit_shared_shape, reproject, FitOptions, FrameState, LandmarkTargets,
};
use gagavatar_track::mapping::{MEDIAPIPE_IRIS_CENTRES, MEDIAPIPE_TO_IBUG68};
use gagavatar_track::pipeline::{track_video, TrackOptions};
use gagavatar_track::rig::LandmarkRig;
use gagavatar_track::{FaceLandmarks, Observation};

fn frame(rig: &LandmarkRig, t: f64) -> FrameState {
    let cfg = SampleConfig::default();
    let f = sample_frame(&cfg, 5, 0, 1, rig.n_exp);
    let mut cam = CameraPose::frontal(9.2);
    cam.retract(
        &[0.1 * (t / 7.0).sin(), 0.3 * (t / 11.0).sin(), 0.0],
        &[0.0; 3],
    );
    FrameState {
        expression: f
            .expression
            .iter()
            .map(|e| e * (1.0 + 0.3 * (t / 3.0).sin()))
            .collect(),
        jaw: [0.1 + 0.05 * (t / 2.0).sin(), 0.0, 0.0],
        eyes: f.eye,
        camera: cam,
    }
}

fn targets(rig: &LandmarkRig, shape: &[f64], s: &FrameState, rng: &mut Rng) -> LandmarkTargets {
    let px = reproject(rig, shape, s).unwrap();
    let pts: [[f64; 2]; 70] = std::array::from_fn(|k| {
        let p = px[k].unwrap();
        [p[0] + rng.normal(), p[1] + rng.normal()]
    });
    LandmarkTargets::with_weights(pts, &FitOptions::default().landmark_weights).unwrap()
}

fn observation(t: &LandmarkTargets) -> Observation {
    let mut pts = vec![[256.0, 256.0]; 478];
    for (k, &i) in MEDIAPIPE_TO_IBUG68.iter().enumerate() {
        pts[i] = t.points[k];
    }
    for (e, &i) in MEDIAPIPE_IRIS_CENTRES.iter().enumerate() {
        pts[i] = t.points[68 + e];
    }
    Observation::new(512, 512, Some(FaceLandmarks::new(pts).unwrap())).unwrap()
}

fn bench(c: &mut Criterion) {
    let asset = synthesize(0);
    let rig = LandmarkRig::for_tracking(&asset).unwrap();
    let o = FitOptions::default();
    let shape = sample_shape(&SampleConfig::default(), 5, 0, rig.n_shape);
    let mut rng = Rng::stream(1, &[0]);
    let seq: Vec<FrameState> = (0..100).map(|i| frame(&rig, i as f64)).collect();
    let tg: Vec<LandmarkTargets> = seq
        .iter()
        .map(|s| targets(&rig, &shape, s, &mut rng))
        .collect();

    let mut g = c.benchmark_group("track");
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(4));
    g.bench_function("photo", |b| b.iter(|| fit_photo(&rig, &tg[0], &o).unwrap()));
    let prev = fit_frame(&rig, &shape, &tg[0], None, &o).unwrap().state;
    g.bench_function("video_frame_warm", |b| {
        b.iter(|| fit_frame(&rig, &shape, &tg[1], Some(&prev), &o).unwrap())
    });
    let keys: Vec<&LandmarkTargets> = tg.iter().step_by(12).take(8).collect();
    let zero = vec![0.0; rig.n_shape];
    let starts: Vec<FrameState> = keys
        .iter()
        .map(|t| fit_frame(&rig, &zero, t, None, &o).unwrap().state)
        .collect();
    g.bench_function("video_shape_8_keyframes", |b| {
        b.iter(|| fit_shared_shape(&rig, &keys, &zero, &starts, &o).unwrap())
    });
    let obs: Vec<Observation> = tg.iter().map(observation).collect();
    let opts = TrackOptions::default();
    g.bench_function("track_video_100", |b| {
        b.iter(|| track_video(obs.clone(), &rig, &opts, "bench", |_, _| {}).unwrap())
    });
    let img = image::RgbImage::from_fn(1920, 1080, |x, y| {
        image::Rgb([(x % 256) as u8, (y % 256) as u8, ((x + y) % 256) as u8])
    });
    let win = CropWindow {
        x0: 600,
        y0: 150,
        x1: 1300,
        y1: 850,
    };
    g.bench_function("crop_1080p", |b| b.iter(|| crop_image(&img, &win).unwrap()));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
