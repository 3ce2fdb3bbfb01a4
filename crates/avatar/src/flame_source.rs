//! Which FLAME asset an engine and its tracker use.

use std::path::{Path, PathBuf};

/// Which FLAME asset drives the avatars.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum FlameSource {
    /// The one the weights were trained with: the built-in synthetic asset when their metadata
    /// names it (or, without metadata, for the `tiny` / `small` architectures trained here);
    /// an error asking for the file otherwise (the release's weights need `FLAME_with_eye.pt`).
    #[default]
    FromWeights,
    /// The built-in synthetic asset (`gagavatar flame synth`, seed 0).
    Synthetic,
    /// A file: the release's `FLAME_with_eye.pt`, or safetensors with the same keys.
    File(PathBuf),
}

impl FlameSource {
    /// The CLI's spelling: `synthetic` (when no such file exists) or a path.
    pub fn from_arg(arg: &Path) -> Self {
        if arg.as_os_str() == SYNTHETIC_FLAME && !arg.exists() {
            FlameSource::Synthetic
        } else {
            FlameSource::File(arg.to_path_buf())
        }
    }
}

/// The word that names the built-in synthetic FLAME asset on the command line.
pub const SYNTHETIC_FLAME: &str = "synthetic";
