//! AKD, the average keypoint distance: the mean Euclidean distance, in pixels of the 512
//! realigned crop, between the 68 facial landmarks of the result and of the ground truth.
//!
//! The 68 points are iBUG's, taken from MediaPipe's 478-point mesh (`crates/face`) through the
//! same one-index-per-point mapping the tracker fits (`gagavatar_track::mapping`, "mapping B"
//! of TRACKING.md section 12). The paper's AKD used another 68-point detector; the numbers are
//! comparable in kind, not digit for digit.

use gagavatar_track::mapping::MEDIAPIPE_TO_IBUG68;
use gagavatar_track::observation::FaceLandmarks;

use crate::error::{input_err, Result};

/// Points AKD averages over.
pub const AKD_POINTS: usize = 68;

/// iBUG 68 points of a face mesh, in the mesh's pixels.
pub fn ibug68(lm: &FaceLandmarks) -> [[f64; 2]; AKD_POINTS] {
    let pts = lm.points();
    let mut out = [[0.0; 2]; AKD_POINTS];
    for (o, &i) in out.iter_mut().zip(&MEDIAPIPE_TO_IBUG68) {
        *o = pts[i];
    }
    out
}

/// Mean distance between corresponding points.
pub fn keypoint_distance(a: &[[f64; 2]], b: &[[f64; 2]]) -> Result<f64> {
    if a.len() != b.len() || a.is_empty() {
        return Err(input_err(
            "keypoints",
            format!(
                "{} and {} points; need the same non-zero count",
                a.len(),
                b.len()
            ),
        ));
    }
    let mut sum = 0.0;
    for (i, (p, q)) in a.iter().zip(b).enumerate() {
        let d = (p[0] - q[0]).hypot(p[1] - q[1]);
        if !d.is_finite() {
            return Err(input_err(
                "keypoints",
                format!("point {i} is not finite: {p:?} vs {q:?}"),
            ));
        }
        sum += d;
    }
    Ok(sum / a.len() as f64)
}

/// AKD of two faces' landmarks (both in the realigned crop's pixels).
pub fn akd(result: &FaceLandmarks, target: &FaceLandmarks) -> Result<f64> {
    keypoint_distance(&ibug68(result), &ibug68(target))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh(shift: [f64; 2]) -> FaceLandmarks {
        FaceLandmarks::new(
            (0..478)
                .map(|i| [i as f64 + shift[0], (i % 17) as f64 + shift[1]])
                .collect(),
        )
        .unwrap()
    }

    #[test]
    fn translation_gives_its_length() {
        let a = mesh([0.0, 0.0]);
        assert_eq!(akd(&a, &a).unwrap(), 0.0);
        let d = akd(&a, &mesh([3.0, 4.0])).unwrap();
        assert!((d - 5.0).abs() < 1e-12, "expected 5, got {d}");
    }

    #[test]
    fn only_the_68_mapped_points_count() {
        let a = mesh([0.0, 0.0]);
        let mut pts = a.points().to_vec();
        pts[1] = [1e6, 1e6]; // mesh point 1 (nose tip) is not one of iBUG's 68
        let b = FaceLandmarks::new(pts.clone()).unwrap();
        assert_eq!(akd(&a, &b).unwrap(), 0.0);
        pts[152] = [pts[152][0] + 68.0, pts[152][1]]; // the chin, iBUG 8
        let c = FaceLandmarks::new(pts).unwrap();
        assert!((akd(&a, &c).unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(keypoint_distance(&[], &[]).is_err());
        assert!(keypoint_distance(&[[0.0, 0.0]], &[[0.0, 0.0], [1.0, 1.0]]).is_err());
        assert!(keypoint_distance(&[[f64::NAN, 0.0]], &[[0.0, 0.0]]).is_err());
    }
}
