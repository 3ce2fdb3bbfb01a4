//! Ground truth from the synthetic FLAME asset and `gagavatar-synthdata`'s samplers (the
//! distributions `gagavatar synth-data` draws its exact records from).

#![allow(dead_code)]

use gagavatar_flame::{synthesize, synthesize_with, BasisMotion};
use gagavatar_synthdata::sample::{sample_frame, sample_shape, Rng, SampleConfig};
use gagavatar_track::camera::{rotation_angle_between, CameraPose};
use gagavatar_track::fit::{reproject, FrameState, LandmarkTargets, LandmarkWeights};
use gagavatar_track::rig::{LandmarkRig, N_LANDMARKS};

pub const SEED: u64 = 11;

pub fn rig() -> LandmarkRig {
    LandmarkRig::for_tracking(&synthesize(0)).unwrap()
}

/// The rig of the synthetic asset with blendshapes free of whole-face motion (as real FLAME
/// bases nearly are; see `BasisMotion`).
pub fn rig_with(motion: BasisMotion) -> LandmarkRig {
    LandmarkRig::for_tracking(&synthesize_with(0, motion)).unwrap()
}

/// RMS distance of the neutral head's 68 landmarks from their centroid: the head's size, which
/// trades against the camera distance.
pub fn head_size(rig: &LandmarkRig, shape: &[f64]) -> f64 {
    let codes = gagavatar_track::rig::FaceCodes {
        shape: shape.to_vec(),
        ..gagavatar_track::rig::FaceCodes::zeros(rig)
    };
    let p = rig.landmarks(&codes).unwrap();
    let p = &p[..68];
    let c: [f64; 3] = std::array::from_fn(|i| p.iter().map(|q| q[i]).sum::<f64>() / 68.0);
    (p.iter()
        .map(|q| (0..3).map(|i| (q[i] - c[i]).powi(2)).sum::<f64>())
        .sum::<f64>()
        / 68.0)
        .sqrt()
}

/// Translation error (percent) after scaling the fitted translation by the ratio of head
/// sizes: what remains once the size-distance trade is taken out.
pub fn size_compensated_translation_error(
    truth: &CameraPose,
    fit: &CameraPose,
    size_truth: f64,
    size_fit: f64,
) -> f64 {
    let k = size_truth / size_fit;
    let d: f64 = (0..3)
        .map(|i| (truth.translation[i] - k * fit.translation[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    let t: f64 = truth.translation.iter().map(|x| x * x).sum::<f64>().sqrt();
    100.0 * d / t
}

/// Identity `id`'s shape and its frame `frame` as a fit state (release conventions).
pub fn truth(rig: &LandmarkRig, id: usize, frame: usize) -> (Vec<f64>, FrameState) {
    let cfg = SampleConfig::default();
    let shape = sample_shape(&cfg, SEED, id, rig.n_shape);
    let f = sample_frame(&cfg, SEED, id, frame, rig.n_exp);
    let state = FrameState {
        expression: f.expression,
        jaw: [f.pose[3], f.pose[4], f.pose[5]],
        eyes: f.eye,
        camera: CameraPose::from_matrix(&f.transform),
    };
    (shape, state)
}

/// The exact 70 landmarks in 512-crop pixels.
pub fn exact_points(rig: &LandmarkRig, shape: &[f64], s: &FrameState) -> [[f64; 2]; N_LANDMARKS] {
    let px = reproject(rig, shape, s).unwrap();
    std::array::from_fn(|k| px[k].expect("synthetic landmarks in front of the camera"))
}

/// Targets with Gaussian noise of `sigma` pixels per coordinate.
pub fn noisy_targets(
    points: &[[f64; 2]; N_LANDMARKS],
    sigma: f64,
    rng: &mut Rng,
    w: &LandmarkWeights,
) -> LandmarkTargets {
    let pts = points.map(|p| [p[0] + sigma * rng.normal(), p[1] + sigma * rng.normal()]);
    LandmarkTargets::with_weights(pts, w).unwrap()
}

/// Camera errors: rotation angle (degrees) and |dT| / |T| (percent).
pub fn camera_error(truth: &CameraPose, fit: &CameraPose) -> (f64, f64) {
    let rot = rotation_angle_between(&truth.rotation, &fit.rotation).to_degrees();
    let d: f64 = (0..3)
        .map(|i| (truth.translation[i] - fit.translation[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    let t: f64 = truth.translation.iter().map(|x| x * x).sum::<f64>().sqrt();
    (rot, 100.0 * d / t)
}

/// Largest distance between two point sets.
pub fn max_dist(a: &[[f64; 2]], b: &[[f64; 2]]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt())
        .fold(0.0, gagavatar_testkit::max_or_nan)
}

pub fn median(v: &[f64]) -> f64 {
    let mut w = v.to_vec();
    w.sort_by(f64::total_cmp);
    w[w.len() / 2]
}

pub fn max(v: &[f64]) -> f64 {
    v.iter().cloned().fold(0.0, gagavatar_testkit::max_or_nan)
}

pub struct TempDir(pub std::path::PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        let p = std::env::temp_dir().join(format!(
            "gagavatar-track-{tag}-{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        Self(p)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A MediaPipe-like observation whose mapped points are `pts70` (frame pixels): the 68 iBUG
/// indices and the iris centres hold the given points, every other mesh point the centroid of
/// the 68 (so the mesh extent is the landmarks' extent).
pub fn observation(
    pts70: &[[f64; 2]; N_LANDMARKS],
    width: u32,
    height: u32,
) -> gagavatar_track::Observation {
    use gagavatar_track::mapping::{MEDIAPIPE_IRIS_CENTRES, MEDIAPIPE_TO_IBUG68};
    let c = [
        pts70[..68].iter().map(|p| p[0]).sum::<f64>() / 68.0,
        pts70[..68].iter().map(|p| p[1]).sum::<f64>() / 68.0,
    ];
    let mut pts = vec![c; 478];
    for (k, &i) in MEDIAPIPE_TO_IBUG68.iter().enumerate() {
        pts[i] = pts70[k];
    }
    for (e, &i) in MEDIAPIPE_IRIS_CENTRES.iter().enumerate() {
        pts[i..i + 5].fill(pts70[68 + e]);
    }
    let lm = gagavatar_track::FaceLandmarks::new(pts).unwrap();
    gagavatar_track::Observation::new(width, height, Some(lm)).unwrap()
}

/// Mean over frames and landmarks of |p[t-1] - 2 p[t] + p[t+1]| (pixels): frame-to-frame
/// jitter, the steadiness measure of the brief.
pub fn mean_second_difference(seq: &[Vec<[f64; 2]>]) -> f64 {
    let mut sum = 0.0;
    let mut n = 0;
    for t in 1..seq.len().saturating_sub(1) {
        for ((a, b), c) in seq[t - 1].iter().zip(&seq[t]).zip(&seq[t + 1]) {
            let d: [f64; 2] = std::array::from_fn(|i| a[i] - 2.0 * b[i] + c[i]);
            sum += (d[0] * d[0] + d[1] * d[1]).sqrt();
            n += 1;
        }
    }
    sum / n.max(1) as f64
}
