use std::path::{Path, PathBuf};

/// What a format reader can refuse. Every message names the file (or the label the caller gave
/// for in-memory bytes), so a user can tell which input is wrong.
///
/// The underlying I/O error is part of the message and deliberately not a `source()`: callers
/// print errors with their chain (`{:#}`), which would otherwise show the cause twice.
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
}

impl FormatError {
    /// A closure for `map_err` that labels an I/O error with the path and what was being done.
    pub fn io(path: &Path, what: &'static str) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.to_path_buf();
        move |err| FormatError::Io { path, what, err }
    }
}
