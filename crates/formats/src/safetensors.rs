//! safetensors files: reading them into [`TensorMap`]s (every dtype we read widened to f32 /
//! i64, the header and metadata checked by the `safetensors` crate), and writing them
//! atomically, one tensor's bytes at a time.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use crate::atomic::write_via_temp;
use crate::error::{label_of, FormatError, Result};
use crate::tensor::{Dtype, RawTensor, TensorMap};

/// Largest header accepted. The safetensors crate caps it at 100 MB; a release-size model's is
/// about 60 kB.
const MAX_HEADER_BYTES: u64 = 100_000_000;

/// What a safetensors file holds, decoded.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SafetensorsFile {
    pub tensors: TensorMap,
    /// The `__metadata__` strings (empty when the file has none).
    pub metadata: BTreeMap<String, String>,
}

/// One tensor's entry in a file's header.
#[derive(Debug, Clone, PartialEq)]
pub struct HeaderEntry {
    /// `None` for a dtype this module does not read (bool, f8, i8, u16, u64, ...); the text says
    /// which it is.
    pub dtype: Option<Dtype>,
    pub dtype_name: String,
    pub shape: Vec<usize>,
}

/// A file's header: its tensors (without their data) and metadata.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Header {
    pub tensors: BTreeMap<String, HeaderEntry>,
    pub metadata: BTreeMap<String, String>,
}

fn st_err(label: &str, reason: impl std::fmt::Display) -> FormatError {
    FormatError::Safetensors {
        label: label.to_owned(),
        reason: reason.to_string(),
    }
}

fn dtype_of(d: ::safetensors::Dtype) -> Option<Dtype> {
    use ::safetensors::Dtype as S;
    Some(match d {
        S::F16 => Dtype::F16,
        S::BF16 => Dtype::BF16,
        S::F32 => Dtype::F32,
        S::F64 => Dtype::F64,
        S::U8 => Dtype::U8,
        S::U32 => Dtype::U32,
        S::I16 => Dtype::I16,
        S::I32 => Dtype::I32,
        S::I64 => Dtype::I64,
        _ => return None,
    })
}

fn st_dtype(d: Dtype) -> ::safetensors::Dtype {
    use ::safetensors::Dtype as S;
    match d {
        Dtype::F16 => S::F16,
        Dtype::BF16 => S::BF16,
        Dtype::F32 => S::F32,
        Dtype::F64 => S::F64,
        Dtype::U8 => S::U8,
        Dtype::U32 => S::U32,
        Dtype::I16 => S::I16,
        Dtype::I32 => S::I32,
        Dtype::I64 => S::I64,
    }
}

/// The header of safetensors bytes (tensor names, dtypes, shapes, metadata) without decoding
/// any tensor; every offset is checked against the data.
pub fn read_header(bytes: &[u8], label: &str) -> Result<Header> {
    check_header_size(bytes, label)?;
    let st = ::safetensors::SafeTensors::deserialize(bytes).map_err(|e| st_err(label, e))?;
    let (_, meta) =
        ::safetensors::SafeTensors::read_metadata(bytes).map_err(|e| st_err(label, e))?;
    let metadata = meta
        .metadata()
        .as_ref()
        .map(|m| m.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
        .unwrap_or_default();
    let tensors = st
        .iter()
        .map(|(name, view)| {
            (
                name.to_owned(),
                HeaderEntry {
                    dtype: dtype_of(view.dtype()),
                    dtype_name: format!("{:?}", view.dtype()),
                    shape: view.shape().to_vec(),
                },
            )
        })
        .collect();
    Ok(Header { tensors, metadata })
}

/// The header length field, checked before the safetensors crate sees the bytes: its own check
/// compares against the data length after an addition that a hostile length could overflow.
fn check_header_size(bytes: &[u8], label: &str) -> Result<()> {
    let Some(head) = bytes.get(..8) else {
        return Err(st_err(
            label,
            format!("{} bytes, too short for a header", bytes.len()),
        ));
    };
    let n = u64::from_le_bytes(head.try_into().unwrap_or([0; 8]));
    if n > MAX_HEADER_BYTES || n > (bytes.len() - 8) as u64 {
        return Err(st_err(
            label,
            format!(
                "the header claims {n} bytes, the file has {} after the length",
                bytes.len() - 8
            ),
        ));
    }
    Ok(())
}

/// Decodes every tensor of safetensors bytes (floats to f32, integers to i64) and the metadata.
pub fn parse_safetensors(bytes: &[u8], label: &str) -> Result<SafetensorsFile> {
    let header = read_header(bytes, label)?;
    let st = ::safetensors::SafeTensors::deserialize(bytes).map_err(|e| st_err(label, e))?;
    let mut tensors = TensorMap::new();
    for (name, view) in st.iter() {
        let Some(dtype) = dtype_of(view.dtype()) else {
            return Err(FormatError::Tensor {
                label: label.to_owned(),
                key: name.to_owned(),
                reason: format!(
                    "dtype {:?}; a float or integer dtype is needed",
                    view.dtype()
                ),
            });
        };
        let raw =
            RawTensor::from_bytes(dtype, view.shape().to_vec(), view.data()).map_err(|reason| {
                FormatError::Tensor {
                    label: label.to_owned(),
                    key: name.to_owned(),
                    reason,
                }
            })?;
        tensors.insert(name.to_owned(), raw);
    }
    Ok(SafetensorsFile {
        tensors,
        metadata: header.metadata,
    })
}

/// Reads and decodes a safetensors file; errors name it.
pub fn read_safetensors(path: &Path) -> Result<SafetensorsFile> {
    let bytes = std::fs::read(path).map_err(FormatError::io(path, "cannot read"))?;
    parse_safetensors(&bytes, &label_of(path))
}

/// A tensor's values for the writer.
#[derive(Debug, Clone)]
pub enum TensorData<'a> {
    F32(Cow<'a, [f32]>),
    I64(Cow<'a, [i64]>),
    /// Little-endian bytes of the given dtype.
    Bytes(Dtype, Cow<'a, [u8]>),
}

/// One tensor to write.
#[derive(Debug, Clone)]
pub struct TensorOut<'a> {
    pub name: String,
    pub shape: Vec<usize>,
    pub data: TensorData<'a>,
}

impl<'a> TensorOut<'a> {
    pub fn f32(
        name: impl Into<String>,
        shape: Vec<usize>,
        data: impl Into<Cow<'a, [f32]>>,
    ) -> Self {
        Self {
            name: name.into(),
            shape,
            data: TensorData::F32(data.into()),
        }
    }

    pub fn i64(
        name: impl Into<String>,
        shape: Vec<usize>,
        data: impl Into<Cow<'a, [i64]>>,
    ) -> Self {
        Self {
            name: name.into(),
            shape,
            data: TensorData::I64(data.into()),
        }
    }

    fn dtype(&self) -> Dtype {
        match &self.data {
            TensorData::F32(_) => Dtype::F32,
            TensorData::I64(_) => Dtype::I64,
            TensorData::Bytes(d, _) => *d,
        }
    }

    fn byte_len(&self) -> usize {
        match &self.data {
            TensorData::F32(v) => v.len() * 4,
            TensorData::I64(v) => v.len() * 8,
            TensorData::Bytes(_, b) => b.len(),
        }
    }

    fn check(&self) -> std::result::Result<(), String> {
        let numel = self
            .shape
            .iter()
            .try_fold(1usize, |n, &d| n.checked_mul(d))
            .ok_or("the shape's element count overflows")?;
        let want = numel.checked_mul(self.dtype().size());
        if want != Some(self.byte_len()) {
            return Err(format!(
                "shape {:?} of {} needs {} bytes, the data has {}",
                self.shape,
                self.dtype(),
                want.map_or("too many".into(), |w| w.to_string()),
                self.byte_len()
            ));
        }
        Ok(())
    }
}

/// The writer's view of a tensor: its bytes are made when the writer asks, one tensor at a time.
impl ::safetensors::View for &TensorOut<'_> {
    fn dtype(&self) -> ::safetensors::Dtype {
        st_dtype(TensorOut::dtype(self))
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        match &self.data {
            TensorData::F32(v) => Cow::Owned(v.iter().flat_map(|x| x.to_le_bytes()).collect()),
            TensorData::I64(v) => Cow::Owned(v.iter().flat_map(|x| x.to_le_bytes()).collect()),
            TensorData::Bytes(_, b) => Cow::Borrowed(b),
        }
    }
    fn data_len(&self) -> usize {
        self.byte_len()
    }
}

fn checked<'t, 'a>(
    tensors: &'t [TensorOut<'a>],
    label: &str,
) -> Result<Vec<(&'t str, &'t TensorOut<'a>)>> {
    let mut seen = std::collections::HashSet::new();
    for t in tensors {
        t.check().map_err(|reason| FormatError::Tensor {
            label: label.to_owned(),
            key: t.name.clone(),
            reason,
        })?;
        if !seen.insert(t.name.as_str()) {
            return Err(FormatError::Tensor {
                label: label.to_owned(),
                key: t.name.clone(),
                reason: "the name is given twice".into(),
            });
        }
    }
    Ok(tensors.iter().map(|t| (t.name.as_str(), t)).collect())
}

fn metadata_map(metadata: &BTreeMap<String, String>) -> Option<HashMap<String, String>> {
    if metadata.is_empty() {
        None
    } else {
        Some(
            metadata
                .iter()
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect(),
        )
    }
}

/// Serialises tensors (and metadata, when not empty) to safetensors bytes.
pub fn to_safetensors_bytes(
    tensors: &[TensorOut],
    metadata: &BTreeMap<String, String>,
) -> Result<Vec<u8>> {
    let label = "safetensors output";
    let views = checked(tensors, label)?;
    ::safetensors::serialize(views, metadata_map(metadata)).map_err(|e| st_err(label, e))
}

/// Writes tensors (and metadata) as a safetensors file atomically (temp sibling + rename); each
/// tensor's bytes exist only while it is written.
pub fn write_safetensors(
    path: &Path,
    tensors: &[TensorOut],
    metadata: &BTreeMap<String, String>,
) -> Result<()> {
    let views = checked(tensors, &label_of(path))?;
    let md = metadata_map(metadata);
    write_via_temp(
        path,
        |tmp| {
            ::safetensors::tensor::serialize_to_file(views, md, tmp).map_err(|e| {
                FormatError::Write {
                    path: path.to_owned(),
                    reason: e.to_string(),
                }
            })
        },
        |e| FormatError::io(path, "cannot write")(e),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tensor::RawData;

    #[test]
    fn tensors_and_metadata_round_trip() {
        let md = BTreeMap::from([("k".to_string(), "v".to_string())]);
        let tensors = [
            TensorOut::f32("a", vec![2, 2], vec![1.0, 2.0, 3.0, -4.5]),
            TensorOut::i64("b", vec![3], vec![-1, 0, 7]),
            TensorOut {
                name: "c".into(),
                shape: vec![1],
                data: TensorData::Bytes(Dtype::F16, Cow::Borrowed(&[0x00, 0x3c])),
            },
        ];
        let bytes = to_safetensors_bytes(&tensors, &md).unwrap();
        let back = parse_safetensors(&bytes, "mem").unwrap();
        assert_eq!(back.metadata, md);
        assert_eq!(
            back.tensors["a"].data,
            RawData::Float(vec![1.0, 2.0, 3.0, -4.5])
        );
        assert_eq!(back.tensors["a"].shape, [2, 2]);
        assert_eq!(back.tensors["b"].data, RawData::Int(vec![-1, 0, 7]));
        assert_eq!(back.tensors["c"].data, RawData::Float(vec![1.0]));
        assert_eq!(back.tensors["c"].file_dtype, "F16");
        let h = read_header(&bytes, "mem").unwrap();
        assert_eq!(h.tensors["b"].dtype, Some(Dtype::I64));
    }

    #[test]
    fn bad_writes_and_reads_are_errors() {
        let e = to_safetensors_bytes(&[TensorOut::f32("a", vec![3], vec![1.0])], &BTreeMap::new())
            .unwrap_err();
        assert!(e.to_string().contains("needs 12 bytes"), "{e}");
        let e = to_safetensors_bytes(
            &[
                TensorOut::f32("a", vec![1], vec![1.0]),
                TensorOut::f32("a", vec![1], vec![1.0]),
            ],
            &BTreeMap::new(),
        )
        .unwrap_err();
        assert!(e.to_string().contains("twice"), "{e}");
        for bad in [
            &b""[..],
            b"\x10\0\0\0\0\0\0\0{}",
            b"\xff\xff\xff\xff\xff\xff\xff\xff{}",
        ] {
            let e = parse_safetensors(bad, "mem").unwrap_err();
            assert!(matches!(e, FormatError::Safetensors { .. }), "{e}");
        }
    }
}
