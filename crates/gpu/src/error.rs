//! The crate's error type.

use crate::policy::AdapterPolicy;

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter the policy allows. `seen` lists every adapter wgpu found.
    #[error("no GPU adapter found{} (adapters seen: {seen}){}",
        wanted.as_ref().map(|w| format!(" whose name contains `{w}`")).unwrap_or_default(),
        if *policy == AdapterPolicy::RealOnly {
            "; CPU-emulated adapters such as lavapipe are skipped unless asked for"
        } else {
            ""
        })]
    NoAdapter {
        policy: AdapterPolicy,
        wanted: Option<String>,
        seen: String,
    },
    /// The device could not be created or was lost.
    #[error("GPU device error: {0}")]
    Device(String),
    /// An input does not fit (shape, size, non-finite values).
    #[error("{name}: {reason}")]
    Input { name: String, reason: String },
    /// A model size the GPU path does not handle.
    #[error("unsupported on the GPU path: {0}")]
    Unsupported(String),
    /// A weight tensor could not be read.
    #[error("weights: {0}")]
    Weights(String),
}

pub type Result<T> = std::result::Result<T, GpuError>;

pub(crate) fn input_err(name: &str, reason: impl Into<String>) -> GpuError {
    GpuError::Input {
        name: name.to_string(),
        reason: reason.into(),
    }
}
