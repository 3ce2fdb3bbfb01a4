//! CPU kernels the network needs that candle lacks or runs slowly, each a differentiable op:
//! 2-D convolution (`conv`) and separable resampling (`resample`).

pub mod conv;
pub mod resample;

pub use conv::{conv2d, Conv2dSpec};
pub use resample::{resize, ResizeMode};
