//! Plain data out of a Python pickle: dicts, lists, strings, numbers, bytes and numpy arrays.
//!
//! The stream is parsed by [`crate::pickle::read`] (data-only: nothing is imported or
//! called), then walked into a [`PyValue`]. The walk knows exactly these callables:
//!
//! * numpy arrays as numpy 1.x and 2.x pickle them: `numpy.core.multiarray._reconstruct` /
//!   `numpy._core.multiarray._reconstruct` of `numpy.ndarray` followed by a BUILD state
//!   `(version, shape, dtype, fortran, data)`, and protocol 5's
//!   `numpy[._]core.numeric._frombuffer(buffer, dtype, shape, order)`; the dtype is a
//!   `numpy.dtype(code, align, copy)` call whose BUILD state carries the byte order;
//! * numpy scalars (`numpy[._]core.multiarray.scalar(dtype, bytes)`), read as plain numbers;
//! * how Python 3 spells `bytes` / `bytearray` in protocols 0-2 (`_codecs.encode(text,
//!   "latin1")`, `builtins.bytes()`, `builtins.bytearray(...)`);
//! * `collections.OrderedDict`, read as a dict.
//!
//! Anything else (a class, a function, a torch tensor, a set) is an error naming it. The tree
//! may share sub-trees and contain cycles: the walk is depth-bounded, refuses cycles and has a
//! budget on visited values and on array bytes, both growing with the input size.

use std::collections::HashMap;
use std::path::Path;

use crate::error::{label_of, FormatError, Result};
use crate::numpy::{decode_elements, f16_to_f64, fortran_to_c, ArrayData, DType, NdArray};
use crate::pickle::read::{self as pickle, Id, Limits, Object, Pickle, Value};

/// A plain Python value.
#[derive(Debug, Clone, PartialEq)]
pub enum PyValue {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    /// `bytes` and `bytearray`.
    Bytes(Vec<u8>),
    /// Lists and tuples.
    List(Vec<PyValue>),
    /// Entries in insertion order, keys unique (a repeated key keeps its first position and its
    /// last value, as Python's dict assignment does).
    Dict(Vec<(DictKey, PyValue)>),
    Array(NdArray),
}

#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum DictKey {
    Str(String),
    Int(i64),
}

impl std::fmt::Display for DictKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DictKey::Str(s) => write!(f, "{s:?}"),
            DictKey::Int(i) => write!(f, "{i}"),
        }
    }
}

impl PyValue {
    /// The value under a string key, if this is a dict holding it.
    pub fn get(&self, key: &str) -> Option<&PyValue> {
        match self {
            PyValue::Dict(entries) => entries.iter().find_map(|(k, v)| match k {
                DictKey::Str(s) if s == key => Some(v),
                _ => None,
            }),
            _ => None,
        }
    }

    /// The Python-side type with an article ("an int", "a dict"), for error messages.
    pub fn kind(&self) -> &'static str {
        match self {
            PyValue::None => "None",
            PyValue::Bool(_) => "a bool",
            PyValue::Int(_) => "an int",
            PyValue::Float(_) => "a float",
            PyValue::Str(_) => "a str",
            PyValue::Bytes(_) => "bytes",
            PyValue::List(_) => "a list",
            PyValue::Dict(_) => "a dict",
            PyValue::Array(_) => "a numpy array",
        }
    }
}

/// Reads a pickle file into plain data.
pub fn read_pickle(path: &Path) -> Result<PyValue> {
    let data = std::fs::read(path).map_err(FormatError::io(path, "cannot read"))?;
    parse_pickle(&data).map_err(|reason| FormatError::Pickle {
        label: label_of(path),
        reason,
    })
}

/// Parses pickle bytes into plain data; the error is one line without the file name.
pub fn parse_pickle(data: &[u8]) -> std::result::Result<PyValue, String> {
    let parsed = pickle::parse_with_limits(data, limits_for(data.len()))
        .map_err(|e| format!("not a readable pickle: {e}"))?;
    let mut walk = Walk {
        p: &parsed,
        ancestors: Vec::new(),
        visits: 0,
        max_visits: MIN_VISITS.saturating_add(data.len()),
        array_bytes: 0,
        max_array_bytes: MIN_ARRAY_BYTES.saturating_add(data.len().saturating_mul(8)),
    };
    walk.value(parsed.root()).map_err(|f| f.render())
}

/// Container nesting followed (optim.pkl nests 2 deep).
const MAX_DEPTH: usize = 64;
/// Visit budget floor; it grows by one per input byte, since every value a sane pickle holds
/// costs at least one byte, while shared sub-trees of a hostile one could describe an
/// exponentially large tree.
const MIN_VISITS: usize = 1 << 22;
/// Array bytes materialised, floor; grows by 8 per input byte (shared arrays are copied per
/// reference).
const MIN_ARRAY_BYTES: usize = 64 << 20;

/// Parser caps that grow with the input: a release `optim.pkl` of many thousand frames has more
/// values than the checkpoint-sized defaults allow, and a sane pickle spends at least a few bytes
/// per value.
fn limits_for(len: usize) -> Limits {
    let d = Limits::default();
    Limits {
        max_values: d.max_values.max(len / 4),
        max_memo: d.max_memo.max(len / 4),
        max_stack: d.max_stack.max(len / 4),
        max_items: d.max_items.max(len / 2),
        ..d
    }
}

/// A failure and where in the tree it happened (outermost step last while unwinding).
struct Fail {
    location: Vec<String>,
    message: String,
}

impl Fail {
    fn new(message: impl Into<String>) -> Self {
        Fail {
            location: Vec::new(),
            message: message.into(),
        }
    }

    fn at(mut self, step: String) -> Self {
        self.location.push(step);
        self
    }

    fn render(self) -> String {
        if self.location.is_empty() {
            return self.message;
        }
        let mut loc = String::from("root");
        for step in self.location.iter().rev() {
            loc.push_str(step);
        }
        format!("at {loc}: {}", self.message)
    }
}

type F<T> = std::result::Result<T, Fail>;

const NUMPY_CORE: [&str; 2] = ["numpy.core", "numpy._core"];

fn is_numpy(module: &str, submodule: &str) -> bool {
    NUMPY_CORE.iter().any(|core| {
        module
            .strip_prefix(core)
            .and_then(|rest| rest.strip_prefix('.'))
            .is_some_and(|rest| rest == submodule)
    })
}

fn refuse_global(module: &str, name: &str) -> Fail {
    if module == "torch" || module.starts_with("torch.") {
        Fail::new(format!(
            "`{module}.{name}` is a torch object (a tensor?): only numpy arrays and plain \
             Python data are read; convert tensors with `.numpy()` before pickling"
        ))
    } else {
        Fail::new(format!(
            "`{module}.{name}` is not allowed: only dicts, lists, strings, numbers and numpy \
             arrays are read (nothing in the file is imported or run)"
        ))
    }
}

/// A numpy dtype as pickled: element type (None = object) and byte order.
#[derive(Debug, Clone, Copy)]
struct DTypeSpec {
    elem: Option<DType>,
    big_endian: bool,
}

struct Walk<'p> {
    p: &'p Pickle,
    ancestors: Vec<Id>,
    visits: usize,
    max_visits: usize,
    array_bytes: usize,
    max_array_bytes: usize,
}

impl<'p> Walk<'p> {
    fn value(&mut self, id: Id) -> F<PyValue> {
        self.visits += 1;
        if self.visits > self.max_visits {
            return Err(Fail::new(format!(
                "the pickle's containers reach more than {} values (shared sub-trees?)",
                self.max_visits
            )));
        }
        let p = self.p;
        Ok(match p.get(id) {
            Value::None => PyValue::None,
            Value::Bool(b) => PyValue::Bool(*b),
            Value::Int(i) => PyValue::Int(*i),
            Value::BigInt(s) => {
                return Err(Fail::new(format!(
                    "the integer {s} does not fit in 64 bits"
                )))
            }
            Value::Float(f) => PyValue::Float(*f),
            Value::Str(s) => PyValue::Str(s.clone()),
            Value::Bytes(b) => PyValue::Bytes(b.clone()),
            Value::List(items) | Value::Tuple(items) => {
                self.enter(id)?;
                let mut out = Vec::with_capacity(items.len().min(1 << 16));
                for (i, &item) in items.iter().enumerate() {
                    out.push(self.value(item).map_err(|f| f.at(format!("[{i}]")))?);
                }
                self.leave();
                PyValue::List(out)
            }
            Value::Dict(entries) => {
                self.enter(id)?;
                let d = self.dict(entries)?;
                self.leave();
                d
            }
            Value::Set(_) | Value::FrozenSet(_) => {
                return Err(Fail::new("a set is not supported (only dicts and lists)"))
            }
            Value::Global(g) => return Err(refuse_global(&g.module, &g.name)),
            Value::PersistentId(_) => {
                return Err(Fail::new(
                    "a persistent reference (data outside the pickle, as in torch files) is \
                     not supported",
                ))
            }
            Value::Object(o) => {
                self.enter(id)?;
                let v = self.object(o)?;
                self.leave();
                v
            }
        })
    }

    fn enter(&mut self, id: Id) -> F<()> {
        if self.ancestors.contains(&id) {
            return Err(Fail::new(
                "a container contains itself (reference cycle); plain data has none",
            ));
        }
        if self.ancestors.len() >= MAX_DEPTH {
            return Err(Fail::new(format!(
                "containers nested more than {MAX_DEPTH} deep"
            )));
        }
        self.ancestors.push(id);
        Ok(())
    }

    fn leave(&mut self) {
        self.ancestors.pop();
    }

    fn dict(&mut self, entries: &[(Id, Id)]) -> F<PyValue> {
        let mut out: Vec<(DictKey, PyValue)> = Vec::with_capacity(entries.len().min(1 << 16));
        let mut index: HashMap<DictKey, usize> = HashMap::new();
        for &(k, v) in entries {
            let key = match self.p.get(k) {
                Value::Str(s) => DictKey::Str(s.clone()),
                Value::Int(i) => DictKey::Int(*i),
                _ => {
                    return Err(Fail::new(format!(
                        "a dict key is {}; only string and integer keys are supported",
                        self.p.describe(k)
                    )))
                }
            };
            let value = self.value(v).map_err(|f| f.at(format!("[{key}]")))?;
            match index.get(&key) {
                Some(&at) => out[at].1 = value,
                None => {
                    index.insert(key.clone(), out.len());
                    out.push((key, value));
                }
            }
        }
        Ok(PyValue::Dict(out))
    }

    fn global_of(&self, id: Id) -> Option<(&'p str, &'p str)> {
        self.p.global(id)
    }

    fn args(&self, o: &Object) -> F<&'p [Id]> {
        match self.p.get(o.args) {
            Value::Tuple(a) => Ok(a.as_slice()),
            _ => Err(Fail::new("call arguments are not a tuple")),
        }
    }

    fn object(&mut self, o: &Object) -> F<PyValue> {
        let Some((module, name)) = self.global_of(o.callable) else {
            return Err(Fail::new(format!(
                "a call of {} is not supported",
                self.p.describe(o.callable)
            )));
        };
        let plain_call = o.kwargs.is_none() && o.items.is_empty() && o.elems.is_empty();
        let what = format!("`{module}.{name}`");
        match (module, name) {
            (m, "_reconstruct") if is_numpy(m, "multiarray") => self.reconstruct(o),
            (m, "_frombuffer") if is_numpy(m, "numeric") => {
                if !plain_call || o.state.is_some() {
                    return Err(Fail::new(format!("{what} with extra state")));
                }
                self.frombuffer(o)
            }
            (m, "scalar") if is_numpy(m, "multiarray") => {
                if !plain_call || o.state.is_some() {
                    return Err(Fail::new(format!("{what} with extra state")));
                }
                self.scalar(o)
            }
            ("_codecs", "encode")
            | ("builtins" | "__builtin__", "bytes")
            | ("builtins" | "__builtin__", "bytearray") => {
                if !plain_call || o.state.is_some() {
                    return Err(Fail::new(format!("{what} with extra state")));
                }
                Ok(PyValue::Bytes(self.bytes_call(module, name, o)?))
            }
            ("collections", "OrderedDict") => self.ordered_dict(o),
            ("numpy", "dtype") => Err(Fail::new(
                "a numpy dtype object outside an array is not supported",
            )),
            ("numpy", "ndarray") => Err(Fail::new(
                "a `numpy.ndarray` call outside `_reconstruct` is not supported",
            )),
            _ => Err(refuse_global(module, name)),
        }
    }

    /// `_codecs.encode(text, "latin1")`, `bytes()`, `bytearray(...)`: Python 3's spelling of
    /// byte strings in protocols 0-2.
    fn bytes_call(&mut self, module: &str, name: &str, o: &Object) -> F<Vec<u8>> {
        let p = self.p;
        let args = self.args(o)?;
        let arg = |i: usize| args.get(i).map(|&a| p.get(a));
        let latin1 = |s: &str| -> F<Vec<u8>> {
            s.chars()
                .map(|c| {
                    u8::try_from(u32::from(c)).map_err(|_| {
                        Fail::new(format!("`{module}.{name}`: a character beyond Latin-1"))
                    })
                })
                .collect()
        };
        let is_latin1 = |v: Option<&Value>| matches!(v, Some(Value::Str(e)) if matches!(e.to_ascii_lowercase().as_str(), "latin1" | "latin-1" | "iso-8859-1"));
        match (name, args.len(), arg(0)) {
            (_, 0, _) if name != "encode" => Ok(Vec::new()),
            ("encode" | "bytearray", 2, Some(Value::Str(s))) if is_latin1(arg(1)) => {
                latin1(s.as_str())
            }
            ("bytearray" | "bytes", 1, Some(Value::Bytes(b))) => Ok(b.clone()),
            ("bytearray" | "bytes", 1, Some(Value::Object(_))) => {
                // protocol 2: bytearray(_codecs.encode(...)) is not what CPython writes, but
                // harmless to accept.
                match self.value(args[0])? {
                    PyValue::Bytes(b) => Ok(b),
                    other => Err(Fail::new(format!("`{module}.{name}` of {}", other.kind()))),
                }
            }
            _ => Err(Fail::new(format!(
                "`{module}.{name}` with unsupported arguments {}",
                p.describe(o.args)
            ))),
        }
    }

    fn ordered_dict(&mut self, o: &Object) -> F<PyValue> {
        let p = self.p;
        let args = self.args(o)?;
        if o.state.is_some() || !o.elems.is_empty() || o.kwargs.is_some() {
            return Err(Fail::new("`collections.OrderedDict` with extra state"));
        }
        let mut entries: Vec<(Id, Id)> = Vec::new();
        match args {
            [] => {}
            // Protocols 0-1: OrderedDict([[k, v], ...]).
            [items] => match p.get(*items) {
                Value::List(pairs) => {
                    for &pair in pairs {
                        match p.get(pair) {
                            Value::List(kv) | Value::Tuple(kv) if kv.len() == 2 => {
                                entries.push((kv[0], kv[1]))
                            }
                            _ => {
                                return Err(Fail::new(
                                    "`collections.OrderedDict` item is not a pair",
                                ))
                            }
                        }
                    }
                }
                _ => return Err(Fail::new("`collections.OrderedDict` of a non-list")),
            },
            _ => {
                return Err(Fail::new(
                    "`collections.OrderedDict` with several arguments",
                ))
            }
        }
        entries.extend_from_slice(&o.items);
        self.dict(&entries)
    }

    /// Bytes-like array or scalar payload: `bytes`, a protocol 0-2 `_codecs.encode` call, or
    /// (Python 2 pickles) text, usable only when it decoded losslessly.
    fn payload(&mut self, id: Id) -> F<Vec<u8>> {
        match self.p.get(id) {
            Value::Bytes(b) => Ok(b.clone()),
            Value::Object(_) => match self.value(id)? {
                PyValue::Bytes(b) => Ok(b),
                other => Err(Fail::new(format!(
                    "array data is {}, not bytes",
                    other.kind()
                ))),
            },
            Value::Str(s) if !s.contains(char::REPLACEMENT_CHARACTER) => Ok(s.as_bytes().to_vec()),
            Value::Str(_) => Err(Fail::new(
                "array data is a Python 2 byte string with non-UTF-8 bytes, which this reader \
                 cannot recover; re-save the pickle with Python 3",
            )),
            _ => Err(Fail::new(format!(
                "array data is {}, not bytes",
                self.p.describe(id)
            ))),
        }
    }

    fn dtype(&self, id: Id) -> F<DTypeSpec> {
        let p = self.p;
        let Value::Object(o) = p.get(id) else {
            return Err(Fail::new(format!(
                "array dtype is {}, not a numpy dtype",
                p.describe(id)
            )));
        };
        if self.global_of(o.callable) != Some(("numpy", "dtype")) {
            return Err(Fail::new(format!(
                "array dtype is made by {}, not `numpy.dtype`",
                p.describe(o.callable)
            )));
        }
        let args = self.args(o)?;
        let code = match args.first().map(|&a| p.get(a)) {
            Some(Value::Str(s)) => s.as_str(),
            _ => return Err(Fail::new("numpy dtype without a type code")),
        };
        // Older pickles may spell the byte order in the code itself.
        let (code_order, code) = match code.as_bytes().first() {
            Some(b'<' | b'>' | b'|' | b'=') => (code.chars().next(), &code[1..]),
            _ => (None, code),
        };
        let elem = match code {
            "b1" | "?" => Some(DType::Bool),
            "u1" => Some(DType::U8),
            "i1" => Some(DType::I8),
            "u2" => Some(DType::U16),
            "i2" => Some(DType::I16),
            "u4" => Some(DType::U32),
            "i4" => Some(DType::I32),
            "u8" => Some(DType::U64),
            "i8" => Some(DType::I64),
            "f2" => Some(DType::F16),
            "f4" => Some(DType::F32),
            "f8" => Some(DType::F64),
            "O4" | "O8" => None,
            other => {
                let what = match other.as_bytes().first() {
                    Some(b'c') => "complex numbers",
                    Some(b'S' | b'a') => "byte strings",
                    Some(b'U') => "text",
                    Some(b'V') => "structured records",
                    Some(b'M' | b'm') => "dates or times",
                    Some(b'f') => "an extended-precision float",
                    _ => "an unknown type",
                };
                return Err(Fail::new(format!(
                    "numpy dtype `{other}` ({what}) is not supported"
                )));
            }
        };
        let mut order = code_order;
        if let Some(state) = o.state {
            let Value::Tuple(st) = p.get(state) else {
                return Err(Fail::new("numpy dtype state is not a tuple"));
            };
            if st.len() < 5 {
                return Err(Fail::new("numpy dtype state has fewer than 5 items"));
            }
            match p.get(st[1]) {
                Value::Str(s) if s.chars().count() == 1 => order = s.chars().next(),
                _ => return Err(Fail::new("numpy dtype byte order is not one character")),
            }
            if !matches!(p.get(st[2]), Value::None) {
                return Err(Fail::new("numpy sub-array dtypes are not supported"));
            }
            if !matches!(p.get(st[3]), Value::None) || !matches!(p.get(st[4]), Value::None) {
                return Err(Fail::new(
                    "structured numpy dtypes (named fields) are not supported",
                ));
            }
        }
        let big_endian = match order {
            Some('>') => true,
            // '=' is the writing machine's order: in practice always little-endian.
            Some('<' | '=' | '|') | None => false,
            Some(c) => return Err(Fail::new(format!("numpy byte order {c:?} is unknown"))),
        };
        Ok(DTypeSpec { elem, big_endian })
    }

    fn shape(&self, id: Id) -> F<Vec<usize>> {
        let p = self.p;
        let items = match p.get(id) {
            Value::Tuple(t) | Value::List(t) => t,
            // `_frombuffer` of a 1-D array may get a bare int.
            Value::Int(_) => std::slice::from_ref(&id),
            _ => {
                return Err(Fail::new(format!(
                    "array shape is {}, not a tuple",
                    p.describe(id)
                )))
            }
        };
        items
            .iter()
            .map(|&d| match p.get(d) {
                Value::Int(n) if *n >= 0 => usize::try_from(*n)
                    .map_err(|_| Fail::new(format!("array dimension {n} is too large"))),
                _ => Err(Fail::new(format!(
                    "array dimension {} is not a non-negative integer",
                    p.describe(d)
                ))),
            })
            .collect()
    }

    fn numel(shape: &[usize]) -> F<usize> {
        shape.iter().try_fold(1usize, |acc, &d| {
            acc.checked_mul(d)
                .ok_or_else(|| Fail::new(format!("array shape {shape:?} overflows")))
        })
    }

    fn charge(&mut self, bytes: usize) -> F<()> {
        self.array_bytes = self.array_bytes.saturating_add(bytes);
        if self.array_bytes > self.max_array_bytes {
            return Err(Fail::new(format!(
                "arrays totalling more than {} bytes (shared arrays count once per reference)",
                self.max_array_bytes
            )));
        }
        Ok(())
    }

    /// `_reconstruct(ndarray, (0,), b"b")` + BUILD `(version, shape, dtype, fortran, data)`.
    fn reconstruct(&mut self, o: &Object) -> F<PyValue> {
        let p = self.p;
        let args = self.args(o)?;
        match args.first().and_then(|&c| self.global_of(c)) {
            Some(("numpy", "ndarray")) => {}
            Some((m, n)) => {
                return Err(Fail::new(format!(
                    "numpy array subclass `{m}.{n}` is not supported (plain numpy.ndarray only)"
                )))
            }
            None => return Err(Fail::new("`_reconstruct` without a class")),
        }
        if o.kwargs.is_some() || !o.items.is_empty() || !o.elems.is_empty() {
            return Err(Fail::new("numpy array with extra state"));
        }
        let Some(state) = o.state else {
            return Err(Fail::new("numpy array without its BUILD state"));
        };
        let Value::Tuple(st) = p.get(state) else {
            return Err(Fail::new("numpy array state is not a tuple"));
        };
        // Version 1 prepends a version number; very old pickles have the 4-item form.
        let st: &[Id] = match st.len() {
            5 => &st[1..],
            4 => st,
            n => {
                return Err(Fail::new(format!(
                    "numpy array state has {n} items, expected 5"
                )))
            }
        };
        let shape = self.shape(st[0])?;
        let dtype = self.dtype(st[1])?;
        let fortran = match p.get(st[2]) {
            Value::Bool(b) => *b,
            Value::Int(i @ (0 | 1)) => *i == 1,
            _ => return Err(Fail::new("numpy array order flag is not a bool")),
        };
        let numel = Self::numel(&shape)?;
        let data = match dtype.elem {
            Some(elem) => {
                let raw = self.payload(st[3])?;
                decode_elements(&raw, elem, dtype.big_endian, numel, &mut |n| {
                    self.charge(n).map_err(|f| f.message)
                })
                .map_err(Fail::new)?
            }
            // Object arrays pickle their elements as a list, always in C order.
            None => return self.object_array(st[3], shape, numel),
        };
        let data = if fortran {
            fortran_to_c(data, &shape)
        } else {
            data
        };
        Ok(PyValue::Array(NdArray { shape, data }))
    }

    /// Protocol 5: `_frombuffer(buffer, dtype, shape, order)`.
    fn frombuffer(&mut self, o: &Object) -> F<PyValue> {
        let p = self.p;
        let args = self.args(o)?;
        let [buf, dtype, shape, order] = args else {
            return Err(Fail::new("`_frombuffer` needs 4 arguments"));
        };
        let dtype = self.dtype(*dtype)?;
        let shape = self.shape(*shape)?;
        let fortran = match p.get(*order) {
            Value::Str(s) if s == "C" => false,
            Value::Str(s) if s == "F" => true,
            _ => return Err(Fail::new("`_frombuffer` order is not 'C' or 'F'")),
        };
        let Some(elem) = dtype.elem else {
            return Err(Fail::new("`_frombuffer` of an object dtype"));
        };
        let numel = Self::numel(&shape)?;
        let raw = self.payload(*buf)?;
        let data = decode_elements(&raw, elem, dtype.big_endian, numel, &mut |n| {
            self.charge(n).map_err(|f| f.message)
        })
        .map_err(Fail::new)?;
        let data = if fortran {
            fortran_to_c(data, &shape)
        } else {
            data
        };
        Ok(PyValue::Array(NdArray { shape, data }))
    }

    fn object_array(&mut self, id: Id, shape: Vec<usize>, numel: usize) -> F<PyValue> {
        let p = self.p;
        let Value::List(items) = p.get(id) else {
            return Err(Fail::new("object array data is not a list"));
        };
        if items.len() != numel {
            return Err(Fail::new(format!(
                "object array of shape {shape:?} has {} elements",
                items.len()
            )));
        }
        self.charge(numel.saturating_mul(8))?;
        let mut ints = Vec::with_capacity(numel);
        let mut floats = Vec::with_capacity(numel);
        let mut all_int = true;
        for &it in items {
            match p.get(it) {
                Value::Int(i) => {
                    ints.push(*i);
                    floats.push(*i as f64);
                }
                Value::Float(f) => {
                    all_int = false;
                    floats.push(*f);
                }
                _ => {
                    return Err(Fail::new(format!(
                        "object array element {} is not a number",
                        p.describe(it)
                    )))
                }
            }
        }
        let data = if all_int {
            ArrayData::I64(ints)
        } else {
            ArrayData::F64(floats)
        };
        Ok(PyValue::Array(NdArray { shape, data }))
    }

    /// `scalar(dtype, bytes)`: a numpy scalar, read as the plain number.
    fn scalar(&mut self, o: &Object) -> F<PyValue> {
        let args = self.args(o)?;
        let [dtype, payload] = args else {
            return Err(Fail::new("numpy scalar needs 2 arguments"));
        };
        let dtype = self.dtype(*dtype)?;
        let Some(elem) = dtype.elem else {
            return Err(Fail::new("numpy object scalars are not supported"));
        };
        let raw = self.payload(*payload)?;
        let data =
            decode_elements(&raw, elem, dtype.big_endian, 1, &mut |_| Ok(())).map_err(Fail::new)?;
        Ok(match data {
            ArrayData::Bool(v) => PyValue::Bool(v[0]),
            ArrayData::U8(v) => PyValue::Int(v[0].into()),
            ArrayData::I8(v) => PyValue::Int(v[0].into()),
            ArrayData::U16(v) => PyValue::Int(v[0].into()),
            ArrayData::I16(v) => PyValue::Int(v[0].into()),
            ArrayData::U32(v) => PyValue::Int(v[0].into()),
            ArrayData::I32(v) => PyValue::Int(v[0].into()),
            ArrayData::U64(v) => match i64::try_from(v[0]) {
                Ok(i) => PyValue::Int(i),
                Err(_) => {
                    return Err(Fail::new(format!(
                        "numpy uint64 scalar {} does not fit in 64-bit signed",
                        v[0]
                    )))
                }
            },
            ArrayData::I64(v) => PyValue::Int(v[0]),
            ArrayData::F16(v) => PyValue::Float(f16_to_f64(v[0])),
            ArrayData::F32(v) => PyValue::Float(v[0].into()),
            ArrayData::F64(v) => PyValue::Float(v[0]),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_floats_convert_exactly() {
        for (bits, want) in [
            (0x3c00u16, 1.0),
            (0xbc00, -1.0),
            (0x7bff, 65504.0),
            (0x0001, 2f64.powi(-24)),
            (0x3800, 0.5),
            (0x0000, 0.0),
        ] {
            assert_eq!(f16_to_f64(bits), want, "bits {bits:04x}");
        }
        assert!(f16_to_f64(0x7c00).is_infinite());
        assert!(f16_to_f64(0x7e00).is_nan());
    }

    #[test]
    fn fortran_order_is_transposed() {
        // [[0, 1, 2], [3, 4, 5]] stored column-major is 0 3 1 4 2 5.
        let f = ArrayData::I32(vec![0, 3, 1, 4, 2, 5]);
        assert_eq!(
            fortran_to_c(f, &[2, 3]),
            ArrayData::I32(vec![0, 1, 2, 3, 4, 5])
        );
        // 3-D: element (i, j, k) of shape (2, 2, 2) sits at i + 2j + 4k in Fortran order.
        let f: Vec<i32> = (0..8).collect();
        let ArrayData::I32(c) = fortran_to_c(ArrayData::I32(f), &[2, 2, 2]) else {
            unreachable!()
        };
        for (n, &v) in c.iter().enumerate() {
            let (i, j, k) = (n / 4, (n / 2) % 2, n % 2);
            assert_eq!(v as usize, i + 2 * j + 4 * k, "c index {n}");
        }
    }

    #[test]
    fn handmade_globals_are_refused_without_running_anything() {
        // cos\nsystem\n(S'echo hi'\ntR.  -- protocol 0 `os.system("echo hi")`.
        let e = parse_pickle(b"cos\nsystem\n(S'echo hi'\ntR.").unwrap_err();
        assert!(e.contains("`os.system` is not allowed"), "{e}");
        // A bare global (a pickled function object).
        let e = parse_pickle(b"\x80\x02cbuiltins\neval\n.").unwrap_err();
        assert!(e.contains("`builtins.eval`"), "{e}");
        // A class instance via NEWOBJ.
        let e = parse_pickle(b"\x80\x02]q\x00c__main__\nFoo\n)\x81a.").unwrap_err();
        assert!(e.contains("`__main__.Foo`") && e.contains("root[0]"), "{e}");
    }

    #[test]
    fn cycles_depth_and_odd_keys_are_errors() {
        // l = []; l.append(l)
        let e = parse_pickle(b"\x80\x02]q\x00h\x00a.").unwrap_err();
        assert!(e.contains("contains itself"), "{e}");
        let mut deep = b"\x80\x02".to_vec();
        deep.extend(b"]".repeat(100));
        deep.extend(b"a".repeat(99));
        deep.push(b'.');
        let e = parse_pickle(&deep).unwrap_err();
        assert!(e.contains("nested more than 64"), "{e}");
        // {(1,): 2}
        let e = parse_pickle(b"\x80\x02}K\x01\x85K\x02s.").unwrap_err();
        assert!(e.contains("dict key"), "{e}");
        // A shared list referenced twice is fine (not a cycle).
        let v = parse_pickle(b"\x80\x02]q\x00(K\x01eh\x00\x86.").unwrap();
        assert_eq!(
            v,
            PyValue::List(vec![
                PyValue::List(vec![PyValue::Int(1)]),
                PyValue::List(vec![PyValue::Int(1)])
            ])
        );
    }

    #[test]
    fn repeated_keys_keep_first_position_last_value() {
        // {"a": 1, "b": 2, "a": 3}
        let v = parse_pickle(
            b"\x80\x02}(X\x01\x00\x00\x00aK\x01X\x01\x00\x00\x00bK\x02X\x01\x00\x00\x00aK\x03u.",
        )
        .unwrap();
        assert_eq!(
            v,
            PyValue::Dict(vec![
                (DictKey::Str("a".into()), PyValue::Int(3)),
                (DictKey::Str("b".into()), PyValue::Int(2)),
            ])
        );
        assert_eq!(v.get("a"), Some(&PyValue::Int(3)));
        assert_eq!(v.get("zz"), None);
    }
}
