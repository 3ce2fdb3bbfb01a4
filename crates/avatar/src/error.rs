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
        source: Box<gagavatar_net::NetError>,
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
        source: Box<gagavatar_flame::FlameError>,
    },
    /// The FLAME asset the tracker fits with could not be read.
    #[error("loading FLAME {}", path.display())]
    FlameFile {
        path: PathBuf,
        #[source]
        source: Box<gagavatar_flame::FlameError>,
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
    /// A monitor asked to stop ([`crate::Monitor::cancelled`]); nothing was left half-written.
    #[error("cancelled; no output was written")]
    Cancelled,
    /// A file or folder the library reads or writes itself (the tracking cache).
    #[error("{what} {}", path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A precision this CPU cannot run (bf16 without AVX512-BF16).
    #[error(transparent)]
    Precision(#[from] gagavatar_ops::bf16::Bf16Error),
    #[error(transparent)]
    Track(#[from] gagavatar_track::TrackError),
    #[error(transparent)]
    Face(#[from] gagavatar_face::FaceError),
    #[error(transparent)]
    Video(#[from] gagavatar_video::VideoError),
    #[error(transparent)]
    Format(#[from] gagavatar_formats::FormatError),
    #[error(transparent)]
    Data(#[from] gagavatar_data::DataError),
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

pub(crate) fn io_err(
    what: &'static str,
    path: &std::path::Path,
) -> impl FnOnce(std::io::Error) -> AvatarError {
    let path = path.to_owned();
    move |source| AvatarError::Io { what, path, source }
}

/// An error and its causes on one line (`a: b: c`), as the CLI prints them: what the Python
/// package raises and the server answers.
pub fn one_line(e: &(dyn std::error::Error + 'static)) -> String {
    let mut s = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cause = c.source();
    }
    s
}
