//! Differentiable many-channel 3D Gaussian splatting on the CPU, as specified in section 7 of
//! `GAGAVATAR.md`: the release's 3DGS rasterizer (16x16 tiles, EWA projection with dilation,
//! unnormalised quaternions, early termination) with an exact backward, exposed as a candle op.

// Index loops mirror the matrix algebra of the spec; negated float comparisons are deliberate so
// that NaN takes the "skip" branch.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

pub mod binning;
pub mod camera;
pub mod error;
pub mod lanes;
pub mod params;
pub mod project;
pub mod raster;
pub mod real;
pub mod rng;
pub mod scene;
pub mod splat;
pub mod testscene;

pub use camera::Camera;
pub use error::{Result, SplatError};
pub use scene::GaussianScene;
pub use splat::{splat, Gaussians, SplatOutput};
