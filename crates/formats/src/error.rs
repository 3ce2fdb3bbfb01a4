use std::path::{Path, PathBuf};

/// What a format reader or writer can refuse. Every message names the file (or the label the
/// caller gave for in-memory bytes), so a user can tell which input is wrong.
///
/// Underlying errors are part of the message and deliberately never a `source()`: callers print
/// errors with their chain (`{:#}`), which would otherwise show the cause twice.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The file could not be read or written at all.
    #[error("{}: {what}: {err}", path.display())]
    Io {
        path: PathBuf,
        what: &'static str,
        err: std::io::Error,
    },
    /// The bytes are not a usable image; `reason` says why in words a user can act on.
    #[error("{label}: {reason}")]
    Image { label: String, reason: String },
    /// A pickle that cannot be parsed, or that holds something other than what was asked for.
    #[error("{label}: {reason}")]
    Pickle { label: String, reason: String },
    /// A torch zip checkpoint whose archive or pickle cannot be used.
    #[error("{label}: not a readable torch zip checkpoint: {reason}")]
    TorchZip { label: String, reason: String },
    #[error("{label}: not a readable safetensors file: {reason}")]
    Safetensors { label: String, reason: String },
    /// One tensor of a tensor file that cannot be read as stored.
    #[error("{label}: tensor `{key}`: {reason}")]
    Tensor {
        label: String,
        key: String,
        reason: String,
    },
    #[error("{}: not a readable LMDB environment: {reason}", path.display())]
    Lmdb { path: PathBuf, reason: String },
    #[error("{label}: not a readable PLY file: {reason}")]
    Ply { label: String, reason: String },
    /// An ONNX model file that cannot be decoded, or that uses what the reader does not keep.
    #[error("{label}: {reason}")]
    Onnx { label: String, reason: String },
    /// Values that cannot be written (duplicate or empty keys, sizes beyond the format, ...).
    #[error("{}: cannot write: {reason}", path.display())]
    Write { path: PathBuf, reason: String },
}

impl FormatError {
    /// A closure for `map_err` that labels an I/O error with the path and what was being done.
    pub fn io(path: &Path, what: &'static str) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.to_path_buf();
        move |err| FormatError::Io { path, what, err }
    }

    /// The message without the file name or label it starts with, for callers that name the
    /// file themselves.
    pub fn detail(&self) -> String {
        match self {
            FormatError::Io { what, err, .. } => format!("{what}: {err}"),
            FormatError::Image { reason, .. }
            | FormatError::Pickle { reason, .. }
            | FormatError::Onnx { reason, .. }
            | FormatError::Write { reason, .. } => reason.clone(),
            FormatError::TorchZip { reason, .. } => {
                format!("not a readable torch zip checkpoint: {reason}")
            }
            FormatError::Safetensors { reason, .. } => {
                format!("not a readable safetensors file: {reason}")
            }
            FormatError::Tensor { key, reason, .. } => format!("tensor `{key}`: {reason}"),
            FormatError::Lmdb { reason, .. } => {
                format!("not a readable LMDB environment: {reason}")
            }
            FormatError::Ply { reason, .. } => format!("not a readable PLY file: {reason}"),
        }
    }

    /// The underlying I/O error when this is one (e.g. to tell a missing file apart).
    pub fn io_kind(&self) -> Option<std::io::ErrorKind> {
        match self {
            FormatError::Io { err, .. } => Some(err.kind()),
            _ => None,
        }
    }
}

pub type Result<T> = std::result::Result<T, FormatError>;

/// How a path is shown in messages about its content.
pub(crate) fn label_of(path: &Path) -> String {
    path.display().to_string()
}
