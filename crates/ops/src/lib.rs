//! CPU kernels the network needs that candle lacks or runs slowly: 2-D convolution (`conv`) and
//! separable resampling (`resample`), each a differentiable op; the ViT's fused inference
//! kernels (`vit`: layer norm, attention, GELU, softmax); the renderer's fused element-wise
//! epilogues (`epilogue`); and bf16 products with f32 sums for `--precision bf16` (`bf16`, and
//! `conv::Bf16Conv`).

pub mod bf16;
pub mod conv;
pub mod epilogue;
pub mod resample;
mod storage;
pub mod vit;

pub use bf16::Precision;
pub use conv::{conv2d, conv2d_with_algo, Conv2dSpec, ConvAlgo};
pub use resample::{resize, ResizeMode};
