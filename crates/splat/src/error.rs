use thiserror::Error;

/// Everything the splatting API can refuse. Inputs come from users and files, so every
/// check is an error value, never a panic.
#[derive(Debug, Error)]
pub enum SplatError {
    #[error("{name} has shape {got:?}, expected {expected}")]
    Shape {
        name: &'static str,
        got: Vec<usize>,
        expected: String,
    },
    #[error("{name} contains a non-finite value ({value}) at flat index {index}")]
    NonFinite {
        name: &'static str,
        index: usize,
        value: f64,
    },
    #[error("image size {width}x{height} is invalid: both sides must be between 1 and {max}")]
    ImageSize {
        width: usize,
        height: usize,
        max: usize,
    },
    #[error("invalid camera: {0}")]
    Camera(String),
    #[error("batch mismatch: {0}")]
    Batch(String),
    #[error("unsupported dtype {0:?}: splatting runs in f32 or f64")]
    DType(candle_core::DType),
    #[error("all inputs must share one dtype: means is {0:?} but another input is {1:?}")]
    MixedDType(candle_core::DType, candle_core::DType),
    #[error("splatting runs on the CPU only for now (got a {0:?} tensor)")]
    Device(candle_core::DeviceLocation),
    #[error("scene file {path}: {msg}")]
    Scene { path: String, msg: String },
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// The cause is part of the message and deliberately not a `source()`, which the CLI
    /// would print a second time.
    #[error("{path}: {err}")]
    Io { path: String, err: std::io::Error },
}

pub type Result<T> = std::result::Result<T, SplatError>;
