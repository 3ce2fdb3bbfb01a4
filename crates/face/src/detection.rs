//! Face detection as MediaPipe's `FaceDetection` graph does it (spec TRACKING.md section 9):
//! letterbox the image into the detector's square input, run the network, decode boxes and
//! keypoints against the SSD anchors, keep scores at or above the threshold, merge overlapping
//! boxes by score-weighted non-maximum suppression, and map the result back through the
//! letterbox into the image. Arithmetic follows MediaPipe's calculators in f32, operation by
//! operation, so results agree to rounding.

use image::RgbImage;

use crate::anchors::{self, Anchor};
use crate::detection_net::{FullRangeNet, RawDetections, ShortRangeNet};
use crate::warp::{self, RotatedRect};
use crate::weights::{bundled, WeightsFile};
use crate::FaceError;

/// A detected face in normalised image coordinates (0..1 of the width and height, x right, y
/// down), as MediaPipe reports it.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    /// Face probability.
    pub score: f32,
    pub xmin: f32,
    pub ymin: f32,
    pub width: f32,
    pub height: f32,
    /// Right eye, left eye, nose tip, mouth centre, right ear tragion, left ear tragion ("right"
    /// is the subject's right: image left in an unmirrored photo).
    pub keypoints: [[f32; 2]; 6],
}

impl Detection {
    /// `[x0, y0, x1, y1]` in pixels of a `w x h` image.
    pub fn box_pixels(&self, w: u32, h: u32) -> [f32; 4] {
        let (w, h) = (w as f32, h as f32);
        [
            self.xmin * w,
            self.ymin * h,
            (self.xmin + self.width) * w,
            (self.ymin + self.height) * h,
        ]
    }

    /// The keypoints in pixels of a `w x h` image.
    pub fn keypoints_pixels(&self, w: u32, h: u32) -> [[f32; 2]; 6] {
        self.keypoints.map(|[x, y]| [x * w as f32, y * h as f32])
    }
}

/// Which detector network.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DetectorModel {
    /// 128x128, faces within about 2 m (MediaPipe `model_selection=0`; FaceMesh's detector).
    ShortRange,
    /// 192x192, faces within about 5 m (`model_selection=1`).
    FullRange,
}

impl DetectorModel {
    /// The weights file's model name.
    pub fn name(self) -> &'static str {
        match self {
            DetectorModel::ShortRange => "face_detection_short_range",
            DetectorModel::FullRange => "face_detection_full_range",
        }
    }
}

#[derive(Debug, Clone)]
enum Net {
    Short(Box<ShortRangeNet>),
    Full(Box<FullRangeNet>),
}

/// A face detector: network, anchors and decoding.
#[derive(Debug, Clone)]
pub struct FaceDetector {
    net: Net,
    anchors: Vec<Anchor>,
    size: usize,
    /// Detections below this score are dropped before suppression: the graphs' defaults,
    /// 0.5 for short range and 0.6 for full range. (MediaPipe 0.10.21's Python
    /// `FaceDetection` ignores its `min_detection_confidence`: measured, the graph defaults
    /// apply whatever it is set to.)
    pub min_score: f32,
}

/// IoU above which boxes merge in the weighted suppression.
const NMS_IOU: f32 = 0.3;
/// Logits are clipped to +-100 before the sigmoid.
const SCORE_CLIP: f32 = 100.0;

impl FaceDetector {
    /// The detector with the weights shipped in this crate.
    pub fn new(model: DetectorModel) -> Result<Self, FaceError> {
        let (bytes, label) = match model {
            DetectorModel::ShortRange => (
                bundled::FACE_DETECTION_SHORT_RANGE,
                "face_detection_short_range.safetensors",
            ),
            DetectorModel::FullRange => (
                bundled::FACE_DETECTION_FULL_RANGE,
                "face_detection_full_range.safetensors",
            ),
        };
        Self::from_weights(model, WeightsFile::from_bytes(bytes, label)?)
    }

    /// The detector with weights from a file (refused unless every key and shape matches).
    pub fn from_weights(model: DetectorModel, file: WeightsFile) -> Result<Self, FaceError> {
        let (net, anchors, size, min_score) = match model {
            DetectorModel::ShortRange => (
                Net::Short(Box::new(file.build(model.name(), ShortRangeNet::new)?)),
                anchors::short_range(),
                ShortRangeNet::INPUT,
                0.5,
            ),
            DetectorModel::FullRange => (
                Net::Full(Box::new(file.build(model.name(), FullRangeNet::new)?)),
                anchors::full_range(),
                FullRangeNet::INPUT,
                0.6,
            ),
        };
        Ok(FaceDetector {
            net,
            anchors,
            size,
            min_score,
        })
    }

    /// The network's input size in pixels.
    pub fn input_size(&self) -> usize {
        self.size
    }

    /// Raw network outputs for an input tensor (`size x size x 3` in [-1, 1]).
    pub fn raw(&self, x: &crate::tensor::Nhwc) -> RawDetections {
        match &self.net {
            Net::Short(n) => n.forward(x),
            Net::Full(n) => n.forward(x),
        }
    }

    /// Faces in `img`, best first.
    pub fn detect(&self, img: &RgbImage) -> Result<Vec<Detection>, FaceError> {
        if img.width() == 0 || img.height() == 0 {
            return Err(FaceError::Input("the image is empty".into()));
        }
        let (x, roi) = warp::letterbox(img, self.size, -1.0, 1.0);
        let raw = self.raw(&x);
        let dets = decode(&raw, &self.anchors, self.size as f32, self.min_score);
        let dets = weighted_nms(dets, NMS_IOU);
        Ok(dets
            .into_iter()
            .map(|d| project(&d, &roi, img.width(), img.height()))
            .collect())
    }
}

/// Boxes and keypoints from the raw outputs (`TensorsToDetectionsCalculator`, reverse output
/// order: x before y), in tensor-normalised coordinates, in anchor order.
pub fn decode(
    raw: &RawDetections,
    anchors: &[Anchor],
    scale: f32,
    min_score: f32,
) -> Vec<Detection> {
    let mut out = Vec::new();
    for (i, a) in anchors.iter().enumerate() {
        let r = &raw.regressors[i * 16..(i + 1) * 16];
        let logit = raw.logits[i].clamp(-SCORE_CLIP, SCORE_CLIP);
        let score = 1.0f32 / (1.0f32 + (-logit).exp());
        if score < min_score {
            continue;
        }
        let xc = r[0] / scale + a.x;
        let yc = r[1] / scale + a.y;
        let w = r[2] / scale;
        let h = r[3] / scale;
        let (ymin, xmin, ymax, xmax) = (yc - h / 2.0, xc - w / 2.0, yc + h / 2.0, xc + w / 2.0);
        let (width, height) = (xmax - xmin, ymax - ymin);
        if !(width >= 0.0 && height >= 0.0) {
            continue;
        }
        let keypoints =
            std::array::from_fn(|k| [r[4 + 2 * k] / scale + a.x, r[5 + 2 * k] / scale + a.y]);
        out.push(Detection {
            score,
            xmin,
            ymin,
            width,
            height,
            keypoints,
        });
    }
    out
}

/// Intersection over union of two boxes (MediaPipe's `Rectangle_f`, edges included).
pub fn iou(a: &Detection, b: &Detection) -> f32 {
    let (ax1, ay1) = (a.xmin + a.width, a.ymin + a.height);
    let (bx1, by1) = (b.xmin + b.width, b.ymin + b.height);
    let empty = |x0: f32, y0: f32, x1: f32, y1: f32| x0 > x1 || y0 > y1;
    if empty(a.xmin, a.ymin, ax1, ay1)
        || empty(b.xmin, b.ymin, bx1, by1)
        || bx1 < a.xmin
        || ax1 < b.xmin
        || by1 < a.ymin
        || ay1 < b.ymin
    {
        return 0.0;
    }
    let (ix0, iy0) = (a.xmin.max(b.xmin), a.ymin.max(b.ymin));
    let (ix1, iy1) = (ax1.min(bx1), ay1.min(by1));
    let inter = (ix1 - ix0) * (iy1 - iy0);
    let union = a.width * a.height + b.width * b.height - inter;
    if union > 0.0 {
        inter / union
    } else {
        0.0
    }
}

/// MediaPipe's weighted non-maximum suppression: take the best remaining detection, average
/// the corners and keypoints of every remaining box overlapping it by more than `threshold`
/// (itself included) weighted by score, keep the best score; repeat.
pub fn weighted_nms(mut dets: Vec<Detection>, threshold: f32) -> Vec<Detection> {
    // Stable, so equal scores keep anchor order.
    dets.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut out = Vec::new();
    let mut remaining = dets;
    while !remaining.is_empty() {
        let top = remaining[0].clone();
        let (cluster, rest): (Vec<Detection>, Vec<Detection>) = remaining
            .into_iter()
            .partition(|d| iou(d, &top) > threshold);
        let mut merged = top;
        if !cluster.is_empty() {
            let (mut x0, mut y0, mut x1, mut y1, mut total) =
                (0.0f32, 0.0f32, 0.0f32, 0.0f32, 0.0f32);
            let mut kps = [[0.0f32; 2]; 6];
            for c in &cluster {
                total += c.score;
                x0 += c.xmin * c.score;
                y0 += c.ymin * c.score;
                x1 += (c.xmin + c.width) * c.score;
                y1 += (c.ymin + c.height) * c.score;
                for (k, kp) in kps.iter_mut().enumerate() {
                    kp[0] += c.keypoints[k][0] * c.score;
                    kp[1] += c.keypoints[k][1] * c.score;
                }
            }
            merged.xmin = x0 / total;
            merged.ymin = y0 / total;
            merged.width = x1 / total - merged.xmin;
            merged.height = y1 / total - merged.ymin;
            merged.keypoints = kps.map(|[x, y]| [x / total, y / total]);
        }
        out.push(merged);
        // A degenerate box does not even overlap itself; MediaPipe stops there.
        if cluster.is_empty() {
            break;
        }
        remaining = rest;
    }
    out
}

/// Maps a detection from the letterboxed tensor into the image (`DetectionProjectionCalculator`
/// with the matrix of `GetRotatedSubRectToRectTransformMatrix`, rotation 0).
pub fn project(d: &Detection, roi: &RotatedRect, w: u32, h: u32) -> Detection {
    let (a, b) = (roi.w, roi.h);
    let (c, s) = (roi.rotation.cos(), roi.rotation.sin());
    let (g, hh) = (1.0f32 / w as f32, 1.0f32 / h as f32);
    let m = [
        a * c * g,
        -b * s * g,
        (-0.5f32 * a * c + 0.5f32 * b * s + roi.cx) * g,
        a * s * hh,
        b * c * hh,
        (-0.5f32 * b * c - 0.5f32 * a * s + roi.cy) * hh,
    ];
    let pr = |x: f32, y: f32| [x * m[0] + y * m[1] + m[2], x * m[3] + y * m[4] + m[5]];
    let (x1, y1) = (d.xmin + d.width, d.ymin + d.height);
    let corners = [
        pr(d.xmin, d.ymin),
        pr(x1, d.ymin),
        pr(x1, y1),
        pr(d.xmin, y1),
    ];
    let (mut lx, mut ly, mut rx, mut ry) = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
    for p in corners {
        lx = lx.min(p[0]);
        ly = ly.min(p[1]);
        rx = rx.max(p[0]);
        ry = ry.max(p[1]);
    }
    Detection {
        score: d.score,
        xmin: lx,
        ymin: ly,
        width: rx - lx,
        height: ry - ly,
        keypoints: d.keypoints.map(|[x, y]| pr(x, y)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn det(score: f32, x: f32, y: f32, s: f32) -> Detection {
        Detection {
            score,
            xmin: x,
            ymin: y,
            width: s,
            height: s,
            keypoints: [[x, y]; 6],
        }
    }

    #[test]
    fn weighted_nms_merges_by_score() {
        let d = vec![
            det(0.6, 0.1, 0.1, 0.2),
            det(0.9, 0.12, 0.1, 0.2),
            det(0.8, 0.7, 0.7, 0.1),
        ];
        let out = weighted_nms(d, 0.3);
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].score, 0.9);
        let want = (0.1 * 0.6 + 0.12 * 0.9) / 1.5;
        assert!(
            (out[0].xmin - want).abs() < 1e-6,
            "{} vs {want}",
            out[0].xmin
        );
        assert_eq!(out[1].score, 0.8);
        assert_eq!(out[1].xmin, 0.7);
    }

    #[test]
    fn iou_cases() {
        let a = det(1.0, 0.0, 0.0, 1.0);
        assert_eq!(iou(&a, &a), 1.0);
        assert_eq!(iou(&a, &det(1.0, 2.0, 2.0, 1.0)), 0.0);
        let b = det(1.0, 0.5, 0.0, 1.0);
        assert!((iou(&a, &b) - 1.0 / 3.0).abs() < 1e-6);
    }

    #[test]
    fn projection_undoes_the_letterbox() {
        // A 200x100 image letterboxed into a square: tensor y 0.25..0.75 covers the image.
        let roi = warp::letterbox_rect(200, 100);
        let d = det(1.0, 0.0, 0.25, 0.5);
        let p = project(&d, &roi, 200, 100);
        assert!(
            (p.ymin - 0.0).abs() < 1e-6 && (p.height - 1.0).abs() < 1e-6,
            "{p:?}"
        );
        assert!(
            (p.xmin - 0.0).abs() < 1e-6 && (p.width - 0.5).abs() < 1e-6,
            "{p:?}"
        );
    }
}
