//! Typed errors. Every failure a file or a record can cause names the key or field involved, so a
//! user with a broken asset learns which entry to look at without a debugger.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum FlameError {
    #[error("{path}: cannot read")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not a readable torch zip checkpoint: {reason}")]
    Archive { path: PathBuf, reason: String },
    #[error("{path}: unsupported pickle content: {reason}")]
    Pickle { path: PathBuf, reason: String },
    #[error("{path}: not a readable safetensors file: {reason}")]
    Safetensors { path: PathBuf, reason: String },
    #[error("FLAME asset: missing key `{key}`")]
    MissingKey { key: String },
    #[error("FLAME asset: key `{key}` has shape {found:?}, expected {expected}")]
    Shape {
        key: String,
        expected: String,
        found: Vec<usize>,
    },
    #[error("FLAME asset: key `{key}` has dtype {found}, expected {expected}")]
    DType {
        key: String,
        expected: &'static str,
        found: String,
    },
    #[error("FLAME asset: key `{key}`: {reason}")]
    Invalid { key: String, reason: String },
    #[error("FLAME asset has {available} {what} components but {requested} were requested")]
    Components {
        what: &'static str,
        available: usize,
        requested: usize,
    },
    #[error("tracked-frame record: field `{field}`: {reason}")]
    Record { field: String, reason: String },
    #[error("FLAME input `{name}`: {reason}")]
    Input { name: &'static str, reason: String },
    #[error("tensor computation failed: {0}")]
    Candle(#[from] candle_core::Error),
}

pub type Result<T> = std::result::Result<T, FlameError>;
