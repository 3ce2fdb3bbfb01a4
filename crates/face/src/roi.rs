//! Where the landmark model looks: the rotated square around a face, from a detection or from
//! the previous frame's landmarks (spec TRACKING.md section 10; MediaPipe's
//! `DetectionsToRectsCalculator` and `RectTransformationCalculator` with the face mesh's
//! options, in their f32 arithmetic).

use crate::detection::Detection;
use crate::warp::RotatedRect;

/// A rectangle in normalised image coordinates with a rotation in radians (MediaPipe's
/// `NormalizedRect`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NormRect {
    pub x_center: f32,
    pub y_center: f32,
    pub width: f32,
    pub height: f32,
    pub rotation: f32,
}

/// The landmark crop is this much larger than the face box (both ways).
pub const ROI_SCALE: f32 = 1.5;

impl NormRect {
    /// The rectangle in pixels of a `w x h` image (`GetRoi`).
    pub fn to_pixels(&self, w: u32, h: u32) -> RotatedRect {
        RotatedRect {
            cx: self.x_center * w as f32,
            cy: self.y_center * h as f32,
            w: self.width * w as f32,
            h: self.height * h as f32,
            rotation: self.rotation,
        }
    }

    /// Intersection over union of the axis-aligned extents (rotation ignored).
    pub fn iou(&self, o: &NormRect) -> f32 {
        let a = (
            self.x_center - self.width / 2.0,
            self.y_center - self.height / 2.0,
        );
        let b = (o.x_center - o.width / 2.0, o.y_center - o.height / 2.0);
        let ix = (a.0 + self.width).min(b.0 + o.width) - a.0.max(b.0);
        let iy = (a.1 + self.height).min(b.1 + o.height) - a.1.max(b.1);
        if ix <= 0.0 || iy <= 0.0 {
            return 0.0;
        }
        let inter = ix * iy;
        inter / (self.width * self.height + o.width * o.height - inter)
    }
}

/// `angle` wrapped into [-pi, pi) (computed in f64 as MediaPipe's `NormalizeRadians`).
pub fn normalize_radians(angle: f32) -> f32 {
    let a = angle as f64;
    let pi = std::f64::consts::PI;
    (a - 2.0 * pi * ((a + pi) / (2.0 * pi)).floor()) as f32
}

/// The rotation that brings the vector from point 0 to point 1 (normalised coordinates of a
/// `w x h` image, measured in pixels) to horizontal.
pub fn rotation(p0: [f32; 2], p1: [f32; 2], w: u32, h: u32) -> f32 {
    let (x0, y0) = (p0[0] * w as f32, p0[1] * h as f32);
    let (x1, y1) = (p1[0] * w as f32, p1[1] * h as f32);
    normalize_radians(0.0 - (-(y1 - y0)).atan2(x1 - x0))
}

/// Squares the rectangle by its longer side in pixels and scales it by [`ROI_SCALE`].
fn square_long_scaled(mut r: NormRect, w: u32, h: u32) -> NormRect {
    let long = (r.width * w as f32).max(r.height * h as f32);
    r.width = long / w as f32 * ROI_SCALE;
    r.height = long / h as f32 * ROI_SCALE;
    r
}

/// The landmark ROI of a detection: its box, turned so the eyes (keypoints 0 and 1) are level.
pub fn from_detection(d: &Detection, w: u32, h: u32) -> NormRect {
    let r = NormRect {
        x_center: d.xmin + d.width / 2.0,
        y_center: d.ymin + d.height / 2.0,
        width: d.width,
        height: d.height,
        rotation: rotation(d.keypoints[0], d.keypoints[1], w, h),
    };
    square_long_scaled(r, w, h)
}

/// The next frame's ROI from this frame's landmarks (normalised x, y): their bounding box,
/// turned so the outer eye corners (points 33 and 263) are level.
pub fn from_landmarks(lm: &[[f32; 3]], w: u32, h: u32) -> NormRect {
    // MediaPipe starts the maxima at the smallest positive float, not the lowest.
    let (mut x0, mut x1, mut y0, mut y1) =
        (f32::MAX, f32::MIN_POSITIVE, f32::MAX, f32::MIN_POSITIVE);
    for p in lm {
        x0 = x0.min(p[0]);
        x1 = x1.max(p[0]);
        y0 = y0.min(p[1]);
        y1 = y1.max(p[1]);
    }
    let (bw, bh) = (x1 - x0, y1 - y0);
    let r = NormRect {
        x_center: x0 + bw / 2.0,
        y_center: y0 + bh / 2.0,
        width: bw,
        height: bh,
        rotation: rotation([lm[33][0], lm[33][1]], [lm[263][0], lm[263][1]], w, h),
    };
    square_long_scaled(r, w, h)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radians_wrap() {
        assert!((normalize_radians(3.5) - (3.5 - 2.0 * std::f32::consts::PI)).abs() < 1e-6);
        assert_eq!(normalize_radians(0.25), 0.25);
        assert!((normalize_radians(std::f32::consts::PI) + std::f32::consts::PI).abs() < 1e-6);
    }

    #[test]
    fn rotation_levels_the_eyes() {
        // The image-right eye 10 px higher than the image-left one over 20 px.
        let r = rotation([0.4, 0.5], [0.6, 0.4], 100, 100);
        assert!((r + 10f32.atan2(20.0)).abs() < 1e-6, "{r}");
        assert_eq!(rotation([0.4, 0.5], [0.6, 0.5], 100, 100), 0.0);
    }

    #[test]
    fn detection_roi_is_a_scaled_square() {
        let d = Detection {
            score: 1.0,
            xmin: 0.2,
            ymin: 0.1,
            width: 0.2,
            height: 0.4,
            keypoints: [
                [0.25, 0.2],
                [0.35, 0.2],
                [0.3, 0.3],
                [0.3, 0.4],
                [0.2, 0.2],
                [0.4, 0.2],
            ],
        };
        // 200x100 image: the box is 40x40 px.
        let r = from_detection(&d, 200, 100);
        assert!(
            (r.width * 200.0 - 60.0).abs() < 1e-4 && (r.height * 100.0 - 60.0).abs() < 1e-4,
            "{r:?}"
        );
        assert_eq!((r.x_center, r.y_center, r.rotation), (0.3, 0.3, 0.0));
    }
}
