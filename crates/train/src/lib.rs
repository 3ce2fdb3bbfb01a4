//! Numeric building blocks of GAGAvatar training (spec section 11), each self-contained and
//! device-agnostic (tensors stay on the device they come from; only the nearest-neighbour
//! search and the validation metrics read values back to the host):
//!
//! - [`losses`]: the release's loss `img + box + percep + point`;
//! - [`head_box`](mod@head_box): the target's head box and the differentiable crop-and-resize;
//! - [`nearest`]: exact nearest neighbours (k-d tree) and the lifting-distance loss;
//! - [`perceptual`]: the frozen AlexNet + VGG-Face perceptual distance (`percep_loss.*`);
//! - [`adam`]: Adam with the release's parameter groups and linear learning-rate decay;
//! - [`metrics`]: validation PSNR and SSIM;
//! - [`lpips`](mod@lpips): the LPIPS v0.1 (AlexNet) evaluation metric;
//! - [`kernels`]: the fused CPU ops of the perceptual network (max-pool, ReLU, layer distance).
//!
//! and the training itself:
//!
//! - [`config`]: the TOML training configuration (`configs/tiny.toml`, `configs/release.toml`);
//! - [`pairs`]: training and evaluation pairs, sample loading, the prefetching loader;
//! - [`render_half`]: the interface of a device that runs the step's rendering half
//!   (`train --device gpu`);
//! - [`trainer`]: the step ([`TrainState`]), the NaN guard, the run folder ([`Run`]): logging,
//!   validation, checkpoints and resume;
//! - [`ckpt`]: the checkpoint file and the run folder's file names;
//! - [`eval`]: PSNR / SSIM of fine, coarse and copy-the-source on a split;
//! - [`bench`](mod@bench): step timing on a synthetic batch.

pub mod adam;
pub mod bench;
pub mod ckpt;
pub mod collective;
pub mod config;
pub mod error;
pub mod eval;
pub mod head_box;
pub mod kernels;
pub mod losses;
pub mod lpips;
pub mod metrics;
pub mod nearest;
pub mod pairs;
pub mod perceptual;
pub mod render_half;
pub mod run_error;
pub mod trainer;

pub use adam::{Adam, AdamConfig, LrRule};
pub use collective::{Collective, Single};
pub use config::TrainConfig;
pub use error::{Result, TrainError};
pub use eval::{evaluate, EvalReport, Scores};
pub use head_box::{crop_resize, head_box, head_boxes, HeadBox};
pub use losses::{LossConfig, LossInputs, LossTerms, Term, TrainLosses};
pub use lpips::Lpips;
pub use metrics::{
    psnr, psnr_per_image, ssim, ssim_gray, ssim_per_image, ssim_per_image_with, SsimWindows,
};
pub use nearest::{lifting_loss, KdTree, LIFTING_WEIGHT};
pub use pairs::{eval_pairs, Pair, PairSampler};
pub use perceptual::{PerceptualFeatures, PerceptualLoss, PERCEP_PREFIX};
pub use render_half::{
    BackendError, LiftSample, LiftedGaussians, RenderForward, RenderGrads, RenderHalf, RenderSample,
};
pub use run_error::{RunError, RunResult};
pub use trainer::{Monitor, NoMonitor, Run, RunSummary, StepReport, TrainState};
