//! FLAME head model (spec section 9): loading the release asset (`FLAME_with_eye.pt`, or the same
//! keys in safetensors), the differentiable forward pass, landmarks and their projection, and a
//! synthetic stand-in asset with the release's exact layout.

pub mod asset;
pub mod embedding;
pub mod error;
pub mod landmarks;
pub mod lbs;
pub mod record;
pub mod rodrigues;
pub mod skinning;
pub mod synth;

pub use asset::{BasisLayout, FlameAsset, LoadOptions};
pub use error::{FlameError, Result};
pub use landmarks::{project_point, project_points, LandmarkEmbedding, Landmarks};
pub use lbs::{FlameConfig, FlameIdentity, FlameModel, FlameOutput, FlameParams, FLAME_SCALE};
pub use record::TrackedFrame;
pub use rodrigues::rodrigues;
pub use synth::{synthesize, synthesize_with, BasisMotion};
