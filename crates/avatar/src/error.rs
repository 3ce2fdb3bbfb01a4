use std::path::PathBuf;

/// Everything the pipeline library can fail with. Messages are one line; a cause is kept as the
/// `source()` (never repeated in the message), so `{err:#}`-style printing shows it once.
#[derive(Debug, thiserror::Error)]
pub enum AvatarError {
    /// The weights file could not be read or does not fit its architecture.
    #[error("loading {}", path.display())]
    Weights {
        path: PathBuf,
        #[source]
        source: gagavatar_net::NetError,
    },
    /// The FLAME asset could not be read with the requested component counts.
    #[error(
        "loading FLAME {} as {n_shape} shape + {n_exp} expression components",
        path.display()
    )]
    FlameAsset {
        path: PathBuf,
        n_shape: usize,
        n_exp: usize,
        #[source]
        source: gagavatar_flame::FlameError,
    },
    /// No FLAME asset was named and the weights do not say which one they were trained with.
    #[error("{0}")]
    FlameNeeded(String),
    /// The FLAME asset and the model disagree on the mesh.
    #[error("the FLAME asset has {asset} vertices, the model expects {model}")]
    FlameVertices { asset: usize, model: usize },
    /// A caller-supplied input (record, image, camera, batch) is unusable.
    #[error("{what}: {reason}")]
    Input { what: String, reason: String },
    #[error(transparent)]
    Net(#[from] gagavatar_net::NetError),
    #[error(transparent)]
    Flame(#[from] gagavatar_flame::FlameError),
    #[error(transparent)]
    Gpu(#[from] gagavatar_gpu::GpuError),
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

pub type Result<T> = std::result::Result<T, AvatarError>;

pub(crate) fn input_err(what: impl Into<String>, reason: impl Into<String>) -> AvatarError {
    AvatarError::Input {
        what: what.into(),
        reason: reason.into(),
    }
}
