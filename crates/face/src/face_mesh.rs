//! MediaPipe's FaceMesh with refined landmarks (478 points), for photos and for video (spec
//! TRACKING.md section 10):
//!
//! - [`FaceLandmarker`]: the attention mesh on one ROI: crop (rotated square, border
//!   replicate, [0, 1]), network, face flag, the 478 points refined and projected back into
//!   the image.
//! - [`FaceMesh`]: photos: short-range detection, then landmarks on each detection's ROI.
//! - [`FaceTracker`]: video: the ROI comes from the previous frame's landmarks; the detector
//!   runs only when there is no previous face (first frame, or the face flag dropped).

use image::RgbImage;

use crate::detection::{Detection, DetectorModel, FaceDetector};
use crate::mesh_net::{AttentionMeshNet, MeshOutputs, LEFT_EYE, LIPS, RIGHT_EYE};
use crate::roi::{self, NormRect};
use crate::warp::{self, Border};
use crate::weights::{bundled, WeightsFile};
use crate::FaceError;

/// Number of landmarks: the 468-point mesh plus 5 per iris.
pub const NUM_LANDMARKS: usize = 478;
/// Landmark crop size.
const CROP: usize = 192;
/// Mesh points whose mean depth the iris points take (lower and upper contour of each eye).
const LEFT_IRIS_DEPTH: [usize; 16] = [
    33, 7, 163, 144, 145, 153, 154, 155, 133, 246, 161, 160, 159, 158, 157, 173,
];
const RIGHT_IRIS_DEPTH: [usize; 16] = [
    263, 249, 390, 373, 374, 380, 381, 382, 362, 466, 388, 387, 386, 385, 384, 398,
];

/// 478 landmarks in normalised image coordinates: x, y in 0..1 of the width and height, z in
/// the same unit as x (negative toward the camera). Points 468 and 473 are the iris centres
/// (468: the eye with corners 33/133, the subject's right, image left).
pub type Landmarks = Vec<[f32; 3]>;

/// One face found in an image.
#[derive(Debug, Clone)]
pub struct Face {
    /// The detection the landmarks were placed from (`None` in tracking frames that reused
    /// the previous landmarks instead of detecting).
    pub detection: Option<Detection>,
    /// The ROI the landmark model saw.
    pub roi: NormRect,
    /// Face presence from the landmark model (sigmoid of its flag).
    pub presence: f32,
    /// The 478 landmarks, normalised.
    pub landmarks: Landmarks,
}

impl Face {
    /// Landmarks in pixels of a `w x h` image: (x, y, z) with x = normalised x times the
    /// width, y times the height, z times the width.
    pub fn landmarks_pixels(&self, w: u32, h: u32) -> Vec<[f32; 3]> {
        let (w, h) = (w as f32, h as f32);
        self.landmarks
            .iter()
            .map(|p| [p[0] * w, p[1] * h, p[2] * w])
            .collect()
    }
}

/// The landmark model with its decoding.
#[derive(Debug, Clone)]
pub struct FaceLandmarker {
    net: AttentionMeshNet,
    /// A face counts as present when the flag's probability is above this (MediaPipe's
    /// `min_tracking_confidence`, default 0.5).
    pub min_presence: f32,
}

impl FaceLandmarker {
    /// The model with the weights shipped in this crate.
    pub fn new() -> Result<Self, FaceError> {
        Self::from_weights(WeightsFile::from_bytes(
            bundled::FACE_LANDMARK_WITH_ATTENTION,
            "face_landmark_with_attention.safetensors",
        )?)
    }

    pub fn from_weights(file: WeightsFile) -> Result<Self, FaceError> {
        Ok(FaceLandmarker {
            net: file.build("face_landmark_with_attention", AttentionMeshNet::new)?,
            min_presence: 0.5,
        })
    }

    /// Raw outputs for the crop of `roi`.
    pub fn raw(&self, img: &RgbImage, roi: &NormRect) -> MeshOutputs {
        let r = roi.to_pixels(img.width(), img.height());
        let crop = warp::warp_u8(img, &r, CROP, CROP, Border::Replicate);
        self.net
            .forward(&warp::to_tensor(&crop, CROP, CROP, 0.0, 1.0))
    }

    /// Presence probability and, when the face is present, the 478 normalised landmarks.
    pub fn landmarks(&self, img: &RgbImage, roi: &NormRect) -> (f32, Option<Landmarks>) {
        let out = self.raw(img, roi);
        let presence = 1.0f32 / (1.0f32 + (-out.face_flag).exp());
        // MediaPipe's ThresholdingCalculator: accept when strictly above, compared in f64.
        if presence as f64 <= self.min_presence as f64 {
            return (presence, None);
        }
        (presence, Some(project(&refine(&out), roi)))
    }
}

/// The 478 points in crop-normalised coordinates (`TensorsToFaceLandmarksWithAttention`): the
/// mesh, the lip and eye points written over their mesh points' x and y, the irises appended
/// with the mean depth of their eye's contour.
pub fn refine(out: &MeshOutputs) -> Landmarks {
    let s = CROP as f32;
    let mut lm: Landmarks = out
        .mesh
        .chunks_exact(3)
        .map(|p| [p[0] / s, p[1] / s, p[2] / s])
        .collect();
    for (idx, pts) in [
        (&LIPS[..], &out.lips),
        (&LEFT_EYE[..], &out.left_eye),
        (&RIGHT_EYE[..], &out.right_eye),
    ] {
        for (&i, p) in idx.iter().zip(pts.chunks_exact(2)) {
            lm[i][0] = p[0] / s;
            lm[i][1] = p[1] / s;
        }
    }
    for (pts, depth) in [
        (&out.left_iris, &LEFT_IRIS_DEPTH),
        (&out.right_iris, &RIGHT_IRIS_DEPTH),
    ] {
        let mut z = 0.0f32;
        for &i in depth.iter() {
            z += lm[i][2];
        }
        let z = z / depth.len() as f32;
        for p in pts.chunks_exact(2) {
            lm.push([p[0] / s, p[1] / s, z]);
        }
    }
    lm
}

/// Crop-normalised points to image-normalised ones (`LandmarkProjectionCalculator`).
pub fn project(lm: &[[f32; 3]], roi: &NormRect) -> Landmarks {
    let (c, s) = (roi.rotation.cos(), roi.rotation.sin());
    lm.iter()
        .map(|p| {
            let (x, y) = (p[0] - 0.5f32, p[1] - 0.5f32);
            let nx = c * x - s * y;
            let ny = s * x + c * y;
            [
                nx * roi.width + roi.x_center,
                ny * roi.height + roi.y_center,
                p[2] * roi.width,
            ]
        })
        .collect()
}

/// Face landmarks for photos: every face the short-range detector finds (up to a maximum),
/// landmarked on its ROI.
#[derive(Debug, Clone)]
pub struct FaceMesh {
    pub detector: FaceDetector,
    pub landmarker: FaceLandmarker,
}

impl FaceMesh {
    /// The shipped models (the short-range detector, as MediaPipe's FaceMesh uses).
    pub fn new() -> Result<Self, FaceError> {
        Ok(FaceMesh {
            detector: FaceDetector::new(DetectorModel::ShortRange)?,
            landmarker: FaceLandmarker::new()?,
        })
    }

    /// Faces of a photo, in detection order (best first), at most `max_faces`; detections
    /// whose landmark face flag fails are left out, as in MediaPipe.
    pub fn process(&self, img: &RgbImage, max_faces: usize) -> Result<Vec<Face>, FaceError> {
        let dets = self.detector.detect(img)?;
        Ok(self.landmark_detections(img, dets, max_faces))
    }

    /// Landmarks for given detections (e.g. from the full-range detector).
    pub fn landmark_detections(
        &self,
        img: &RgbImage,
        dets: Vec<Detection>,
        max_faces: usize,
    ) -> Vec<Face> {
        let (w, h) = (img.width(), img.height());
        dets.into_iter()
            .take(max_faces)
            .filter_map(|d| {
                let roi = roi::from_detection(&d, w, h);
                let (presence, lm) = self.landmarker.landmarks(img, &roi);
                lm.map(|landmarks| Face {
                    detection: Some(d),
                    roi,
                    presence,
                    landmarks,
                })
            })
            .collect()
    }
}

/// Face landmarks for video, one face, as MediaPipe's FaceMesh in tracking mode
/// (`static_image_mode=False`, `max_num_faces=1`): the detector runs on the first frame and
/// whenever the previous frame lost the face; otherwise the ROI is the previous frame's
/// landmarks' (bounding box, eye-corner rotation, squared, x1.5).
#[derive(Debug, Clone)]
pub struct FaceTracker {
    mesh: FaceMesh,
    previous: Option<NormRect>,
}

impl FaceTracker {
    pub fn new() -> Result<Self, FaceError> {
        Ok(Self::with_models(FaceMesh::new()?))
    }

    pub fn with_models(mesh: FaceMesh) -> Self {
        FaceTracker {
            mesh,
            previous: None,
        }
    }

    /// The face in the next frame, or `None` when there is none (the next frame then runs
    /// the detector).
    pub fn process(&mut self, img: &RgbImage) -> Result<Option<Face>, FaceError> {
        let (w, h) = (img.width(), img.height());
        if w == 0 || h == 0 {
            return Err(FaceError::Input("the frame is empty".into()));
        }
        let (roi, detection) = match self.previous.take() {
            Some(r) => (r, None),
            None => match self.mesh.detector.detect(img)?.into_iter().next() {
                Some(d) => (roi::from_detection(&d, w, h), Some(d)),
                None => return Ok(None),
            },
        };
        let (presence, lm) = self.mesh.landmarker.landmarks(img, &roi);
        Ok(lm.map(|landmarks| {
            self.previous = Some(roi::from_landmarks(&landmarks, w, h));
            Face {
                detection,
                roi,
                presence,
                landmarks,
            }
        }))
    }

    /// Forgets the previous face (a cut in the video): the next frame detects.
    pub fn reset(&mut self) {
        self.previous = None;
    }

    /// Whether the next frame reuses the previous landmarks instead of detecting.
    pub fn is_tracking(&self) -> bool {
        self.previous.is_some()
    }
}
