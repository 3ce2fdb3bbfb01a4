//! Ground truth on synthetic heads: landmarks projected from known FLAME codes and cameras
//! (the samplers of `gagavatar synth-data`), fitted back.
//!
//! What 70 landmarks can determine, and so what each test asserts:
//! - The identity known (a video after its shape solve): the camera, to a fraction of a
//!   degree and a percent (`exact_landmarks_give_the_camera_when_the_identity_is_known`).
//! - One photo, the identity unknown: not the camera. The 100 shape and 100 expression
//!   blendshapes move the 140 landmark coordinates in every direction a turn of the camera
//!   does (`one_photo_cannot_determine_the_camera_without_the_identity` shows it by linear
//!   algebra at the true state), so the priors alone choose the split between camera and codes;
//!   the fit still reprojects the landmarks to a fraction of a pixel.
//! - A video, the identity unknown: views from several directions pin the shared shape, and
//!   the rotation is back within a degree. The translation is known only relative to the
//!   head's size: a head k times larger, k times farther away gives the same image under any
//!   pinhole camera, and the shape blendshapes change the head's size. The tests score the
//!   translation after that trade (`size_compensated_translation_error`) and print both.
//!
//! Figures: `cargo test -p gagavatar-track --test ground_truth -- --nocapture`.

mod common;

use common::*;
use gagavatar_synthdata::sample::Rng;
use gagavatar_track::fit::{
    fit_frame, fit_photo, fit_sequence, reproject, FitOptions, FrameState, LandmarkWeights,
};
use gagavatar_track::rig::LandmarkRig;

/// Reprojection of exact landmarks (pixels at 512): the brief's 1 px.
const REPROJ_TOL_PX: f64 = 1.0;
/// The brief's 1 % (for the unknown identity: after the size-distance trade).
const TRANS_TOL_PCT: f64 = 1.0;
/// The brief's 1 degree, on every frame.
const ROT_TOL_DEG: f64 = 1.0;
/// One photo, identity unknown: the ambiguity described above (measured up to 5.4 degrees and
/// 9.6 %); these bounds catch a broken solver (a flipped or unconverged camera), not the
/// ambiguity.
const PHOTO_ROT_TOL_DEG: f64 = 9.0;
const PHOTO_TRANS_TOL_PCT: f64 = 12.0;

/// How much weaker than the defaults the priors are for exact landmarks. The defaults hold the
/// codes against a real detector's noise; exact landmarks have none, so their priors only need
/// to choose among explanations that fit exactly, and Huber's outlier guard has nothing to do.
/// The shape's is the weakest: it is what a video's several views determine. (Measured on the
/// video test, rotation max 0.24 degrees at these scales, 0.83 with the codes' also at 1e-3,
/// 1.8 with the shape's at 1e-2: a stronger shape prior keeps the shared shape from its value.)
const EXACT_SHAPE_PRIOR_SCALE: f64 = 1e-3;
const EXACT_CODE_PRIOR_SCALE: f64 = 1e-2;

/// The synthetic contour is exactly FLAME's static contour, so it is trusted fully here (the
/// default halves it for real detectors, whose jaw line is another curve). The jaw's sideways
/// and twist terms, the eyes' roll and the eyes' coupling stay: they hold motions the
/// synthetic heads never make, as real faces seldom do.
fn exact_options() -> FitOptions {
    let d = FitOptions::default();
    let k = EXACT_CODE_PRIOR_SCALE;
    let mut o = FitOptions {
        shape_prior: d.shape_prior * EXACT_SHAPE_PRIOR_SCALE,
        expression_prior: d.expression_prior * k,
        jaw_prior: [d.jaw_prior[0] * k, d.jaw_prior[1], d.jaw_prior[2]],
        eye_prior: [d.eye_prior[0] * k, d.eye_prior[1] * k, d.eye_prior[2]],
        huber_px: None,
        ..d
    };
    o.landmark_weights.contour = 1.0;
    o
}

fn weights() -> LandmarkWeights {
    exact_options().landmark_weights
}

/// Fraction of the landmarks' motion along `c` that no combination of `others` reproduces
/// (0: `c` lies in their span). Modified Gram-Schmidt, twice for stability.
fn fraction_outside_span(others: &[Vec<f64>], c: &[f64]) -> f64 {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let remove = |w: &mut Vec<f64>, basis: &[Vec<f64>]| {
        for _ in 0..2 {
            for b in basis {
                let d = dot(w, b);
                w.iter_mut().zip(b).for_each(|(wi, bi)| *wi -= d * bi);
            }
        }
    };
    let mut basis: Vec<Vec<f64>> = vec![];
    for v in others {
        let scale = dot(v, v).sqrt();
        let mut w = v.clone();
        remove(&mut w, &basis);
        let n = dot(&w, &w).sqrt();
        if n > 1e-8 * scale.max(1e-300) {
            basis.push(w.iter().map(|x| x / n).collect());
        }
    }
    let mut w = c.to_vec();
    remove(&mut w, &basis);
    dot(&w, &w).sqrt() / dot(c, c).sqrt()
}

/// Central-difference derivatives of the 140 landmark coordinates (pixels) at the true state:
/// (shape columns, expression + jaw + eye columns, rotation columns, translation columns).
#[allow(clippy::type_complexity)]
fn landmark_jacobian(
    rig: &LandmarkRig,
    shape: &[f64],
    st: &FrameState,
) -> (Vec<Vec<f64>>, Vec<Vec<f64>>, Vec<Vec<f64>>, Vec<Vec<f64>>) {
    const H: f64 = 1e-5;
    let points = |sh: &[f64], s: &FrameState| -> Vec<f64> {
        exact_points(rig, sh, s)
            .iter()
            .flat_map(|p| [p[0], p[1]])
            .collect()
    };
    let column = |f: &dyn Fn(&mut Vec<f64>, &mut FrameState, f64)| -> Vec<f64> {
        let (mut s1, mut a) = (shape.to_vec(), st.clone());
        f(&mut s1, &mut a, H);
        let (mut s2, mut b) = (shape.to_vec(), st.clone());
        f(&mut s2, &mut b, -H);
        points(&s1, &a)
            .iter()
            .zip(points(&s2, &b))
            .map(|(p, q)| (p - q) / (2.0 * H))
            .collect()
    };
    let shape_cols = (0..rig.n_shape)
        .map(|k| column(&|sh, _, e| sh[k] += e))
        .collect();
    let mut code_cols: Vec<Vec<f64>> = (0..rig.n_exp)
        .map(|k| column(&|_, s, e| s.expression[k] += e))
        .collect();
    code_cols.extend((0..3).map(|k| column(&|_, s, e| s.jaw[k] += e)));
    code_cols.extend((0..6).map(|k| column(&|_, s, e| s.eyes[k] += e)));
    let axis = |k: usize, e: f64| {
        let mut d = [0.0; 3];
        d[k] = e;
        d
    };
    let rot = (0..3)
        .map(|k| column(&|_, s, e| s.camera.retract(&axis(k, e), &[0.0; 3])))
        .collect();
    let trans = (0..3)
        .map(|k| column(&|_, s, e| s.camera.retract(&[0.0; 3], &axis(k, e))))
        .collect();
    (shape_cols, code_cols, rot, trans)
}

#[test]
fn exact_landmarks_give_the_camera_when_the_identity_is_known() {
    let rig = rig();
    // The exact options, then the defaults (set for real detectors, so the priors bias the
    // codes a little and the camera with them).
    for (name, o) in [
        ("exact", exact_options()),
        ("default", FitOptions::default()),
    ] {
        let mut rng = Rng::stream(1, &[0]);
        let (mut rots, mut trans, mut reps, mut gaze) = (vec![], vec![], vec![], vec![]);
        for id in 0..16 {
            let (shape, st) = truth(&rig, id, 1);
            let pts = exact_points(&rig, &shape, &st);
            let t = noisy_targets(&pts, 0.0, &mut rng, &o.landmark_weights);
            let fit = fit_frame(&rig, &shape, &t, None, &o).unwrap();
            let (r, tr) = camera_error(&st.camera, &fit.state.camera);
            let e = max_dist(&exact_points(&rig, &shape, &fit.state), &pts);
            assert!(
                e <= REPROJ_TOL_PX && tr <= TRANS_TOL_PCT && r <= ROT_TOL_DEG,
                "{name} options, identity {id}: reprojection {e:.3} px (tol {REPROJ_TOL_PX}), \
                 translation {tr:.3} % (tol {TRANS_TOL_PCT}), rotation {r:.3} deg (tol \
                 {ROT_TOL_DEG})"
            );
            rots.push(r);
            trans.push(tr);
            reps.push(e);
            // Gaze (pitch, yaw of both eyes; the synthetic eyes look the same way).
            for i in [0, 1, 3, 4] {
                gaze.push((fit.state.eyes[i] - st.eyes[i]).abs().to_degrees());
            }
        }
        println!(
            "known identity, exact landmarks, {name} options, 16 frames: rotation median {:.3} \
             max {:.3} deg; translation median {:.3} max {:.3} %; reprojection max {:.3} px; \
             gaze angles median {:.2} max {:.2} deg off",
            median(&rots),
            max(&rots),
            median(&trans),
            max(&trans),
            max(&reps),
            median(&gaze),
            max(&gaze)
        );
    }
}

/// The linear algebra behind the photo's ambiguity, at the true state of several heads: the
/// landmarks' motion under a small turn of the camera about any axis is reproduced by the codes
/// (with the other camera parameters) once the shape is free, but not with the shape known.
/// It holds for the blendshapes as drawn and for blendshapes made free of whole-face motion
/// (`BasisMotion::RigidFree`, as real FLAME bases nearly are): what the codes reproduce is not
/// a rigid turn but its image, depth-proportional shifts a view from 9 units cannot tell apart.
#[test]
fn one_photo_cannot_determine_the_camera_without_the_identity() {
    use gagavatar_flame::BasisMotion;
    /// "In the span": what is left is numerical noise of the central differences.
    const IN_SPAN: f64 = 1e-4;
    /// "Determined": a 1 degree turn (15-21 px over the 140 coordinates) leaves at least
    /// 0.15 px that no code explains; measured at least 0.020.
    const OUTSIDE_SPAN: f64 = 0.01;
    for motion in [BasisMotion::AsDrawn, BasisMotion::RigidFree] {
        let rig = rig_with(motion);
        let (mut free, mut known) = (0.0f64, f64::INFINITY);
        for id in 0..4 {
            let (shape, st) = truth(&rig, id, 1);
            let (shape_cols, code_cols, rot, trans) = landmark_jacobian(&rig, &shape, &st);
            for (a, c) in rot.iter().enumerate() {
                let mut others = code_cols.clone();
                others.extend(
                    rot.iter()
                        .enumerate()
                        .filter(|(b, _)| *b != a)
                        .map(|x| x.1.clone()),
                );
                others.extend(trans.iter().cloned());
                let with_shape_known = fraction_outside_span(&others, c);
                others.extend(shape_cols.iter().cloned());
                let with_shape_free = fraction_outside_span(&others, c);
                assert!(
                    with_shape_free <= IN_SPAN && with_shape_known >= OUTSIDE_SPAN,
                    "{motion:?}, identity {id}, rotation axis {a}: fraction of the turn's \
                     landmark motion outside the codes' span {with_shape_free:.2e} with the \
                     shape free (expected <= {IN_SPAN:e}), {with_shape_known:.4} with it known \
                     (expected >= {OUTSIDE_SPAN})"
                );
                free = free.max(with_shape_free);
                known = known.min(with_shape_known);
            }
        }
        println!(
            "blendshapes {motion:?}, 4 heads x 3 axes: a camera turn's landmark motion outside \
             the codes' span: at most {free:.1e} with the shape free, at least {known:.4} with \
             it known"
        );
    }
}

#[test]
fn exact_landmarks_reproject_from_one_photo() {
    let rig = rig();
    let o = exact_options();
    let mut rng = Rng::stream(1, &[1]);
    let (mut rots, mut trans, mut reps, mut trans_c) = (vec![], vec![], vec![], vec![]);
    for id in 0..6 {
        let (shape, st) = truth(&rig, id, 1);
        let pts = exact_points(&rig, &shape, &st);
        let t = noisy_targets(&pts, 0.0, &mut rng, &weights());
        let fit = fit_photo(&rig, &t, &o).unwrap();
        let (r, tr) = camera_error(&st.camera, &fit.frame.state.camera);
        let trc = size_compensated_translation_error(
            &st.camera,
            &fit.frame.state.camera,
            head_size(&rig, &shape),
            head_size(&rig, &fit.shape),
        );
        trans_c.push(trc);
        let e = max_dist(&exact_points(&rig, &fit.shape, &fit.frame.state), &pts);
        assert!(
            e <= REPROJ_TOL_PX && r <= PHOTO_ROT_TOL_DEG && tr <= PHOTO_TRANS_TOL_PCT,
            "identity {id}: reprojection {e:.3} px, rotation {r:.3} deg, translation {tr:.3} %"
        );
        rots.push(r);
        trans.push(tr);
        reps.push(e);
    }
    println!(
        "one photo, identity unknown, exact landmarks, 6 photos: rotation median {:.3} max \
         {:.3} deg; translation median {:.3} max {:.3} % (after the size-distance trade \
         median {:.3} max {:.3} %); reprojection max {:.3} px",
        median(&rots),
        max(&rots),
        median(&trans),
        max(&trans),
        median(&trans_c),
        max(&trans_c),
        max(&reps)
    );
}

/// Realistic detector noise: figures only beyond loose sanity bounds (the noise's own size).
#[test]
fn noisy_landmarks_figures() {
    let rig = rig();
    let o = FitOptions::default();
    for sigma in [1.0, 2.0] {
        let mut rng = Rng::stream(2, &[sigma as u64]);
        let (mut rots, mut trans, mut reps) = (vec![], vec![], vec![]);
        for id in 0..8 {
            let (shape, st) = truth(&rig, id, 2);
            let pts = exact_points(&rig, &shape, &st);
            let t = noisy_targets(&pts, sigma, &mut rng, &o.landmark_weights);
            let fit = fit_frame(&rig, &shape, &t, None, &o).unwrap();
            let (r, tr) = camera_error(&st.camera, &fit.state.camera);
            let e = max_dist(&exact_points(&rig, &shape, &fit.state), &pts);
            // Noise of sigma spreads over 140 coordinates; a fit pulled off by it by more than
            // 4 sigma at any landmark would be broken.
            assert!(
                e <= 4.0 * sigma,
                "sigma {sigma}, identity {id}: max error to the clean points {e:.3} px"
            );
            rots.push(r);
            trans.push(tr);
            reps.push(e);
        }
        println!(
            "known identity, noise {sigma} px: rotation median {:.3} max {:.3} deg; translation \
             median {:.3} max {:.3} %; max error to the clean landmarks median {:.3} max {:.3} px",
            median(&rots),
            max(&rots),
            median(&trans),
            max(&trans),
            median(&reps),
            max(&reps)
        );
    }
}

/// Per-frame camera errors of a 16-frame video of one synthetic head (poses drawn
/// independently per frame) with landmark noise `sigma`, fitted by `fit_sequence`.
struct VideoFigures {
    rotation_deg: Vec<f64>,
    translation_pct: Vec<f64>,
    /// After the size-distance trade.
    translation_traded_pct: Vec<f64>,
    /// Largest distance of each frame's reprojection from the clean landmarks (pixels).
    reprojection_px: Vec<f64>,
}

fn video_figures(o: &FitOptions, sigma: f64) -> VideoFigures {
    let rig = rig();
    let mut rng = Rng::stream(3, &[sigma.to_bits()]);
    let id = 3;
    let n = 16;
    let mut truths = vec![];
    let mut targets = vec![];
    let mut shape_true = vec![];
    for f in 0..n {
        let (shape, st) = truth(&rig, id, f + 1);
        shape_true = shape.clone();
        let pts = exact_points(&rig, &shape, &st);
        targets.push(Some(noisy_targets(
            &pts,
            sigma,
            &mut rng,
            &o.landmark_weights,
        )));
        truths.push((st, pts));
    }
    let fit = fit_sequence(&rig, &targets, o, |_| {}).unwrap();
    assert_eq!(fit.shape.len(), rig.n_shape);
    assert_eq!(fit.keyframes.len(), o.keyframes);
    let mut v = VideoFigures {
        rotation_deg: vec![],
        translation_pct: vec![],
        translation_traded_pct: vec![],
        reprojection_px: vec![],
    };
    let (size_t, size_f) = (head_size(&rig, &shape_true), head_size(&rig, &fit.shape));
    for (f, (st, pts)) in fit.frames.iter().zip(&truths) {
        let f = f.as_ref().expect("every frame has targets");
        let (r, tr) = camera_error(&st.camera, &f.state.camera);
        v.rotation_deg.push(r);
        v.translation_pct.push(tr);
        v.translation_traded_pct
            .push(size_compensated_translation_error(
                &st.camera,
                &f.state.camera,
                size_t,
                size_f,
            ));
        let px = reproject(&rig, &fit.shape, &f.state).unwrap();
        let px: Vec<[f64; 2]> = px.into_iter().map(Option::unwrap).collect();
        v.reprojection_px.push(max_dist(&px, pts));
    }
    v
}

impl VideoFigures {
    fn print(&self, what: &str) {
        println!(
            "video of 16 frames, identity unknown, {what}: rotation median {:.3} max {:.3} deg; \
             translation median {:.3} max {:.3} % (after the size-distance trade median {:.3} \
             max {:.3} %); distance to the clean landmarks max {:.3} px",
            median(&self.rotation_deg),
            max(&self.rotation_deg),
            median(&self.translation_pct),
            max(&self.translation_pct),
            median(&self.translation_traded_pct),
            max(&self.translation_traded_pct),
            max(&self.reprojection_px)
        );
    }
}

/// A video with the identity unknown, exact landmarks: one shape solved on keyframes, then
/// every frame. Views from several directions pin the shared shape, so the cameras come back
/// within the brief's bounds (the translation up to the head's size, see the top of this file).
#[test]
fn video_shares_one_shape_and_tracks_the_camera() {
    let v = video_figures(&exact_options(), 0.0);
    v.print("exact landmarks, exact options");
    for f in 0..v.rotation_deg.len() {
        let (r, tc, e) = (
            v.rotation_deg[f],
            v.translation_traded_pct[f],
            v.reprojection_px[f],
        );
        assert!(
            r <= ROT_TOL_DEG && tc <= TRANS_TOL_PCT && e <= REPROJ_TOL_PX,
            "frame {f}: rotation {r:.3} deg (tol {ROT_TOL_DEG}), translation after the \
             size-distance trade {tc:.3} % (tol {TRANS_TOL_PCT}), reprojection {e:.3} px (tol \
             {REPROJ_TOL_PX})"
        );
    }
    // The head's size itself is the prior's choice; only a far-off one would be a fault.
    assert!(
        max(&v.translation_pct) <= PHOTO_TRANS_TOL_PCT,
        "translation {:.3} %",
        max(&v.translation_pct)
    );
}

/// The same video with the default options, exact and with realistic detector noise: figures,
/// beyond a guard against a broken fit. The default shape prior (set against distorted heads
/// in photos) holds the shared shape near the mean, which these heads (drawn with |shape|
/// about 3.5) are not: that bias alone is 3.5 px and 4.7 degrees with exact landmarks, and
/// the guard allows it plus 4 sigma of noise at a landmark. With a weaker shape prior
/// (`FitOptions::shape_prior`) the camera is better and the head's size worse (measured,
/// exact landmarks: prior 4, 1.7 degrees and 8.7 %; prior 0.4, 1.1 degrees and 20 %).
#[test]
fn noisy_video_figures() {
    const PRIOR_BIAS_PX: f64 = 4.0;
    /// Measured up to 9.1 degrees at 2 px; a flipped or unconverged camera is tens of degrees.
    const ROT_GUARD_DEG: f64 = 15.0;
    for sigma in [0.0, 1.0, 2.0] {
        let v = video_figures(&FitOptions::default(), sigma);
        v.print(&format!("{sigma} px noise, default options"));
        assert!(
            max(&v.reprojection_px) <= PRIOR_BIAS_PX + 4.0 * sigma
                && max(&v.rotation_deg) <= ROT_GUARD_DEG,
            "sigma {sigma}: distance to the clean landmarks {:.3} px, rotation {:.3} deg",
            max(&v.reprojection_px),
            max(&v.rotation_deg)
        );
    }
}
