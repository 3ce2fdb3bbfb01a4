//! Face perception (placeholder docs, rewritten below).

pub mod anchors;
pub mod detection;
pub mod detection_net;
pub mod error;
pub mod face_mesh;
pub mod kernels;
pub mod layers;
pub mod matte;
pub mod mesh_net;
pub mod overlay;
pub mod pool;
pub mod roi;
pub mod selfie_net;
pub mod simd;
pub mod tensor;
pub mod warp;
pub mod weights;

pub use error::FaceError;
