//! numpy arrays as plain data: the element types read, row-major typed storage, and the
//! conversion of raw (possibly big-endian, possibly Fortran-ordered) element bytes into it.
//! What a pickled array looks like is [`crate::pickle::plain`]'s business; this module only
//! knows arrays.

/// Element types of the numpy arrays we read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DType {
    Bool,
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F16,
    F32,
    F64,
}

impl DType {
    pub fn size(self) -> usize {
        match self {
            DType::Bool | DType::U8 | DType::I8 => 1,
            DType::U16 | DType::I16 | DType::F16 => 2,
            DType::U32 | DType::I32 | DType::F32 => 4,
            DType::U64 | DType::I64 | DType::F64 => 8,
        }
    }

    /// numpy's type code without byte order (`f4`, `i8`, `b1`, ...).
    pub fn numpy_code(self) -> &'static str {
        match self {
            DType::Bool => "b1",
            DType::U8 => "u1",
            DType::I8 => "i1",
            DType::U16 => "u2",
            DType::I16 => "i2",
            DType::U32 => "u4",
            DType::I32 => "i4",
            DType::U64 => "u8",
            DType::I64 => "i8",
            DType::F16 => "f2",
            DType::F32 => "f4",
            DType::F64 => "f8",
        }
    }

    pub fn is_float(self) -> bool {
        matches!(self, DType::F16 | DType::F32 | DType::F64)
    }
}

/// Array elements in row-major (C) order, in the machine's representation.
#[derive(Debug, Clone, PartialEq)]
pub enum ArrayData {
    Bool(Vec<bool>),
    U8(Vec<u8>),
    I8(Vec<i8>),
    U16(Vec<u16>),
    I16(Vec<i16>),
    U32(Vec<u32>),
    I32(Vec<i32>),
    U64(Vec<u64>),
    I64(Vec<i64>),
    /// IEEE half-precision bit patterns.
    F16(Vec<u16>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

/// A numpy array: shape and row-major data.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    pub shape: Vec<usize>,
    pub data: ArrayData,
}

impl NdArray {
    pub fn dtype(&self) -> DType {
        match &self.data {
            ArrayData::Bool(_) => DType::Bool,
            ArrayData::U8(_) => DType::U8,
            ArrayData::I8(_) => DType::I8,
            ArrayData::U16(_) => DType::U16,
            ArrayData::I16(_) => DType::I16,
            ArrayData::U32(_) => DType::U32,
            ArrayData::I32(_) => DType::I32,
            ArrayData::U64(_) => DType::U64,
            ArrayData::I64(_) => DType::I64,
            ArrayData::F16(_) => DType::F16,
            ArrayData::F32(_) => DType::F32,
            ArrayData::F64(_) => DType::F64,
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        match &self.data {
            ArrayData::Bool(v) => v.len(),
            ArrayData::U8(v) => v.len(),
            ArrayData::I8(v) => v.len(),
            ArrayData::U16(v) | ArrayData::F16(v) => v.len(),
            ArrayData::I16(v) => v.len(),
            ArrayData::U32(v) => v.len(),
            ArrayData::I32(v) => v.len(),
            ArrayData::U64(v) => v.len(),
            ArrayData::I64(v) => v.len(),
            ArrayData::F32(v) => v.len(),
            ArrayData::F64(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every element as f64 (64-bit integers beyond 2^53 round; bools are 0 / 1).
    pub fn to_f64(&self) -> Vec<f64> {
        match &self.data {
            ArrayData::Bool(v) => v.iter().map(|&b| f64::from(u8::from(b))).collect(),
            ArrayData::U8(v) => v.iter().map(|&x| x.into()).collect(),
            ArrayData::I8(v) => v.iter().map(|&x| x.into()).collect(),
            ArrayData::U16(v) => v.iter().map(|&x| x.into()).collect(),
            ArrayData::I16(v) => v.iter().map(|&x| x.into()).collect(),
            ArrayData::U32(v) => v.iter().map(|&x| x.into()).collect(),
            ArrayData::I32(v) => v.iter().map(|&x| x.into()).collect(),
            ArrayData::U64(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::F16(v) => v.iter().map(|&h| f16_to_f64(h)).collect(),
            ArrayData::F32(v) => v.iter().map(|&x| x.into()).collect(),
            ArrayData::F64(v) => v.clone(),
        }
    }

    /// The elements as little-endian bytes, row-major (bools as 0 / 1).
    pub fn to_le_bytes(&self) -> Vec<u8> {
        fn cat<T: Copy, const N: usize>(v: &[T], f: impl Fn(T) -> [u8; N]) -> Vec<u8> {
            v.iter().flat_map(|&x| f(x)).collect()
        }
        match &self.data {
            ArrayData::Bool(v) => v.iter().map(|&b| u8::from(b)).collect(),
            ArrayData::U8(v) => v.clone(),
            ArrayData::I8(v) => cat(v, i8::to_le_bytes),
            ArrayData::U16(v) | ArrayData::F16(v) => cat(v, u16::to_le_bytes),
            ArrayData::I16(v) => cat(v, i16::to_le_bytes),
            ArrayData::U32(v) => cat(v, u32::to_le_bytes),
            ArrayData::I32(v) => cat(v, i32::to_le_bytes),
            ArrayData::U64(v) => cat(v, u64::to_le_bytes),
            ArrayData::I64(v) => cat(v, i64::to_le_bytes),
            ArrayData::F32(v) => cat(v, f32::to_le_bytes),
            ArrayData::F64(v) => cat(v, f64::to_le_bytes),
        }
    }
}

/// IEEE 754 binary16 to f64 (exact).
pub fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = i32::from((h >> 10) & 0x1f);
    let frac = f64::from(h & 0x3ff);
    match exp {
        0 => sign * frac * 2f64.powi(-24),
        0x1f if frac == 0.0 => sign * f64::INFINITY,
        0x1f => f64::NAN,
        e => sign * (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

/// Raw element bytes to typed, machine-order elements. `charge` is told the byte count first
/// and may refuse it (a budget on what a hostile file makes us allocate).
pub fn decode_elements(
    raw: &[u8],
    elem: DType,
    big_endian: bool,
    numel: usize,
    charge: &mut dyn FnMut(usize) -> Result<(), String>,
) -> Result<ArrayData, String> {
    let size = elem.size();
    let want = numel.checked_mul(size).ok_or("array byte size overflows")?;
    if raw.len() != want {
        return Err(format!(
            "array data has {} bytes, expected {want} ({numel} elements of {})",
            raw.len(),
            elem.numpy_code()
        ));
    }
    charge(want)?;
    fn conv<T, const N: usize>(raw: &[u8], be: bool, f: fn([u8; N], bool) -> T) -> Vec<T> {
        raw.chunks_exact(N)
            .map(|c| {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                f(a, be)
            })
            .collect()
    }
    macro_rules! num {
        ($t:ty) => {
            |a, be| {
                if be {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }
            }
        };
    }
    Ok(match elem {
        DType::Bool => {
            let mut v = Vec::with_capacity(raw.len());
            for &b in raw {
                match b {
                    0 => v.push(false),
                    1 => v.push(true),
                    other => return Err(format!("bool array holds the byte {other} (not 0 or 1)")),
                }
            }
            ArrayData::Bool(v)
        }
        DType::U8 => ArrayData::U8(raw.to_vec()),
        DType::I8 => ArrayData::I8(raw.iter().map(|&b| b as i8).collect()),
        DType::U16 => ArrayData::U16(conv(raw, big_endian, num!(u16))),
        DType::I16 => ArrayData::I16(conv(raw, big_endian, num!(i16))),
        DType::U32 => ArrayData::U32(conv(raw, big_endian, num!(u32))),
        DType::I32 => ArrayData::I32(conv(raw, big_endian, num!(i32))),
        DType::U64 => ArrayData::U64(conv(raw, big_endian, num!(u64))),
        DType::I64 => ArrayData::I64(conv(raw, big_endian, num!(i64))),
        DType::F16 => ArrayData::F16(conv(raw, big_endian, num!(u16))),
        DType::F32 => ArrayData::F32(conv(raw, big_endian, num!(f32))),
        DType::F64 => ArrayData::F64(conv(raw, big_endian, num!(f64))),
    })
}

/// Column-major elements to row-major.
pub fn fortran_to_c(data: ArrayData, shape: &[usize]) -> ArrayData {
    if shape.len() < 2 {
        return data;
    }
    fn perm<T: Copy>(v: Vec<T>, shape: &[usize]) -> Vec<T> {
        let n = v.len();
        if n == 0 {
            return v;
        }
        // Fortran strides (in elements) of each axis.
        let mut fstride = vec![1usize; shape.len()];
        for d in 1..shape.len() {
            fstride[d] = fstride[d - 1] * shape[d - 1];
        }
        let mut out = Vec::with_capacity(n);
        let mut idx = vec![0usize; shape.len()];
        for _ in 0..n {
            let src: usize = idx.iter().zip(&fstride).map(|(i, s)| i * s).sum();
            out.push(v[src]);
            for d in (0..shape.len()).rev() {
                idx[d] += 1;
                if idx[d] < shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        out
    }
    match data {
        ArrayData::Bool(v) => ArrayData::Bool(perm(v, shape)),
        ArrayData::U8(v) => ArrayData::U8(perm(v, shape)),
        ArrayData::I8(v) => ArrayData::I8(perm(v, shape)),
        ArrayData::U16(v) => ArrayData::U16(perm(v, shape)),
        ArrayData::I16(v) => ArrayData::I16(perm(v, shape)),
        ArrayData::U32(v) => ArrayData::U32(perm(v, shape)),
        ArrayData::I32(v) => ArrayData::I32(perm(v, shape)),
        ArrayData::U64(v) => ArrayData::U64(perm(v, shape)),
        ArrayData::I64(v) => ArrayData::I64(perm(v, shape)),
        ArrayData::F16(v) => ArrayData::F16(perm(v, shape)),
        ArrayData::F32(v) => ArrayData::F32(perm(v, shape)),
        ArrayData::F64(v) => ArrayData::F64(perm(v, shape)),
    }
}
