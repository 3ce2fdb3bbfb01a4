//! CPU kernels the network needs that candle lacks or runs slowly, each a differentiable op:
//! 2-D convolution (`conv`) and separable resampling (`resample`); and the ViT's fused inference
//! kernels (`vit`: layer norm, attention, GELU, softmax).

pub mod conv;
pub mod resample;
mod storage;
pub mod vit;

pub use conv::{conv2d, conv2d_with_algo, Conv2dSpec, ConvAlgo};
pub use resample::{resize, ResizeMode};
