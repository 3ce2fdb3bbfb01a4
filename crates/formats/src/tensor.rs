//! Tensors as tensor files hold them, before any meaning is attached: a dtype, a shape and
//! little-endian row-major bytes ([`TensorBytes`]), or those decoded to f32 / i64 values
//! ([`RawTensor`]), which is what the FLAME asset, checkpoints and image tensors need.

use std::collections::BTreeMap;

/// Element types of the tensor files we read (torch storages and safetensors). A torch bool
/// storage is read as [`Dtype::U8`] (torch stores each bool as one byte, 0 or 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Dtype {
    U8,
    I16,
    U32,
    I32,
    I64,
    F16,
    BF16,
    F32,
    F64,
}

impl Dtype {
    pub fn size(self) -> usize {
        match self {
            Dtype::U8 => 1,
            Dtype::I16 | Dtype::F16 | Dtype::BF16 => 2,
            Dtype::U32 | Dtype::I32 | Dtype::F32 => 4,
            Dtype::I64 | Dtype::F64 => 8,
        }
    }

    pub fn is_float(self) -> bool {
        matches!(self, Dtype::F16 | Dtype::BF16 | Dtype::F32 | Dtype::F64)
    }

    /// The name used in messages and [`RawTensor::file_dtype`] (`F32`, `BF16`, `I64`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Dtype::U8 => "U8",
            Dtype::I16 => "I16",
            Dtype::U32 => "U32",
            Dtype::I32 => "I32",
            Dtype::I64 => "I64",
            Dtype::F16 => "F16",
            Dtype::BF16 => "BF16",
            Dtype::F32 => "F32",
            Dtype::F64 => "F64",
        }
    }
}

impl std::fmt::Display for Dtype {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One tensor's bytes as stored: little-endian, row-major, `shape.product() * dtype.size()`
/// bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct TensorBytes {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub bytes: Vec<u8>,
}

#[derive(Debug, Clone, PartialEq)]
pub enum RawData {
    Float(Vec<f32>),
    Int(Vec<i64>),
}

/// A tensor as read from a file, floats widened or narrowed to f32 and integers widened to i64.
#[derive(Debug, Clone, PartialEq)]
pub struct RawTensor {
    pub shape: Vec<usize>,
    pub data: RawData,
    /// The dtype in the file ([`Dtype::name`]), for error messages.
    pub file_dtype: String,
}

pub type TensorMap = BTreeMap<String, RawTensor>;

impl RawTensor {
    pub fn float(shape: Vec<usize>, data: Vec<f32>) -> Self {
        Self {
            shape,
            data: RawData::Float(data),
            file_dtype: Dtype::F32.name().into(),
        }
    }

    pub fn int(shape: Vec<usize>, data: Vec<i64>) -> Self {
        Self {
            shape,
            data: RawData::Int(data),
            file_dtype: Dtype::I64.name().into(),
        }
    }

    /// Decodes little-endian row-major bytes; the error says what does not fit.
    pub fn from_bytes(dtype: Dtype, shape: Vec<usize>, bytes: &[u8]) -> Result<Self, String> {
        let numel = shape
            .iter()
            .try_fold(1usize, |n, &d| n.checked_mul(d))
            .ok_or("the shape's element count overflows")?;
        if Some(bytes.len()) != numel.checked_mul(dtype.size()) {
            return Err(format!(
                "{} bytes of data for {numel} elements of {dtype}",
                bytes.len()
            ));
        }
        fn each<const N: usize, T>(bytes: &[u8], f: impl Fn([u8; N]) -> T) -> Vec<T> {
            bytes
                .chunks_exact(N)
                .map(|c| {
                    let mut a = [0u8; N];
                    a.copy_from_slice(c);
                    f(a)
                })
                .collect()
        }
        let data = match dtype {
            Dtype::F32 => RawData::Float(each(bytes, f32::from_le_bytes)),
            Dtype::F64 => RawData::Float(each(bytes, |a| f64::from_le_bytes(a) as f32)),
            Dtype::F16 => RawData::Float(each(bytes, |a| f16_to_f32(u16::from_le_bytes(a)))),
            Dtype::BF16 => RawData::Float(each(bytes, |a| {
                f32::from_bits(u32::from(u16::from_le_bytes(a)) << 16)
            })),
            Dtype::U8 => RawData::Int(bytes.iter().map(|&b| i64::from(b)).collect()),
            Dtype::I16 => RawData::Int(each(bytes, |a| i64::from(i16::from_le_bytes(a)))),
            Dtype::U32 => RawData::Int(each(bytes, |a| i64::from(u32::from_le_bytes(a)))),
            Dtype::I32 => RawData::Int(each(bytes, |a| i64::from(i32::from_le_bytes(a)))),
            Dtype::I64 => RawData::Int(each(bytes, i64::from_le_bytes)),
        };
        Ok(Self {
            shape,
            data,
            file_dtype: dtype.name().into(),
        })
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        match &self.data {
            RawData::Float(v) => v.len(),
            RawData::Int(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// IEEE 754 binary16 to f32 (exact: every half is a float).
pub fn f16_to_f32(h: u16) -> f32 {
    crate::numpy::f16_to_f64(h) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_dtype_decodes_little_endian() {
        let t = RawTensor::from_bytes(Dtype::F16, vec![2], &[0x00, 0x3c, 0x00, 0xc0]).unwrap();
        assert_eq!(t.data, RawData::Float(vec![1.0, -2.0]));
        let t = RawTensor::from_bytes(Dtype::BF16, vec![1], &[0x80, 0x3f]).unwrap();
        assert_eq!(t.data, RawData::Float(vec![1.0]));
        let t = RawTensor::from_bytes(Dtype::F64, vec![1], &0.5f64.to_le_bytes()).unwrap();
        assert_eq!(t.data, RawData::Float(vec![0.5]));
        let t = RawTensor::from_bytes(Dtype::I16, vec![1], &(-3i16).to_le_bytes()).unwrap();
        assert_eq!(t.data, RawData::Int(vec![-3]));
        let t = RawTensor::from_bytes(Dtype::U32, vec![1], &u32::MAX.to_le_bytes()).unwrap();
        assert_eq!(t.data, RawData::Int(vec![u32::MAX as i64]));
        assert_eq!(t.file_dtype, "U32");
    }

    #[test]
    fn byte_counts_and_overflowing_shapes_are_errors() {
        let e = RawTensor::from_bytes(Dtype::F32, vec![3], &[0; 8]).unwrap_err();
        assert!(e.contains("8 bytes of data for 3 elements of F32"), "{e}");
        let e = RawTensor::from_bytes(Dtype::F32, vec![usize::MAX, 2], &[]).unwrap_err();
        assert!(e.contains("overflows"), "{e}");
    }
}
