//! Tracking a photo or a video into the release's FLAME + camera records (TRACKING.md sections
//! 1-7), from face landmarks: no learned piece beyond the landmark detector.
//!
//! Stages, one per module:
//! * [`observation`]: the input, per frame the image size and optional 478 (or 468) MediaPipe
//!   landmarks in frame pixels;
//! * [`mapping`]: MediaPipe points to the 70-point `_with_eye` set (iBUG 68 + pupils);
//! * [`crop`]: the release's 512 crop around a head box, the head box estimated from landmarks,
//!   stable video windows, the crop itself and the matte composite;
//! * [`rig`] and [`camera`]: FLAME's 70 landmarks and the release camera with analytic
//!   derivatives;
//! * [`fit`]: Levenberg-Marquardt fits of shape, expression, jaw, eyes and camera (photo; video
//!   with one shape per video and warm starts);
//! * [`smooth`]: the release's causal EMA and the default offline (two-sided) smoother;
//! * [`pipeline`]: `track_photo` / `track_video`, tying the stages together;
//! * [`output`]: the release layout (`img_lmdb/`, `optim.pkl`, `smoothed.pkl`) plus `track.json`;
//! * [`overlay`]: a picture of a fit (mesh, detected and fitted landmarks, crop window).
//!
//! 2D points everywhere use the continuous pixel convention of PyTorch3D's screen space and
//! MediaPipe's normalised coordinates times the image size: the image's top-left corner is at
//! (0, 0) and pixel `(row i, column j)` is centred at `(j + 0.5, i + 0.5)`.

// Index loops follow the matrix maths; `!(x > 0.0)` is meant to reject NaN too.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

pub mod camera;
pub mod crop;
pub mod error;
pub mod fit;
mod linalg;
pub mod mapping;
pub mod observation;
pub mod output;
pub mod overlay;
pub mod pipeline;
pub mod rig;
pub mod smooth;

pub use camera::CameraPose;
pub use crop::{CropWindow, FramingCalibration, HeadBox};
pub use error::{Result, TrackError};
pub use fit::{FitOptions, FrameFit};
pub use observation::{FaceLandmarks, Observation};
pub use pipeline::{
    track_photo, track_video, FrameTrack, LiveTrack, TrackOptions, TrackedPhoto, TrackedVideo,
};
pub use rig::{FaceCodes, LandmarkRig};
