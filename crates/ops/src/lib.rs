//! CPU kernels the network needs that candle lacks or runs slowly, each a differentiable op:
//! 2-D convolution (`conv`) and separable resampling (`resample`).

pub mod conv;
pub mod resample;

pub use conv::{conv2d, conv2d_with_algo, Conv2dSpec, ConvAlgo};
pub use resample::{resize, ResizeMode};
