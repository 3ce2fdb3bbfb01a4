//! Loading the converted MediaPipe weights (`crates/face/weights/*.safetensors`, written by
//! `tools/convert_mediapipe_face.py`) through candle's `VarBuilder`, strictly: every tensor a
//! model asks for must exist with exactly the asked shape, and every tensor in the file must be
//! used, so a file for another network (or a damaged one) is refused with a message naming the
//! tensor instead of computing nonsense.
//!
//! Keys are `<layer>.kernel`, `<layer>.bias`, `<layer>.alpha` with the Keras layer names TFLite
//! kept; shapes and layouts are TFLite's (convolution kernels `[O, kh, kw, I]`, depthwise
//! `[1, kh, kw, C]`, PReLU `[1, 1, C]`). The file's metadata maps each key to its TFLite tensor.

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;

use crate::FaceError;

/// The `format` metadata value the converter writes.
pub const FORMAT: &str = "gagavatar-face-weights-1";

/// The shipped weights, compiled into the library (about 3.9 MB in all), so nothing is read or
/// downloaded at run time.
pub mod bundled {
    pub const FACE_DETECTION_SHORT_RANGE: &[u8] =
        include_bytes!("../weights/face_detection_short_range.safetensors");
    pub const FACE_DETECTION_FULL_RANGE: &[u8] =
        include_bytes!("../weights/face_detection_full_range.safetensors");
    pub const FACE_LANDMARK_WITH_ATTENTION: &[u8] =
        include_bytes!("../weights/face_landmark_with_attention.safetensors");
    pub const SELFIE_SEGMENTATION: &[u8] =
        include_bytes!("../weights/selfie_segmentation.safetensors");
}

/// A parsed weights file.
pub struct WeightsFile {
    label: String,
    tensors: HashMap<String, Tensor>,
    metadata: HashMap<String, String>,
}

impl WeightsFile {
    /// Parses safetensors bytes; `label` names them in errors.
    pub fn from_bytes(bytes: &[u8], label: &str) -> Result<Self, FaceError> {
        let fmt = |reason: String| FaceError::Format {
            label: label.to_owned(),
            reason,
        };
        let (_, meta) =
            safetensors::SafeTensors::read_metadata(bytes).map_err(|e| fmt(e.to_string()))?;
        let metadata = meta.metadata().clone().unwrap_or_default();
        let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)
            .map_err(|e| fmt(e.to_string()))?;
        Ok(WeightsFile {
            label: label.to_owned(),
            tensors,
            metadata,
        })
    }

    /// Reads and parses a weights file.
    pub fn from_path(path: &Path) -> Result<Self, FaceError> {
        let label = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|e| FaceError::Format {
            label: label.clone(),
            reason: e.to_string(),
        })?;
        Self::from_bytes(&bytes, &label)
    }

    /// A metadata value (`source`, `source_sha256`, `license`, `tflite_tensors`, ...).
    pub fn metadata(&self, key: &str) -> Option<&str> {
        self.metadata.get(key).map(String::as_str)
    }

    /// Builds model `model` (the metadata's `model` value) with `build`, which asks for its
    /// tensors through the `VarBuilder`; refuses a file for another model, a missing or
    /// mis-shaped tensor, and tensors left unused.
    pub fn build<M>(
        self,
        model: &str,
        build: impl FnOnce(VarBuilder) -> candle_core::Result<M>,
    ) -> Result<M, FaceError> {
        let label = self.label.clone();
        if self.metadata("format") != Some(FORMAT) {
            return Err(FaceError::Format {
                label,
                reason: format!("metadata 'format' is not '{FORMAT}'"),
            });
        }
        let found = self.metadata("model").unwrap_or("(none)").to_owned();
        if found != model {
            return Err(FaceError::WrongModel {
                label,
                expected: model.to_owned(),
                found,
            });
        }
        let names: Vec<String> = self.tensors.keys().cloned().collect();
        let used = Arc::new(Mutex::new(HashSet::new()));
        let backend = Strict {
            tensors: self.tensors,
            used: used.clone(),
        };
        let vb = VarBuilder::from_backend(Box::new(backend), DType::F32, Device::Cpu);
        let m = build(vb).map_err(|e| FaceError::Weights {
            label: label.clone(),
            reason: e.to_string(),
        })?;
        let used = used.lock().map_err(|_| FaceError::Weights {
            label: label.clone(),
            reason: "weight loading panicked".into(),
        })?;
        let mut unused: Vec<&String> = names.iter().filter(|n| !used.contains(*n)).collect();
        unused.sort();
        if let Some(first) = unused.first() {
            return Err(FaceError::UnusedWeights {
                label,
                count: unused.len(),
                example: (*first).clone(),
            });
        }
        Ok(m)
    }
}

/// A `VarBuilder` backend over the file's tensors that checks shapes exactly and records every
/// name asked for.
struct Strict {
    tensors: HashMap<String, Tensor>,
    used: Arc<Mutex<HashSet<String>>>,
}

impl SimpleBackend for Strict {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let t = self.get_unchecked(name, dtype, dev)?;
        if t.shape() != &s {
            candle_core::bail!(
                "tensor '{name}' has shape {:?}, the model expects {:?}",
                t.dims(),
                s.dims()
            );
        }
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let t = self
            .tensors
            .get(name)
            .ok_or_else(|| candle_core::Error::Msg(format!("missing tensor '{name}'")))?;
        if let Ok(mut u) = self.used.lock() {
            u.insert(name.to_owned());
        }
        t.to_dtype(dtype)?.to_device(dev)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }
}

/// The values of tensor `name` of exactly `shape`, flattened.
pub fn get_vec(vb: &VarBuilder, shape: &[usize], name: &str) -> candle_core::Result<Vec<f32>> {
    vb.get(shape, name)?.flatten_all()?.to_vec1::<f32>()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(bytes: &[u8]) -> WeightsFile {
        WeightsFile::from_bytes(bytes, "test").unwrap()
    }

    #[test]
    fn bundled_files_carry_provenance() {
        for (bytes, model) in [
            (
                bundled::FACE_DETECTION_SHORT_RANGE,
                "face_detection_short_range",
            ),
            (
                bundled::FACE_DETECTION_FULL_RANGE,
                "face_detection_full_range",
            ),
            (
                bundled::FACE_LANDMARK_WITH_ATTENTION,
                "face_landmark_with_attention",
            ),
            (bundled::SELFIE_SEGMENTATION, "selfie_segmentation"),
        ] {
            let f = file(bytes);
            assert_eq!(f.metadata("model"), Some(model));
            assert_eq!(f.metadata("license"), Some("Apache-2.0"));
            assert!(f.metadata("source").unwrap().contains("mediapipe==0.10.21"));
            assert_eq!(f.metadata("source_sha256").map(str::len), Some(64));
        }
    }

    #[test]
    fn refuses_wrong_model_missing_shape_and_unused() {
        let f = file(bundled::FACE_DETECTION_SHORT_RANGE);
        let e = f.build("selfie_segmentation", |_| Ok(())).err().unwrap();
        assert!(
            e.to_string().contains("expected 'selfie_segmentation'"),
            "{e}"
        );

        let f = file(bundled::FACE_DETECTION_SHORT_RANGE);
        let e = f
            .build("face_detection_short_range", |vb| {
                get_vec(&vb, &[24], "nope.bias").map(|_| ())
            })
            .err()
            .unwrap();
        assert!(e.to_string().contains("missing tensor 'nope.bias'"), "{e}");

        let f = file(bundled::FACE_DETECTION_SHORT_RANGE);
        let e = f
            .build("face_detection_short_range", |vb| {
                get_vec(&vb, &[25], "conv2d.bias").map(|_| ())
            })
            .err()
            .unwrap();
        assert!(
            e.to_string().contains("'conv2d.bias' has shape [24]"),
            "{e}"
        );

        let f = file(bundled::FACE_DETECTION_SHORT_RANGE);
        let e = f
            .build("face_detection_short_range", |vb| {
                get_vec(&vb, &[24], "conv2d.bias").map(|_| ())
            })
            .err()
            .unwrap();
        assert!(
            e.to_string().contains("73 tensors the model does not use"),
            "{e}"
        );
    }

    #[test]
    fn refuses_garbage() {
        for bytes in [&b""[..], b"\x08\0\0\0\0\0\0\0{}", b"not safetensors at all"] {
            assert!(WeightsFile::from_bytes(bytes, "x").is_err());
        }
    }
}
