//! Writes plain data ([`PyValue`]) as a protocol 4 pickle that CPython + numpy load.
//!
//! Arrays are written as numpy pickles them (`_reconstruct` + BUILD state), under the numpy 1.x
//! module name `numpy.core.multiarray`: numpy 1.x only knows that name, and numpy 2.x still
//! resolves it for old pickles (checked with numpy 2.1.3, warnings as errors). The stream has no
//! FRAME opcodes (framing is optional for the unpickler) and memoizes only the numpy globals
//! and dtypes, which are shared by every array.

use std::collections::HashMap;

use crate::numpy::{ArrayData, DType, NdArray};
use crate::pickle::plain::{DictKey, PyValue};

mod op {
    pub const PROTO: u8 = 0x80;
    pub const STOP: u8 = b'.';
    pub const MARK: u8 = b'(';
    pub const NONE: u8 = b'N';
    pub const NEWTRUE: u8 = 0x88;
    pub const NEWFALSE: u8 = 0x89;
    pub const BININT1: u8 = b'K';
    pub const BININT2: u8 = b'M';
    pub const BININT: u8 = b'J';
    pub const LONG1: u8 = 0x8a;
    pub const BINFLOAT: u8 = b'G';
    pub const SHORT_BINUNICODE: u8 = 0x8c;
    pub const BINUNICODE: u8 = b'X';
    pub const BINUNICODE8: u8 = 0x8d;
    pub const SHORT_BINBYTES: u8 = b'C';
    pub const BINBYTES: u8 = b'B';
    pub const BINBYTES8: u8 = 0x8e;
    pub const EMPTY_LIST: u8 = b']';
    pub const APPENDS: u8 = b'e';
    pub const EMPTY_DICT: u8 = b'}';
    pub const SETITEMS: u8 = b'u';
    pub const EMPTY_TUPLE: u8 = b')';
    pub const TUPLE: u8 = b't';
    pub const TUPLE1: u8 = 0x85;
    pub const TUPLE2: u8 = 0x86;
    pub const TUPLE3: u8 = 0x87;
    pub const GLOBAL: u8 = b'c';
    pub const REDUCE: u8 = b'R';
    pub const BUILD: u8 = b'b';
    pub const MEMOIZE: u8 = 0x94;
    pub const BINGET: u8 = b'h';
    pub const LONG_BINGET: u8 = b'j';
}

/// Items per APPENDS / SETITEMS batch, as CPython's pickler does.
const BATCH: usize = 1000;
/// Nesting written before giving up (our own data never comes close).
const MAX_DEPTH: usize = 64;

/// Serialises plain data. Fails only on nesting deeper than 64 levels.
pub fn to_pickle(value: &PyValue) -> Result<Vec<u8>, String> {
    let mut w = Writer {
        out: vec![op::PROTO, 4],
        memo: HashMap::new(),
    };
    w.value(value, 0)?;
    w.out.push(op::STOP);
    Ok(w.out)
}

struct Writer {
    out: Vec<u8>,
    /// Memo index of each memoized global / dtype, by a name of our choosing.
    memo: HashMap<String, u32>,
}

impl Writer {
    fn value(&mut self, v: &PyValue, depth: usize) -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err(format!("values nested more than {MAX_DEPTH} deep"));
        }
        match v {
            PyValue::None => self.out.push(op::NONE),
            PyValue::Bool(b) => self.out.push(if *b { op::NEWTRUE } else { op::NEWFALSE }),
            PyValue::Int(i) => self.int(*i),
            PyValue::Float(f) => {
                self.out.push(op::BINFLOAT);
                self.out.extend_from_slice(&f.to_be_bytes());
            }
            PyValue::Str(s) => self.str(s),
            PyValue::Bytes(b) => self.bytes(b),
            PyValue::List(items) => {
                self.out.push(op::EMPTY_LIST);
                for chunk in items.chunks(BATCH) {
                    self.out.push(op::MARK);
                    for item in chunk {
                        self.value(item, depth + 1)?;
                    }
                    self.out.push(op::APPENDS);
                }
            }
            PyValue::Dict(entries) => {
                self.out.push(op::EMPTY_DICT);
                for chunk in entries.chunks(BATCH) {
                    self.out.push(op::MARK);
                    for (k, item) in chunk {
                        match k {
                            DictKey::Str(s) => self.str(s),
                            DictKey::Int(i) => self.int(*i),
                        }
                        self.value(item, depth + 1)?;
                    }
                    self.out.push(op::SETITEMS);
                }
            }
            PyValue::Array(a) => self.array(a),
        }
        Ok(())
    }

    fn int(&mut self, i: i64) {
        if let Ok(b) = u8::try_from(i) {
            self.out.extend([op::BININT1, b]);
        } else if let Ok(h) = u16::try_from(i) {
            self.out.push(op::BININT2);
            self.out.extend_from_slice(&h.to_le_bytes());
        } else if let Ok(w) = i32::try_from(i) {
            self.out.push(op::BININT);
            self.out.extend_from_slice(&w.to_le_bytes());
        } else {
            // Shortest little-endian two's complement.
            let bytes = i.to_le_bytes();
            let mut n = 8;
            while n > 1 {
                let top = bytes[n - 1];
                let next_sign = bytes[n - 2] & 0x80 != 0;
                if (top == 0 && !next_sign) || (top == 0xff && next_sign) {
                    n -= 1;
                } else {
                    break;
                }
            }
            self.out.extend([op::LONG1, n as u8]);
            self.out.extend_from_slice(&bytes[..n]);
        }
    }

    fn str(&mut self, s: &str) {
        let b = s.as_bytes();
        if let Ok(n) = u8::try_from(b.len()) {
            self.out.extend([op::SHORT_BINUNICODE, n]);
        } else if let Ok(n) = u32::try_from(b.len()) {
            self.out.push(op::BINUNICODE);
            self.out.extend_from_slice(&n.to_le_bytes());
        } else {
            self.out.push(op::BINUNICODE8);
            self.out.extend_from_slice(&(b.len() as u64).to_le_bytes());
        }
        self.out.extend_from_slice(b);
    }

    fn bytes(&mut self, b: &[u8]) {
        if let Ok(n) = u8::try_from(b.len()) {
            self.out.extend([op::SHORT_BINBYTES, n]);
        } else if let Ok(n) = u32::try_from(b.len()) {
            self.out.push(op::BINBYTES);
            self.out.extend_from_slice(&n.to_le_bytes());
        } else {
            self.out.push(op::BINBYTES8);
            self.out.extend_from_slice(&(b.len() as u64).to_le_bytes());
        }
        self.out.extend_from_slice(b);
    }

    fn get(&mut self, index: u32) {
        if let Ok(i) = u8::try_from(index) {
            self.out.extend([op::BINGET, i]);
        } else {
            self.out.push(op::LONG_BINGET);
            self.out.extend_from_slice(&index.to_le_bytes());
        }
    }

    /// Pushes a memoized object, writing it with `make` the first time.
    fn memoized(&mut self, name: &str, make: impl FnOnce(&mut Self)) {
        if let Some(&i) = self.memo.get(name) {
            self.get(i);
            return;
        }
        make(self);
        let index = self.memo.len() as u32;
        self.out.push(op::MEMOIZE);
        self.memo.insert(name.to_owned(), index);
    }

    fn global(&mut self, module: &str, name: &str) {
        self.memoized(&format!("global {module}.{name}"), |w| {
            w.out.push(op::GLOBAL);
            w.out.extend_from_slice(module.as_bytes());
            w.out.push(b'\n');
            w.out.extend_from_slice(name.as_bytes());
            w.out.push(b'\n');
        });
    }

    /// `numpy.dtype(code, False, True)` with numpy's version-3 state.
    fn dtype(&mut self, dtype: DType) {
        let code = dtype.numpy_code();
        let order = if dtype.size() == 1 { "|" } else { "<" };
        self.memoized(&format!("dtype {order}{code}"), |w| {
            w.global("numpy", "dtype");
            w.str(code);
            w.out
                .extend([op::NEWFALSE, op::NEWTRUE, op::TUPLE3, op::REDUCE]);
            w.out.push(op::MARK);
            w.int(3);
            w.str(order);
            w.out.extend([op::NONE, op::NONE, op::NONE]);
            w.int(-1);
            w.int(-1);
            w.int(0);
            w.out.extend([op::TUPLE, op::BUILD]);
        });
    }

    fn array(&mut self, a: &NdArray) {
        self.global("numpy.core.multiarray", "_reconstruct");
        self.global("numpy", "ndarray");
        self.int(0);
        self.out.push(op::TUPLE1);
        self.bytes(b"b");
        self.out.extend([op::TUPLE3, op::REDUCE]);
        // BUILD state: (1, shape, dtype, is_fortran, data)
        self.out.push(op::MARK);
        self.int(1);
        match a.shape.len() {
            0 => self.out.push(op::EMPTY_TUPLE),
            n => {
                let short = n <= 3;
                if !short {
                    self.out.push(op::MARK);
                }
                for &d in &a.shape {
                    self.int(d as i64);
                }
                self.out.push(match n {
                    1 => op::TUPLE1,
                    2 => op::TUPLE2,
                    3 => op::TUPLE3,
                    _ => op::TUPLE,
                });
            }
        }
        self.dtype(a.dtype());
        self.out.push(op::NEWFALSE);
        let raw = match &a.data {
            ArrayData::U8(v) => std::borrow::Cow::Borrowed(v.as_slice()),
            _ => std::borrow::Cow::Owned(a.to_le_bytes()),
        };
        self.bytes(&raw);
        self.out.extend([op::TUPLE, op::BUILD]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pickle::plain::parse_pickle;

    #[test]
    fn values_round_trip_through_our_reader() {
        let arr = |shape: Vec<usize>, data| PyValue::Array(NdArray { shape, data });
        let v = PyValue::Dict(vec![
            (
                DictKey::Str("ints".into()),
                PyValue::List(
                    [
                        0i64,
                        1,
                        255,
                        256,
                        65535,
                        65536,
                        -1,
                        -129,
                        i32::MAX as i64,
                        i32::MIN as i64,
                        1 << 40,
                        -(1 << 40),
                        i64::MAX,
                        i64::MIN,
                    ]
                    .into_iter()
                    .map(PyValue::Int)
                    .collect(),
                ),
            ),
            (DictKey::Int(7), PyValue::Float(-0.1)),
            (DictKey::Str("s".repeat(300)), PyValue::Str("é".repeat(200))),
            (
                DictKey::Str("b".into()),
                PyValue::Bytes((0..=255).collect()),
            ),
            (
                DictKey::Str("n".into()),
                PyValue::List(vec![
                    PyValue::None,
                    PyValue::Bool(true),
                    PyValue::Bool(false),
                ]),
            ),
            (
                DictKey::Str("f32".into()),
                arr(
                    vec![2, 3],
                    ArrayData::F32(vec![1.0, -2.5, 3.25, 0.0, 1e-30, 7.0]),
                ),
            ),
            (
                DictKey::Str("f64".into()),
                arr(vec![], ArrayData::F64(vec![std::f64::consts::PI])),
            ),
            (
                DictKey::Str("u8".into()),
                arr(vec![1, 1, 1, 1, 3], ArrayData::U8(vec![1, 2, 3])),
            ),
            (
                DictKey::Str("bool".into()),
                arr(vec![2], ArrayData::Bool(vec![true, false])),
            ),
            (
                DictKey::Str("i16".into()),
                arr(vec![0, 4], ArrayData::I16(vec![])),
            ),
            (
                DictKey::Str("f16".into()),
                arr(vec![1], ArrayData::F16(vec![0x3c00])),
            ),
            (
                DictKey::Str("many".into()),
                PyValue::List((0..2500).map(PyValue::Int).collect()),
            ),
        ]);
        let bytes = to_pickle(&v).unwrap();
        let back = parse_pickle(&bytes).unwrap();
        assert_eq!(back, v);
    }
}
