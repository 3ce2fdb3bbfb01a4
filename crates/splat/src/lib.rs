//! Differentiable many-channel 3D Gaussian splatting on the CPU, as specified in section 7 of
//! `GAGAVATAR.md`: the release's 3DGS rasterizer (16x16 tiles, EWA projection with dilation,
//! unnormalised quaternions, early termination) with an exact backward, exposed as a candle op.

pub mod binning;
pub mod camera;
pub mod error;
pub mod project;
pub mod raster;
pub mod real;
pub mod scene;
pub mod splat;
pub mod testscene;

pub use camera::Camera;
pub use error::{Result, SplatError};
pub use scene::GaussianScene;
pub use splat::{splat, Gaussians, SplatOutput};
