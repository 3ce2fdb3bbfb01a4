//! AED and APD: how far the result's expression and head pose are from the driver's, both
//! estimated from the images by our own tracker (`crates/track`, a photo fit of FLAME and the
//! release camera to MediaPipe's landmarks, shape prior [`METRIC_SHAPE_PRIOR`]). The paper estimated them with a 3DMM (BFM)
//! regressor; ours are FLAME's codes, so the values are comparable in kind only.
//!
//! Definitions (the README's "Evaluation protocol"):
//! - AED = the mean absolute difference over FLAME's first [`AED_EXPRESSION`] expression
//!   coefficients and the 3 jaw axis-angle components (radians): 53 numbers. Components a FLAME
//!   asset does not have count as zero (the release records are zero-padded the same way).
//! - APD = the geodesic angle, in degrees, between the two heads' rotations relative to the
//!   camera (the rotation part of the fitted `transform_matrix`; FLAME's global pose is zero
//!   in tracked records, the head's rotation lives in the camera). The angle of `Ra^T Rb` is
//!   that of `Rb Ra^T` too, so row- and column-vector conventions agree.

use gagavatar_flame::TrackedFrame;
use gagavatar_track::observation::{FaceLandmarks, Observation};
use gagavatar_track::pipeline::{track_photo, TrackOptions};
use gagavatar_track::rig::LandmarkRig;

use crate::error::{input_err, Result};

/// Expression coefficients AED compares.
pub const AED_EXPRESSION: usize = 50;
/// Jaw axis-angle components AED compares.
pub const AED_JAW: usize = 3;

/// The expression, jaw and head rotation of one face.
#[derive(Debug, Clone, PartialEq)]
pub struct ExpressionPose {
    pub expression: [f64; AED_EXPRESSION],
    pub jaw: [f64; AED_JAW],
    /// Head rotation relative to the camera (row-major 3x3).
    pub rotation: [[f64; 3]; 3],
}

impl ExpressionPose {
    /// From a release record (`expcode`, `posecode[3..6]`, `transform_matrix`).
    pub fn from_record(r: &TrackedFrame) -> Result<Self> {
        let mut expression = [0.0; AED_EXPRESSION];
        for (e, v) in expression.iter_mut().zip(&r.expcode) {
            *e = *v;
        }
        if r.posecode.len() < 6 {
            return Err(input_err(
                "record",
                format!("posecode has {} values, need 6", r.posecode.len()),
            ));
        }
        let jaw = [r.posecode[3], r.posecode[4], r.posecode[5]];
        let tm = r
            .transform_matrix
            .ok_or_else(|| input_err("record", "no transform_matrix"))?;
        let rotation = [
            [tm[0][0], tm[0][1], tm[0][2]],
            [tm[1][0], tm[1][1], tm[1][2]],
            [tm[2][0], tm[2][1], tm[2][2]],
        ];
        let all = expression
            .iter()
            .chain(&jaw)
            .chain(rotation.iter().flatten());
        if let Some(v) = all.into_iter().find(|v| !v.is_finite()) {
            return Err(input_err("record", format!("non-finite value {v}")));
        }
        Ok(Self {
            expression,
            jaw,
            rotation,
        })
    }
}

/// Mean absolute difference of the 50 expression and 3 jaw values.
pub fn aed(a: &ExpressionPose, b: &ExpressionPose) -> f64 {
    let e: f64 = a
        .expression
        .iter()
        .zip(&b.expression)
        .map(|(x, y)| (x - y).abs())
        .sum();
    let j: f64 = a.jaw.iter().zip(&b.jaw).map(|(x, y)| (x - y).abs()).sum();
    (e + j) / (AED_EXPRESSION + AED_JAW) as f64
}

/// Geodesic angle between the head rotations, degrees: the angle of `M = Ra^T Rb` as
/// `atan2(|axis|, (trace - 1) / 2)`, accurate near 0 and near 180 degrees (an `acos` of the
/// trace alone loses half the digits near 0).
pub fn apd(a: &ExpressionPose, b: &ExpressionPose) -> f64 {
    let (ra, rb) = (&a.rotation, &b.rotation);
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = (0..3).map(|k| ra[k][i] * rb[k][j]).sum();
        }
    }
    let cos = (m[0][0] + m[1][1] + m[2][2] - 1.0) / 2.0;
    let sin = 0.5
        * ((m[2][1] - m[1][2]).powi(2) + (m[0][2] - m[2][0]).powi(2) + (m[1][0] - m[0][1]).powi(2))
            .sqrt();
    sin.atan2(cos).to_degrees()
}

/// The shape prior of the metrics' photo fits: 10x the tracker's default (4). One photo's
/// landmarks leave head rotation and the 100 shape components partly interchangeable; with the
/// default prior the fit explains MediaPipe's landmarks on synthetic renders within 1-2 px
/// yet lands 12-58 degrees from the true head rotation, with this one 6-13 degrees (one
/// MediaPipe miss aside), measured on 8 synthetic 512 heads
/// (`tests/reference_checks.rs` prints the per-frame numbers).
pub const METRIC_SHAPE_PRIOR: f64 = 40.0;

/// Estimates expression and pose from landmarks with the tracker's photo fit.
#[derive(Debug)]
pub struct PoseEstimator {
    rig: LandmarkRig,
    options: TrackOptions,
}

impl PoseEstimator {
    pub fn new(rig: LandmarkRig, options: TrackOptions) -> Self {
        Self { rig, options }
    }

    /// The estimator AED and APD use: the tracker's options with [`METRIC_SHAPE_PRIOR`].
    pub fn for_metrics(rig: LandmarkRig) -> Self {
        let mut options = TrackOptions::default();
        options.fit.shape_prior = METRIC_SHAPE_PRIOR;
        Self::new(rig, options)
    }

    pub fn options(&self) -> &TrackOptions {
        &self.options
    }

    /// The fit of a face's landmarks in a `width x height` image.
    pub fn estimate(&self, lm: &FaceLandmarks, width: u32, height: u32) -> Result<ExpressionPose> {
        let obs = Observation::new(width, height, Some(lm.clone()))
            .map_err(|e| input_err("observation", e.to_string()))?;
        let photo = track_photo(&obs, &self.rig, &self.options, "evaluated image")
            .map_err(|e| input_err("tracking", e.to_string()))?;
        ExpressionPose::from_record(&photo.frame.record)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot_z(deg: f64) -> [[f64; 3]; 3] {
        let (s, c) = deg.to_radians().sin_cos();
        [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    }

    fn pose(exp0: f64, jaw0: f64, deg: f64) -> ExpressionPose {
        let mut expression = [0.0; AED_EXPRESSION];
        expression[0] = exp0;
        ExpressionPose {
            expression,
            jaw: [jaw0, 0.0, 0.0],
            rotation: rot_z(deg),
        }
    }

    #[test]
    fn known_differences() {
        let a = pose(0.0, 0.0, 0.0);
        assert_eq!(aed(&a, &a), 0.0);
        assert_eq!(apd(&a, &a), 0.0);
        assert!(
            (apd(&pose(0.0, 0.0, 1e-6), &a) - 1e-6).abs() < 1e-18,
            "small angles keep their digits"
        );
        assert!((apd(&pose(0.0, 0.0, 180.0), &a) - 180.0).abs() < 1e-9);
        let b = pose(2.0, -0.65, 30.0);
        let want = (2.0 + 0.65) / 53.0;
        assert!(
            (aed(&a, &b) - want).abs() < 1e-15,
            "{} vs {want}",
            aed(&a, &b)
        );
        assert!((apd(&a, &b) - 30.0).abs() < 1e-9, "{}", apd(&a, &b));
        // Symmetric, and the angle of a relative rotation whatever the common part.
        let c = pose(0.0, 0.0, 100.0);
        assert!((apd(&c, &pose(0.0, 0.0, 75.0)) - 25.0).abs() < 1e-9);
        assert_eq!(aed(&a, &b), aed(&b, &a));
    }

    #[test]
    fn records_are_read_and_checked() {
        let mut r = TrackedFrame {
            shapecode: vec![0.0; 300],
            expcode: (0..100).map(|i| i as f64).collect(),
            posecode: vec![0.0, 0.0, 0.0, 0.1, 0.2, 0.3],
            eyecode: vec![0.0; 6],
            transform_matrix: Some([
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 9.0],
            ]),
            bbox: None,
        };
        let p = ExpressionPose::from_record(&r).unwrap();
        assert_eq!(p.expression[49], 49.0);
        assert_eq!(p.jaw, [0.1, 0.2, 0.3]);
        r.expcode = vec![1.0; 10]; // a short asset: the rest count as zero
        assert_eq!(ExpressionPose::from_record(&r).unwrap().expression[10], 0.0);
        r.posecode.truncate(3);
        assert!(ExpressionPose::from_record(&r).is_err());
        r.posecode = vec![0.0; 6];
        r.transform_matrix = None;
        assert!(ExpressionPose::from_record(&r).is_err());
        r.transform_matrix = Some([[f64::NAN; 4]; 3]);
        assert!(ExpressionPose::from_record(&r).is_err());
    }
}
