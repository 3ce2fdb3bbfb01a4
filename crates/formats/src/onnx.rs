//! A small reader of ONNX model files: the protobuf wire format decoded by hand (varints,
//! length-delimited fields, fixed 32/64-bit fields), keeping what running a feed-forward
//! graph needs: the graph's nodes in order (op type, inputs, outputs, attributes), its
//! initializers (float32 / int64 tensors, `raw_data` or typed fields), and its input and output
//! names. Tensors stored outside the file (`data_location = EXTERNAL`) are refused.
//!
//! Field numbers are onnx.proto's (ONNX IR 3-10): ModelProto.graph = 7; GraphProto.node = 1,
//! initializer = 5, input = 11, output = 12; NodeProto.input = 1, output = 2, name = 3,
//! op_type = 4, attribute = 5, domain = 7; AttributeProto.name = 1, f = 2, i = 3, s = 4, t = 5,
//! floats = 7, ints = 8; TensorProto.dims = 1, data_type = 2, float_data = 4, int64_data = 7,
//! name = 8, raw_data = 9, data_location = 14; ValueInfoProto.name = 1.

use std::collections::BTreeMap;

use crate::error::{FormatError, Result};

/// Files larger than this are refused (an IResNet-100 is about 260 MB).
pub const MAX_MODEL_BYTES: usize = 1 << 30;

/// TensorProto.DataType values this reader keeps.
const FLOAT: i64 = 1;
const INT64: i64 = 7;

/// An initializer's values.
#[derive(Debug, Clone, PartialEq)]
pub enum Data {
    F32(Vec<f32>),
    I64(Vec<i64>),
}

#[derive(Debug, Clone, PartialEq)]
pub struct OnnxTensor {
    pub name: String,
    pub dims: Vec<usize>,
    pub data: Data,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Attribute {
    Float(f32),
    Int(i64),
    Floats(Vec<f32>),
    Ints(Vec<i64>),
    Bytes(Vec<u8>),
    Tensor(OnnxTensor),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Node {
    pub name: String,
    pub op_type: String,
    pub domain: String,
    pub inputs: Vec<String>,
    pub outputs: Vec<String>,
    pub attributes: BTreeMap<String, Attribute>,
}

impl Node {
    pub fn int(&self, name: &str) -> Option<i64> {
        match self.attributes.get(name) {
            Some(Attribute::Int(v)) => Some(*v),
            _ => None,
        }
    }

    pub fn float(&self, name: &str) -> Option<f32> {
        match self.attributes.get(name) {
            Some(Attribute::Float(v)) => Some(*v),
            _ => None,
        }
    }

    pub fn ints(&self, name: &str) -> Option<&[i64]> {
        match self.attributes.get(name) {
            Some(Attribute::Ints(v)) => Some(v),
            _ => None,
        }
    }
}

/// The parts of a model a feed-forward run needs.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OnnxGraph {
    pub nodes: Vec<Node>,
    pub initializers: BTreeMap<String, OnnxTensor>,
    /// Graph inputs that are not initializers (the data inputs).
    pub inputs: Vec<String>,
    pub outputs: Vec<String>,
}

/// A protobuf message's bytes being read.
struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

/// One field: its number and value.
enum Value<'a> {
    Varint(u64),
    /// A double or fixed64 field (none that this reader keeps).
    Fixed64,
    Bytes(&'a [u8]),
    Fixed32(u32),
}

fn bad(reason: impl Into<String>) -> FormatError {
    FormatError::Onnx {
        label: "ONNX model".into(),
        reason: reason.into(),
    }
}

impl<'a> Reader<'a> {
    fn new(buf: &'a [u8]) -> Self {
        Self { buf, pos: 0 }
    }

    fn varint(&mut self) -> Result<u64> {
        let mut v = 0u64;
        for shift in (0..70).step_by(7) {
            let b = *self
                .buf
                .get(self.pos)
                .ok_or_else(|| bad("truncated varint"))?;
            self.pos += 1;
            if shift == 63 && b > 1 {
                return Err(bad("varint longer than 64 bits"));
            }
            v |= ((b & 0x7f) as u64) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(bad("varint longer than 10 bytes"))
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.buf.len())
            .ok_or_else(|| bad(format!("a field of {n} bytes runs past the end")))?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    /// The next field, `None` at the end of the message.
    fn field(&mut self) -> Result<Option<(u64, Value<'a>)>> {
        if self.pos >= self.buf.len() {
            return Ok(None);
        }
        let key = self.varint()?;
        let (num, wire) = (key >> 3, key & 7);
        let v = match wire {
            0 => Value::Varint(self.varint()?),
            1 => {
                self.take(8)?;
                Value::Fixed64
            }
            2 => {
                let n = usize::try_from(self.varint()?).map_err(|_| bad("length overflow"))?;
                Value::Bytes(self.take(n)?)
            }
            5 => Value::Fixed32(u32::from_le_bytes(
                self.take(4)?.try_into().map_err(|_| bad("fixed32"))?,
            )),
            w => return Err(bad(format!("field {num}: unsupported wire type {w}"))),
        };
        Ok(Some((num, v)))
    }
}

fn string(v: &Value) -> Result<String> {
    match v {
        Value::Bytes(b) => String::from_utf8(b.to_vec()).map_err(|_| bad("a name is not UTF-8")),
        _ => Err(bad("a string field has the wrong wire type")),
    }
}

/// Repeated int64: packed (one length-delimited run of varints) or one varint per field.
fn push_ints(v: &Value, out: &mut Vec<i64>) -> Result<()> {
    match v {
        Value::Varint(x) => out.push(*x as i64),
        Value::Bytes(b) => {
            let mut r = Reader::new(b);
            while r.pos < b.len() {
                out.push(r.varint()? as i64);
            }
        }
        _ => return Err(bad("an int64 list has the wrong wire type")),
    }
    Ok(())
}

/// Repeated float: packed or one fixed32 per field.
fn push_floats(v: &Value, out: &mut Vec<f32>) -> Result<()> {
    match v {
        Value::Fixed32(x) => out.push(f32::from_bits(*x)),
        Value::Bytes(b) => {
            if b.len() % 4 != 0 {
                return Err(bad("a packed float list is not a multiple of 4 bytes"));
            }
            out.extend(
                b.chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
            );
        }
        _ => return Err(bad("a float list has the wrong wire type")),
    }
    Ok(())
}

fn tensor(buf: &[u8]) -> Result<OnnxTensor> {
    let mut r = Reader::new(buf);
    let (mut dims, mut dtype, mut name) = (Vec::new(), 0i64, String::new());
    let (mut floats, mut ints, mut raw) = (Vec::new(), Vec::new(), None);
    while let Some((num, v)) = r.field()? {
        match num {
            1 => push_ints(&v, &mut dims)?,
            2 => {
                if let Value::Varint(x) = v {
                    dtype = x as i64;
                }
            }
            4 => push_floats(&v, &mut floats)?,
            7 => push_ints(&v, &mut ints)?,
            8 => name = string(&v)?,
            9 => {
                if let Value::Bytes(b) = v {
                    raw = Some(b);
                }
            }
            14 => {
                if let Value::Varint(1) = v {
                    return Err(bad(format!(
                        "tensor `{name}` is stored in an external file; save the model with \
                         its weights inside (onnx.save(model, save_as_external_data=False))"
                    )));
                }
            }
            _ => {}
        }
    }
    let dims: Vec<usize> = dims
        .iter()
        .map(|&d| usize::try_from(d).map_err(|_| bad(format!("tensor `{name}`: dim {d}"))))
        .collect::<Result<_>>()?;
    let count = dims
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| bad(format!("tensor `{name}`: too many values")))?;
    let data = match dtype {
        FLOAT => {
            let v = match raw {
                Some(b) => {
                    let mut v = Vec::new();
                    push_floats(&Value::Bytes(b), &mut v)?;
                    v
                }
                None => floats,
            };
            Data::F32(v)
        }
        INT64 => {
            let v = match raw {
                Some(b) if b.len() % 8 == 0 => b
                    .chunks_exact(8)
                    .map(|c| i64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
                    .collect(),
                Some(_) => return Err(bad(format!("tensor `{name}`: int64 raw data size"))),
                None => ints,
            };
            Data::I64(v)
        }
        t => {
            return Err(bad(format!(
                "tensor `{name}` has data type {t}; only float32 (1) and int64 (7) are read"
            )))
        }
    };
    let n = match &data {
        Data::F32(v) => v.len(),
        Data::I64(v) => v.len(),
    };
    if n != count {
        return Err(bad(format!(
            "tensor `{name}` of shape {dims:?} holds {n} values, expected {count}"
        )));
    }
    Ok(OnnxTensor { name, dims, data })
}

fn attribute(buf: &[u8]) -> Result<(String, Option<Attribute>)> {
    let mut r = Reader::new(buf);
    let mut name = String::new();
    let (mut f, mut i, mut s, mut t) = (None, None, None, None);
    let (mut floats, mut ints) = (Vec::new(), Vec::new());
    let (mut has_floats, mut has_ints) = (false, false);
    while let Some((num, v)) = r.field()? {
        match (num, &v) {
            (1, _) => name = string(&v)?,
            (2, Value::Fixed32(x)) => f = Some(f32::from_bits(*x)),
            (3, Value::Varint(x)) => i = Some(*x as i64),
            (4, Value::Bytes(b)) => s = Some(b.to_vec()),
            (5, Value::Bytes(b)) => t = Some(tensor(b)?),
            (7, _) => {
                has_floats = true;
                push_floats(&v, &mut floats)?
            }
            (8, _) => {
                has_ints = true;
                push_ints(&v, &mut ints)?
            }
            _ => {}
        }
    }
    let a = if has_ints {
        Some(Attribute::Ints(ints))
    } else if has_floats {
        Some(Attribute::Floats(floats))
    } else if let Some(t) = t {
        Some(Attribute::Tensor(t))
    } else if let Some(s) = s {
        Some(Attribute::Bytes(s))
    } else if let Some(f) = f {
        Some(Attribute::Float(f))
    } else {
        i.map(Attribute::Int)
    };
    Ok((name, a))
}

fn node(buf: &[u8]) -> Result<Node> {
    let mut r = Reader::new(buf);
    let mut n = Node {
        name: String::new(),
        op_type: String::new(),
        domain: String::new(),
        inputs: Vec::new(),
        outputs: Vec::new(),
        attributes: BTreeMap::new(),
    };
    while let Some((num, v)) = r.field()? {
        match num {
            1 => n.inputs.push(string(&v)?),
            2 => n.outputs.push(string(&v)?),
            3 => n.name = string(&v)?,
            4 => n.op_type = string(&v)?,
            5 => {
                if let Value::Bytes(b) = v {
                    if let (k, Some(a)) = attribute(b)? {
                        n.attributes.insert(k, a);
                    }
                }
            }
            7 => n.domain = string(&v)?,
            _ => {}
        }
    }
    Ok(n)
}

fn value_info_name(buf: &[u8]) -> Result<String> {
    let mut r = Reader::new(buf);
    while let Some((num, v)) = r.field()? {
        if num == 1 {
            return string(&v);
        }
    }
    Err(bad("a graph input or output has no name"))
}

/// Parses a model file's bytes.
pub fn parse_model(bytes: &[u8]) -> Result<OnnxGraph> {
    if bytes.len() > MAX_MODEL_BYTES {
        return Err(bad(format!(
            "{} bytes is over the 1 GiB limit",
            bytes.len()
        )));
    }
    let mut r = Reader::new(bytes);
    let mut graph = None;
    while let Some((num, v)) = r.field()? {
        if let (7, Value::Bytes(b)) = (num, v) {
            graph = Some(b);
        }
    }
    let g = graph.ok_or_else(|| bad("no graph (is this an ONNX model file?)"))?;
    let mut out = OnnxGraph::default();
    let mut inputs = Vec::new();
    let mut r = Reader::new(g);
    while let Some((num, v)) = r.field()? {
        let Value::Bytes(b) = v else { continue };
        match num {
            1 => out.nodes.push(node(b)?),
            5 => {
                let t = tensor(b)?;
                out.initializers.insert(t.name.clone(), t);
            }
            11 => inputs.push(value_info_name(b)?),
            12 => out.outputs.push(value_info_name(b)?),
            _ => {}
        }
    }
    out.inputs = inputs
        .into_iter()
        .filter(|n| !out.initializers.contains_key(n))
        .collect();
    if out.nodes.is_empty() || out.inputs.is_empty() || out.outputs.is_empty() {
        return Err(bad(format!(
            "the graph has {} nodes, {} data inputs and {} outputs",
            out.nodes.len(),
            out.inputs.len(),
            out.outputs.len()
        )));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn varint(mut v: u64, out: &mut Vec<u8>) {
        loop {
            let b = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                out.push(b);
                return;
            }
            out.push(b | 0x80);
        }
    }

    fn bytes_field(num: u64, b: &[u8], out: &mut Vec<u8>) {
        varint(num << 3 | 2, out);
        varint(b.len() as u64, out);
        out.extend_from_slice(b);
    }

    #[test]
    fn varints_round_trip_and_truncation_is_an_error() {
        for v in [0u64, 1, 127, 128, 300, u32::MAX as u64, u64::MAX] {
            let mut b = Vec::new();
            varint(v, &mut b);
            assert_eq!(Reader::new(&b).varint().unwrap(), v);
            assert!(Reader::new(&b[..b.len() - 1]).varint().is_err() || b.len() == 1);
        }
        assert!(Reader::new(&[0x80; 11]).varint().is_err());
    }

    #[test]
    fn a_hand_built_model_parses() {
        // TensorProto "w": dims [2], FLOAT, raw_data 1.5, -2.
        let mut t = Vec::new();
        varint(1 << 3, &mut t);
        varint(2, &mut t);
        varint(2 << 3, &mut t);
        varint(1, &mut t);
        bytes_field(8, b"w", &mut t);
        let raw: Vec<u8> = [1.5f32, -2.0]
            .iter()
            .flat_map(|f| f.to_le_bytes())
            .collect();
        bytes_field(9, &raw, &mut t);
        let mut n = Vec::new();
        bytes_field(1, b"x", &mut n);
        bytes_field(1, b"w", &mut n);
        bytes_field(2, b"y", &mut n);
        bytes_field(4, b"Mul", &mut n);
        let mut g = Vec::new();
        bytes_field(1, &n, &mut g);
        bytes_field(5, &t, &mut g);
        let mut vi = Vec::new();
        bytes_field(1, b"x", &mut vi);
        bytes_field(11, &vi, &mut g);
        let mut vo = Vec::new();
        bytes_field(1, b"y", &mut vo);
        bytes_field(12, &vo, &mut g);
        let mut m = Vec::new();
        varint(1 << 3, &mut m);
        varint(8, &mut m);
        bytes_field(7, &g, &mut m);
        let graph = parse_model(&m).unwrap();
        assert_eq!(graph.inputs, ["x"]);
        assert_eq!(graph.outputs, ["y"]);
        assert_eq!(graph.nodes[0].op_type, "Mul");
        assert_eq!(graph.initializers["w"].data, Data::F32(vec![1.5, -2.0]));
        // Every truncation is an error, never a panic.
        for cut in 0..m.len() {
            let _ = parse_model(&m[..cut]);
        }
        assert!(parse_model(&[]).is_err());
        assert!(parse_model(b"not a model at all").is_err());
    }
}
