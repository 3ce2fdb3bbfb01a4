//! Typed errors. Every failure a file or a record can cause names the key or field involved, so a
//! user with a broken asset learns which entry to look at without a debugger.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum FlameError {
    /// The cause is part of the message and deliberately not a `source()`, which the CLI
    /// would print a second time.
    #[error("{}: cannot read: {err}", path.display())]
    Io { path: PathBuf, err: std::io::Error },
    /// A file that cannot be read as a tensor file (torch zip or safetensors) at all.
    #[error(transparent)]
    Format(#[from] gagavatar_formats::FormatError),
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
    /// A record read from a file (`TrackedFrame::from_json_file`): the message names it.
    #[error("{}: tracked-frame record: field `{field}`: {reason}", path.display())]
    RecordFile {
        path: PathBuf,
        field: String,
        reason: String,
    },
    #[error("FLAME input `{name}`: {reason}")]
    Input { name: &'static str, reason: String },
    #[error("tensor computation failed: {0}")]
    Candle(candle_core::Error),
}

impl From<candle_core::Error> for FlameError {
    fn from(e: candle_core::Error) -> Self {
        FlameError::Candle(e)
    }
}

pub type Result<T> = std::result::Result<T, FlameError>;
