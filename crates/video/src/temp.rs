//! Hidden temporary outputs beside the target, removed unless they were renamed into place.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::VideoError;

/// Distinguishes two writers for the same target in one process (the pid alone would not).
static COUNTER: AtomicUsize = AtomicUsize::new(0);

/// `dir/.name.<tag>tmp<pid>.<n>`: same directory as `path` so the final rename never crosses
/// file systems, and hidden so a half-written video is not picked up by anyone.
pub(crate) fn temp_sibling(path: &Path, tag: &str) -> Result<PathBuf, VideoError> {
    let name = path.file_name().ok_or_else(|| VideoError::BadPath {
        path: path.to_path_buf(),
        reason: "the output path has no file name".into(),
    })?;
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    Ok(dir.join(format!(
        ".{}.{tag}tmp{}.{n}",
        name.to_string_lossy(),
        std::process::id()
    )))
}

/// A temporary file or directory that is deleted on drop unless [`TempPath::persist`] renamed it.
pub(crate) struct TempPath {
    path: PathBuf,
    is_dir: bool,
    armed: bool,
}

impl TempPath {
    pub(crate) fn file(path: PathBuf) -> Self {
        TempPath {
            path,
            is_dir: false,
            armed: true,
        }
    }

    pub(crate) fn dir(path: PathBuf) -> Self {
        TempPath {
            path,
            is_dir: true,
            armed: true,
        }
    }

    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// Renames the temporary over `target`.
    pub(crate) fn persist(mut self, target: &Path) -> Result<(), VideoError> {
        std::fs::rename(&self.path, target).map_err(|e| VideoError::io(target, e))?;
        self.armed = false;
        Ok(())
    }
}

impl Drop for TempPath {
    fn drop(&mut self) {
        if self.armed {
            // Best effort: there is no one to report a failure to while unwinding.
            let _ = if self.is_dir {
                std::fs::remove_dir_all(&self.path)
            } else {
                std::fs::remove_file(&self.path)
            };
        }
    }
}

/// Refuses a target that is a directory (for a video file); an existing file is replaced.
pub(crate) fn check_file_target(path: &Path) -> Result<(), VideoError> {
    if path.is_dir() {
        return Err(VideoError::BadPath {
            path: path.to_path_buf(),
            reason: "is a directory; a video file cannot replace it".into(),
        });
    }
    Ok(())
}

/// Refuses a target that is a file or a non-empty directory (for a PNG folder), so frames are
/// never mixed with, or replace, someone else's files.
pub(crate) fn check_dir_target(path: &Path) -> Result<(), VideoError> {
    let meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(VideoError::io(path, e)),
    };
    if !meta.is_dir() {
        return Err(VideoError::BadPath {
            path: path.to_path_buf(),
            reason: "exists and is not a directory (a PNG frame folder was asked for: use a .mp4 \
                     or .gif extension for a video file)"
                .into(),
        });
    }
    let mut entries = std::fs::read_dir(path).map_err(|e| VideoError::io(path, e))?;
    if entries.next().is_some() {
        return Err(VideoError::BadPath {
            path: path.to_path_buf(),
            reason: "is a directory that is not empty; choose a new folder for the PNG frames"
                .into(),
        });
    }
    Ok(())
}
