//! Reading the shipped model files (safetensors) with a strict check of their tensors.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};

use crate::error::{MetricsError, Result};

/// Where the converted dlib models live in the repository (`tools/identity/convert_dlib.py`).
pub const ASSET_DIR: &str = "assets/identity";
/// The 5-point shape predictor's file name in [`ASSET_DIR`].
pub const SHAPE_PREDICTOR_FILE: &str = "dlib_shape_predictor_5.safetensors";
/// The face-recognition ResNet's file name in [`ASSET_DIR`].
pub const RESNET_FILE: &str = "dlib_face_recognition_resnet_v1.safetensors";

/// The asset folder: `assets/identity` under the working directory when it holds the models,
/// else the one of the source tree this crate was built from.
pub fn default_asset_dir() -> PathBuf {
    let local = PathBuf::from(ASSET_DIR);
    if local.join(RESNET_FILE).is_file() {
        return local;
    }
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(ASSET_DIR)
}

pub(crate) fn weights_err(path: &Path, reason: impl Into<String>) -> MetricsError {
    MetricsError::Weights {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

/// All tensors of a safetensors file, on the CPU.
pub(crate) fn read_tensors(path: &Path) -> Result<HashMap<String, Tensor>> {
    let bytes = std::fs::read(path).map_err(|e| weights_err(path, format!("cannot read: {e}")))?;
    candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)
        .map_err(|e| weights_err(path, format!("not a readable safetensors file: {e}")))
}

/// Checks that `tensors` holds exactly the `expected` keys with these shapes and (when given)
/// dtypes; the message lists what is missing, extra or misshapen.
pub(crate) fn check_tensors(
    path: &Path,
    tensors: &HashMap<String, Tensor>,
    expected: &BTreeMap<String, (Vec<usize>, Option<DType>)>,
) -> Result<()> {
    let mut problems = Vec::new();
    for (key, (shape, dtype)) in expected {
        match tensors.get(key) {
            None => problems.push(format!("missing `{key}`")),
            Some(t) => {
                if t.dims() != shape.as_slice() {
                    problems.push(format!(
                        "`{key}` has shape {:?}, expected {shape:?}",
                        t.dims()
                    ));
                }
                if let Some(d) = dtype {
                    if t.dtype() != *d {
                        problems.push(format!("`{key}` is {:?}, expected {d:?}", t.dtype()));
                    }
                }
            }
        }
    }
    let mut extra: Vec<&String> = tensors
        .keys()
        .filter(|k| !expected.contains_key(*k))
        .collect();
    extra.sort();
    for k in extra {
        problems.push(format!("unexpected `{k}`"));
    }
    if problems.is_empty() {
        Ok(())
    } else {
        let n = problems.len();
        problems.truncate(8);
        Err(weights_err(
            path,
            format!(
                "{}{}",
                problems.join("; "),
                if n > 8 {
                    format!(" (and {} more)", n - 8)
                } else {
                    String::new()
                }
            ),
        ))
    }
}
