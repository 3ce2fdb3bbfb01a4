//! MediaPipe Face Mesh points to the release's 70-point set: iBUG 68 (TRACKING.md section 12,
//! "Mapping B": one mesh index per iBUG point; measured there as the closer of the two public
//! mappings to dlib's 68 points on a test photo, 1.73 px mean against 2.46) followed by the two
//! iris centres as pupils (68 <- 468, the image-left eye; 69 <- 473).
//!
//! Mapping B: jaw 127, 234, 132, 58, 172, 150, 149, 148, 152, 377, 378, 379, 397, 288, 361, 454,
//! 356; brows 70, 63, 105, 66, 107 | 336, 296, 334, 293, 300; nose 168, 197, 5, 4 | 98, 97, 2,
//! 326, 327; eyes 130, 160, 158, 133, 153, 144 | 362, 385, 387, 263, 373, 380; lips (as mapping
//! A) 61, 39, 37, 0, 267, 269, 291, 321, 314, 17, 84, 91 | 78, 82, 13, 312, 308, 317, 14, 87.
//!
//! The FLAME jaw contour is a fixed line on the surface and MediaPipe's jaw points are surface
//! points too, but the two lines are not the same curve: the jaw correspondence is approximate
//! (the fit weights it down by default, see `FitOptions::landmark_weights`).

use crate::observation::FaceLandmarks;
use crate::rig::N_LANDMARKS;

/// iBUG 68 order, one Face Mesh index each.
pub const MEDIAPIPE_TO_IBUG68: [usize; 68] = [
    // jaw 0..16
    127, 234, 132, 58, 172, 150, 149, 148, 152, 377, 378, 379, 397, 288, 361, 454, 356,
    // brows 17..26
    70, 63, 105, 66, 107, 336, 296, 334, 293, 300, // nose 27..35
    168, 197, 5, 4, 98, 97, 2, 326, 327, // eyes 36..47
    130, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380, // outer lips 48..59
    61, 39, 37, 0, 267, 269, 291, 321, 314, 17, 84, 91, // inner lips 60..67
    78, 82, 13, 312, 308, 317, 14, 87,
];

/// Iris centres: image-left eye (pupil 68), then the other (pupil 69).
pub const MEDIAPIPE_IRIS_CENTRES: [usize; 2] = [468, 473];

/// The 70 target points in the landmarks' pixel frame, and which exist (the pupils need the
/// 478-point mesh).
pub fn to_70(landmarks: &FaceLandmarks) -> ([[f64; 2]; N_LANDMARKS], [bool; N_LANDMARKS]) {
    let pts = landmarks.points();
    let mut out = [[0.0; 2]; N_LANDMARKS];
    let mut present = [true; N_LANDMARKS];
    for (o, &i) in out.iter_mut().zip(&MEDIAPIPE_TO_IBUG68) {
        *o = pts[i];
    }
    for (k, &i) in MEDIAPIPE_IRIS_CENTRES.iter().enumerate() {
        if landmarks.has_irises() {
            out[68 + k] = pts[i];
        } else {
            present[68 + k] = false;
        }
    }
    (out, present)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_are_distinct_mesh_points() {
        let mut seen = std::collections::BTreeSet::new();
        for &i in &MEDIAPIPE_TO_IBUG68 {
            assert!(i < 468, "{i}");
            assert!(seen.insert(i), "index {i} used twice");
        }
    }

    #[test]
    fn picks_points_and_flags_missing_irises() {
        let pts: Vec<[f64; 2]> = (0..478).map(|i| [i as f64, -(i as f64)]).collect();
        let (out, present) = to_70(&FaceLandmarks::new(pts.clone()).unwrap());
        assert_eq!(out[8], [152.0, -152.0]);
        assert_eq!(out[36], [130.0, -130.0]);
        assert_eq!(out[68], [468.0, -468.0]);
        assert_eq!(out[69], [473.0, -473.0]);
        assert!(present.iter().all(|&p| p));
        let (_, present) = to_70(&FaceLandmarks::new(pts[..468].to_vec()).unwrap());
        assert!(!present[68] && !present[69] && present[67]);
    }
}
