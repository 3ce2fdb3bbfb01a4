//! The paper's evaluation metrics and protocol (the README's "Evaluation protocol"):
//! realignment ([`realign`]), AKD ([`akd`]), AED / APD ([`expression_pose`]), the pairs
//! ([`protocol`]), the per-pair scorer ([`scorer`]) and the CSV / JSON report ([`report`]).
//! PSNR, SSIM and LPIPS are the training crate's validation metrics, applied by the caller to
//! the realigned images.
//!
//! CSIM, the cosine similarity of face-identity
//! descriptors, computed with dlib's public-domain face-recognition ResNet on dlib's aligned
//! 150x150 face chips (5-point landmarks from dlib's public-domain shape predictor), matching
//! dlib 20's own results.
//!
//! ```no_run
//! use gagavatar_metrics::{default_asset_dir, FaceRect, IdentityNet};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let net = IdentityNet::load(&default_asset_dir())?;
//! let a = image::open("a.png")?.to_rgb8();
//! let b = image::open("b.png")?.to_rgb8();
//! // Face rectangles from a detector (inclusive pixel sides, dlib's convention).
//! let ea = net.embed(&a, FaceRect::new(86, 76, 175, 166)?)?;
//! let eb = net.embed(&b, FaceRect::new(80, 70, 170, 160)?)?;
//! println!("CSIM {:.4}", ea.cosine(&eb)?);
//! # Ok(()) }
//! ```
//!
//! Models: `assets/identity/` (converted from the PyPI package `face_recognition_models`
//! 0.3.0 by `tools/identity/convert_dlib.py`; see the README there).

pub mod akd;
pub mod align;
pub mod arcface;
pub mod error;
pub mod expression_pose;
pub mod geometry;
pub mod identity;
pub mod protocol;
pub mod realign;
pub mod report;
pub mod scorer;
pub mod shape_predictor;
pub mod weights;

pub use akd::{akd, ibug68, keypoint_distance, AKD_POINTS};
pub use align::{extract_image_chip, face_chip_details, ChipDetails, CHIP_PADDING, CHIP_SIZE};
pub use error::{MetricsError, Result};
pub use expression_pose::{aed, apd, ExpressionPose, PoseEstimator};
pub use geometry::{DRect, FaceRect};
pub use identity::{csim, AlignedFace, Embedding, FaceResNet, IdentityNet, EMBEDDING_DIM};
pub use protocol::{cross_pairs, self_pairs, EvalPair, Mode};
pub use realign::{Realignment, REALIGN_SIZE};
pub use report::PairRow;
pub use scorer::{FaceScorer, IdentityModel, SourceFace};
pub use shape_predictor::{IntensityImage, Landmarks5, ShapePredictor, MIN_FACE_SIDE};
pub use weights::{default_asset_dir, ASSET_DIR, RESNET_FILE, SHAPE_PREDICTOR_FILE};
