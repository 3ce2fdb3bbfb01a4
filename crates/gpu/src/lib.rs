//! The GAGAvatar drive step on a GPU (wgpu + WGSL): FLAME skinning, splatting and the neural
//! renderer, with the avatar uploaded once. Every kernel is compared with the CPU path in the
//! tests, which run on any Vulkan device, a CPU-emulated one (lavapipe) included.

pub mod conv;
pub mod device;
pub mod drive;
pub mod error;
pub mod flame;
pub mod grad;
pub mod kernel;
pub mod pipelines;
pub mod policy;
pub mod reconstruct;
pub mod renderer;
pub mod sort;
pub mod splat;
pub mod tuning;

#[cfg(test)]
pub(crate) mod testutil;

pub use device::{AdapterPolicy, Gpu};
pub use error::{GpuError, Result};
pub use tuning::{GpuPrecision, Tuning};
/// The wgpu this crate is built on (its feature and adapter types appear in [`Gpu`]).
pub use wgpu;
