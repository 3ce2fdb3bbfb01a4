//! Training on the GPU, the first pieces of `train --device gpu`: the gradients of a
//! convolution (input, weight, bias), of the activations, resizes and normalisations, of a
//! modulated convolution with its style, the Adam update, and with them the whole neural
//! renderer's training forward and backward ([`renderer::GpuRendererGrad`]: U-Net, condition
//! branches, StyleGAN2 decoder, sigmoid), checked against candle's autograd.
//!
//! `train --device gpu` runs [`render_half::GpuRenderHalf`]: each sample's splatting, renderer,
//! image and perceptual terms, lifting generators ([`lift::GpuLiftGrad`]) and, with a frozen
//! backbone, DPT head ([`dpt::GpuDptGrad`]), forward and backward, behind `gagavatar_train`'s
//! `RenderHalf`, with the lifting term; the expression generator and Adam stay on the CPU for now
//! (the split step's gradients are checked against the CPU step's in `render_half_tests`).
//!
//! They are recorded [`Step`](crate::kernel::Step)s like the forward's, and they reuse the
//! forward's kernels where the mathematics allows: a stride-1 convolution's input gradient is
//! the same convolution of the output gradient with the weight's channels swapped and its
//! kernel rotated ([`conv::ConvGrad`]), so it runs on the forward's f32 or tensor-core kernels.
//! Sums over pixels are split into slices that a second kernel adds in a fixed order, so a
//! gradient does not depend on how the device schedules its workgroups (the multi-rank
//! trajectory test needs every rank's gradients to be reproducible).

pub mod conv;
pub mod crop;
pub mod decoder;
pub mod dpt;
pub mod image_loss;
pub mod layers;
pub mod lift;
pub mod lifting;
pub mod modconv;
pub mod optim;
pub mod params;
pub mod perceptual;
pub mod render_half;
pub mod render_step;
pub mod renderer;
pub mod splat;

#[cfg(test)]
mod tests;

#[cfg(test)]
pub(crate) mod renderer_tests;

#[cfg(test)]
mod splat_tests;

#[cfg(test)]
mod lift_tests;

#[cfg(test)]
mod dpt_tests;

#[cfg(test)]
mod render_half_tests;
