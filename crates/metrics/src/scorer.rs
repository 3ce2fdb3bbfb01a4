//! The face-based scores of one pair: realignment, CSIM, AED, APD and AKD (the README's
//! "Evaluation protocol"). PSNR, SSIM and LPIPS are computed by the caller on the realigned
//! images this returns (they live with the training code's validation metrics).
//!
//! Per pair:
//! 1. the reference (target / driver) gets its crop ([`crate::realign`]); result and reference
//!    are cut to it at 512;
//! 2. MediaPipe's landmarks on both realigned images;
//! 3. CSIM = cosine of the identity descriptors of the realigned result and of the source
//!    (the source realigned on its own face, [`FaceScorer::source`]): dlib's ResNet by
//!    default (the face rectangle given to dlib's 5-point predictor is the bounding box of the
//!    face's 68 iBUG points), or a user's ArcFace ONNX model ([`crate::arcface`]);
//! 4. AED / APD from the tracker's photo fits of the result and the reference
//!    ([`crate::expression_pose`]);
//! 5. AKD between the two faces' 68 points (self reenactment only: it needs ground truth).
//!
//! A face that is not found leaves its scores empty (`None`) instead of failing the run.

use gagavatar_face::face_mesh::FaceMesh;
use gagavatar_track::crop::FramingCalibration;
use gagavatar_track::observation::FaceLandmarks;
use gagavatar_track::pipeline::TrackOptions;
use gagavatar_track::rig::LandmarkRig;
use image::RgbImage;

use crate::akd::{akd, ibug68};
use crate::arcface::{cosine, ArcFace};
use crate::error::{input_err, Result};
use crate::expression_pose::{aed, apd, PoseEstimator};
use crate::geometry::FaceRect;
use crate::identity::IdentityNet;
use crate::protocol::Mode;
use crate::realign::{detect_landmarks, Realignment};
use crate::report::PairRow;

/// The source photo as CSIM needs it.
#[derive(Debug, Clone)]
pub struct SourceFace {
    /// `None`: no face found on the source.
    pub embedding: Option<Vec<f32>>,
}

/// The network CSIM uses.
#[derive(Debug)]
pub enum IdentityModel {
    /// dlib's face-recognition ResNet (shipped, public domain).
    Dlib(IdentityNet),
    /// A user's ArcFace ONNX model (the paper's choice).
    ArcFace(ArcFace),
}

impl IdentityModel {
    pub fn name(&self) -> &'static str {
        match self {
            IdentityModel::Dlib(_) => "dlib face-recognition ResNet v1",
            IdentityModel::ArcFace(_) => "ArcFace (user ONNX model)",
        }
    }
}

/// One image after realignment: the 512 crop and its face, if any.
#[derive(Debug, Clone)]
pub struct RealignedFace {
    pub image: RgbImage,
    pub landmarks: Option<FaceLandmarks>,
}

/// The realigned pair and where its crop came from.
#[derive(Debug, Clone)]
pub struct RealignedPair {
    pub realignment: Realignment,
    pub result: RealignedFace,
    pub reference: RealignedFace,
}

/// The models the face-based scores need; `Sync`, so pairs are scored in parallel.
#[derive(Debug)]
pub struct FaceScorer {
    mesh: FaceMesh,
    identity: IdentityModel,
    pose: PoseEstimator,
    framing: FramingCalibration,
}

/// dlib's face rectangle for a face: the bounding box of its 68 iBUG points.
pub fn face_rect(lm: &FaceLandmarks) -> Result<FaceRect> {
    let p = ibug68(lm);
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for q in &p {
        x0 = x0.min(q[0]);
        y0 = y0.min(q[1]);
        x1 = x1.max(q[0]);
        y1 = y1.max(q[1]);
    }
    FaceRect::from_box(x0, y0, x1, y1)
}

impl FaceScorer {
    /// `rig`: the tracker's landmark rig of the FLAME asset the poses are fitted with.
    pub fn new(identity: IdentityModel, rig: LandmarkRig) -> Result<Self> {
        let mesh = FaceMesh::new().map_err(|e| input_err("face models", e.to_string()))?;
        Ok(Self {
            mesh,
            identity,
            framing: TrackOptions::default().framing,
            pose: PoseEstimator::for_metrics(rig),
        })
    }

    pub fn mesh(&self) -> &FaceMesh {
        &self.mesh
    }

    pub fn identity(&self) -> &IdentityModel {
        &self.identity
    }

    pub fn pose(&self) -> &PoseEstimator {
        &self.pose
    }

    /// The descriptor of a face in a realigned image, `None` without a face or when the
    /// alignment fails on it.
    pub fn embed(&self, face: &RealignedFace) -> Option<Vec<f32>> {
        let lm = face.landmarks.as_ref()?;
        match &self.identity {
            IdentityModel::Dlib(net) => {
                let rect = face_rect(lm).ok()?;
                Some(net.embed(&face.image, rect).ok()?.unit().ok()?.to_vec())
            }
            IdentityModel::ArcFace(net) => net.embed(&face.image, lm).ok(),
        }
    }

    /// The source realigned on its own face, and its descriptor.
    pub fn source(&self, img: &RgbImage) -> Result<SourceFace> {
        let r = Realignment::detect(&self.mesh, &self.framing, img)?;
        let image = r.apply(img, img.dimensions())?;
        let landmarks = detect_landmarks(&self.mesh, &image)?;
        Ok(SourceFace {
            embedding: self.embed(&RealignedFace { image, landmarks }),
        })
    }

    /// Result and reference cut to the reference's crop, with their landmarks.
    pub fn realign(&self, result: &RgbImage, reference: &RgbImage) -> Result<RealignedPair> {
        let realignment = Realignment::detect(&self.mesh, &self.framing, reference)?;
        let size = reference.dimensions();
        let mut out = Vec::with_capacity(2);
        for img in [result, reference] {
            let image = realignment.apply(img, size)?;
            let landmarks = detect_landmarks(&self.mesh, &image)?;
            out.push(RealignedFace { image, landmarks });
        }
        let reference = out.pop().ok_or_else(|| input_err("pair", "realignment"))?;
        let result = out.pop().ok_or_else(|| input_err("pair", "realignment"))?;
        Ok(RealignedPair {
            realignment,
            result,
            reference,
        })
    }

    /// Fills the face-based scores of `row` (CSIM, AED, APD, and AKD for self reenactment)
    /// and returns the realigned images for the pixel metrics.
    pub fn score(
        &self,
        source: &SourceFace,
        result: &RgbImage,
        reference: &RgbImage,
        row: &mut PairRow,
    ) -> Result<RealignedPair> {
        let pair = self.realign(result, reference)?;
        row.realigned = pair.realignment.from_landmarks;
        row.result_face = pair.result.landmarks.is_some();
        if let (Some(s), Some(r)) = (&source.embedding, self.embed(&pair.result)) {
            row.csim = cosine(s, &r).ok();
        }
        if let (Some(lr), Some(lt)) = (&pair.result.landmarks, &pair.reference.landmarks) {
            let (w, h) = pair.result.image.dimensions();
            // A fit that fails (a degenerate face) leaves AED / APD empty for the pair.
            if let (Ok(a), Ok(b)) = (self.pose.estimate(lr, w, h), self.pose.estimate(lt, w, h)) {
                row.aed = Some(aed(&a, &b));
                row.apd = Some(apd(&a, &b));
            }
            if row.pair.mode == Mode::SelfReenactment {
                row.akd = akd(lr, lt).ok();
            }
        }
        Ok(pair)
    }
}
