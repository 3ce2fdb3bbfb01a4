//! Reading torch zip checkpoints (`torch.save` since PyTorch 1.6) whose pickle is a tree of
//! containers with tensor leaves, flattened to `a.b.c` keys.
//!
//! The pickle is parsed by our own data-only interpreter ([`crate::pickle::read`]): classes are recorded
//! by name, never imported or called, so nothing in the file is executed. That also means
//! objects of classes we have never heard of (a release's own config class, `EasyDict`, ...) are
//! kept as data instead of stopping the parse, and the walk below can look inside them.
//!
//! What the walk descends into, and the key each child gets:
//! * dicts, and the SETITEMS items of objects (`OrderedDict`, dict subclasses): the dict key
//!   (str or int keys; other keys are skipped). A key repeated in one dict takes its last value.
//! * lists and tuples, and the APPENDS items of objects (list subclasses): the index.
//! * an object's BUILD state when it is a dict (its attributes) or a `(dict, slots dict)` tuple.
//! * the content of a dict / list subclass pickled with protocol 0 or 1, which is the third
//!   argument of `copyreg._reconstructor(cls, base, content)`.
//!   `EasyDict`-like objects hold the same value as item and attribute; it is read once.
//!
//! It does not descend into the arguments of REDUCE / NEWOBJ calls of unknown callables (what
//! the callable makes of them is unknown), sets, or other values. Every tensor found is
//! collected, including tensors in config objects (`{"model": sd, "meta_cfg": cfg}` yields the
//! `model.*` tensors plus any `meta_cfg.*` tensors); callers pick the prefix they want. A
//! reference cycle is not followed. Two *different* tensors flattening to the same key are an
//! error, as is a tensor of a kind or storage type we cannot read, wherever it sits.
//!
//! candle's own `read_all`/`PthTensors` only look one dict level deep and silently skip storages
//! they do not know (`IntStorage`, ...), which would turn a readable int32 `f` into a confusing
//! "missing key"; its pickle `Stack` stops at the first object of an unknown class.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::io::{Read, Seek};
use std::path::Path;

use crate::error::{label_of, FormatError, Result};
use crate::pickle::read::{self as pickle, Id, Pickle, Value};
use crate::tensor::{Dtype, RawTensor, TensorBytes, TensorMap};

/// Largest pickle accepted. The FLAME pickle is a few kilobytes and a state dict's takes some
/// tens of bytes per tensor; a limit keeps a hostile file from making the parser build an
/// enormous object tree.
const MAX_PICKLE_BYTES: u64 = 64 << 20;
/// Largest tensor accepted (elements); FLAME's biggest (shapedirs) has 6.0 M.
const MAX_TENSOR_ELEMENTS: usize = 1 << 28;
/// Container nesting followed; the release nests 3 deep, configs a few more.
const MAX_DEPTH: usize = 32;
/// Values visited by the walk: shared sub-trees are walked once per path, so a small hostile
/// pickle could otherwise describe an exponentially large tree.
const MAX_VISITS: usize = 1 << 22;
/// `_rebuild_parameter` / `_rebuild_from_type_v2` wrappers followed around one tensor.
const MAX_REBUILD_NESTING: usize = 8;

fn archive_err(label: &str, reason: impl std::fmt::Display) -> FormatError {
    FormatError::TorchZip {
        label: label.to_owned(),
        reason: reason.to_string(),
    }
}

fn pickle_err(label: &str, reason: impl std::fmt::Display) -> FormatError {
    FormatError::Pickle {
        label: label.to_owned(),
        reason: format!("unsupported pickle content: {reason}"),
    }
}

fn tensor_err(label: &str, key: &str, reason: impl Into<String>) -> FormatError {
    FormatError::Tensor {
        label: label.to_owned(),
        key: key.to_owned(),
        reason: reason.into(),
    }
}

/// Storage class name -> element type.
fn storage_dtype(class_name: &str) -> Option<Dtype> {
    Some(match class_name {
        "FloatStorage" => Dtype::F32,
        "DoubleStorage" => Dtype::F64,
        "HalfStorage" => Dtype::F16,
        "BFloat16Storage" => Dtype::BF16,
        "LongStorage" => Dtype::I64,
        "IntStorage" => Dtype::I32,
        "ShortStorage" => Dtype::I16,
        "ByteStorage" => Dtype::U8,
        // torch stores bools as one byte, 0 or 1.
        "BoolStorage" => Dtype::U8,
        _ => return None,
    })
}

/// A tensor leaf as described by the pickle, before its bytes are read.
#[derive(Debug, Clone, PartialEq)]
struct TensorRef {
    storage_key: String,
    class_name: String,
    storage_numel: usize,
    offset: usize,
    size: Vec<usize>,
    stride: Vec<usize>,
}

fn as_usize(v: &Value) -> Option<usize> {
    match v {
        Value::Int(i) if *i >= 0 => usize::try_from(*i).ok(),
        _ => None,
    }
}

fn as_usize_tuple(p: &Pickle, id: Id) -> Option<Vec<usize>> {
    match p.get(id) {
        Value::Tuple(items) | Value::List(items) => {
            items.iter().map(|&i| as_usize(p.get(i))).collect()
        }
        _ => None,
    }
}

/// Recognises a tensor: an object made by `torch._utils._rebuild_tensor_v2(storage, offset,
/// size, stride, ...)`, possibly wrapped in `_rebuild_parameter` or
/// `torch._tensor._rebuild_from_type_v2`.
fn tensor_ref(p: &Pickle, id: Id) -> std::result::Result<Option<TensorRef>, String> {
    match p.get(id) {
        Value::Object(o) => rebuild(p, o.callable, o.args, 0),
        _ => Ok(None),
    }
}

/// What `callable(*args)` makes, if it is a tensor.
fn rebuild(
    p: &Pickle,
    callable: Id,
    args: Id,
    nesting: usize,
) -> std::result::Result<Option<TensorRef>, String> {
    let Some((module, name)) = p.global(callable) else {
        return Ok(None);
    };
    let Value::Tuple(args) = p.get(args) else {
        return Ok(None);
    };
    if nesting > MAX_REBUILD_NESTING {
        return Err("tensor rebuild calls nested too deeply".into());
    }
    match (module, name) {
        ("torch._utils", "_rebuild_parameter")
        | ("torch._utils", "_rebuild_parameter_with_state") => {
            let Some(&inner) = args.first() else {
                return Err("empty _rebuild_parameter".into());
            };
            return match p.get(inner) {
                Value::Object(o) => match rebuild(p, o.callable, o.args, nesting + 1)? {
                    Some(t) => Ok(Some(t)),
                    None => Err(format!(
                        "_rebuild_parameter of a non-tensor {}",
                        p.describe(inner)
                    )),
                },
                _ => Err(format!(
                    "_rebuild_parameter of a non-tensor {}",
                    p.describe(inner)
                )),
            };
        }
        ("torch._tensor", "_rebuild_from_type_v2") => {
            // (func, type, args, state): the tensor is `func(*args)`.
            return match (args.first(), args.get(2)) {
                (Some(&func), Some(&inner_args)) => {
                    match rebuild(p, func, inner_args, nesting + 1)? {
                        Some(t) => Ok(Some(t)),
                        None => Err(format!(
                            "_rebuild_from_type_v2 of {}, which is not a supported tensor",
                            p.describe(func)
                        )),
                    }
                }
                _ => Err("malformed _rebuild_from_type_v2".into()),
            };
        }
        ("torch._utils", "_rebuild_tensor_v2") | ("torch._utils", "_rebuild_tensor") => {}
        ("torch._utils", other) if other.starts_with("_rebuild_") => {
            return Err(format!(
                "tensors made by torch._utils.{other} (quantized, sparse, meta, ...) are not supported"
            ));
        }
        _ => return Ok(None),
    }
    if args.len() < 4 {
        return Err("_rebuild_tensor_v2 with fewer than 4 arguments".into());
    }
    let Value::PersistentId(pid) = p.get(args[0]) else {
        return Err("tensor storage is not a persistent reference".into());
    };
    let pid = match p.get(*pid) {
        Value::Tuple(t) if t.len() >= 5 => t,
        _ => return Err("malformed storage reference".into()),
    };
    let class_name = match p.global(pid[1]) {
        Some((_, class)) => class.to_owned(),
        None => {
            return Err(format!(
                "storage type is not a class: {}",
                p.describe(pid[1])
            ))
        }
    };
    let storage_key = match p.get(pid[2]) {
        Value::Str(s) => s.clone(),
        _ => return Err("storage key is not a string".into()),
    };
    let storage_numel = as_usize(p.get(pid[4])).ok_or("storage size is not an integer")?;
    let offset = as_usize(p.get(args[1])).ok_or("storage offset is not an integer")?;
    let size = as_usize_tuple(p, args[2]).ok_or("tensor size is not a tuple of integers")?;
    let stride = as_usize_tuple(p, args[3]).ok_or("tensor stride is not a tuple of integers")?;
    if size.len() != stride.len() {
        return Err("size and stride ranks differ".into());
    }
    Ok(Some(TensorRef {
        storage_key,
        class_name,
        storage_numel,
        offset,
        size,
        stride,
    }))
}

/// Collects tensor leaves under dotted keys (see the module docs for what is descended into).
struct Walk<'p> {
    p: &'p Pickle,
    out: BTreeMap<String, TensorRef>,
    /// Containers on the current path, to stop at cycles.
    path: Vec<Id>,
    visits: usize,
}

impl<'p> Walk<'p> {
    fn walk(&mut self, id: Id, key: &str, depth: usize) -> std::result::Result<(), String> {
        self.visits += 1;
        if self.visits > MAX_VISITS {
            return Err(format!(
                "the pickle's containers reach more than {MAX_VISITS} values"
            ));
        }
        if let Some(t) = tensor_ref(self.p, id).map_err(|e| format!("`{key}`: {e}"))? {
            return match self.out.get(key) {
                Some(prev) if *prev != t => {
                    Err(format!("two different tensors flatten to the key `{key}`"))
                }
                Some(_) => Ok(()),
                None => {
                    self.out.insert(key.to_owned(), t);
                    Ok(())
                }
            };
        }
        if self.path.contains(&id) {
            return Ok(());
        }
        let children = self.children(id);
        if children.is_empty() {
            return Ok(());
        }
        if depth >= MAX_DEPTH {
            return Err(format!(
                "`{key}`: containers nested more than {MAX_DEPTH} deep"
            ));
        }
        self.path.push(id);
        for (k, child) in children {
            let full = if key.is_empty() {
                k
            } else {
                format!("{key}.{k}")
            };
            self.walk(child, &full, depth + 1)?;
        }
        self.path.pop();
        Ok(())
    }

    /// Named children of a container, without exact (key, value) repeats.
    fn children(&self, id: Id) -> Vec<(String, Id)> {
        let p = self.p;
        let mut out: Vec<(String, Id)> = Vec::new();
        match p.get(id) {
            Value::Dict(entries) => dict_children(p, entries, &mut out),
            Value::List(v) | Value::Tuple(v) => indexed_children(v, &mut out),
            Value::Object(o) => {
                // Protocols 0-1 pickle a dict / list subclass as
                // `copyreg._reconstructor(cls, base, items)`: the third argument is its content.
                if let (Some(("copyreg" | "copy_reg", "_reconstructor")), Value::Tuple(args)) =
                    (p.global(o.callable), p.get(o.args))
                {
                    match args.get(2).map(|&a| p.get(a)) {
                        Some(Value::Dict(items)) => dict_children(p, items, &mut out),
                        Some(Value::List(elems)) => indexed_children(elems, &mut out),
                        _ => {}
                    }
                }
                dict_children(p, &o.items, &mut out);
                indexed_children(&o.elems, &mut out);
                if let Some(state) = o.state {
                    match p.get(state) {
                        Value::Dict(attrs) => dict_children(p, attrs, &mut out),
                        // `__slots__` objects: (instance dict or None, slots dict).
                        Value::Tuple(t) if t.len() == 2 => {
                            for &part in t {
                                if let Value::Dict(attrs) = p.get(part) {
                                    dict_children(p, attrs, &mut out);
                                }
                            }
                        }
                        _ => {}
                    }
                }
            }
            _ => {}
        }
        let mut seen = HashSet::new();
        out.retain(|(k, v)| seen.insert((k.clone(), *v)));
        out
    }
}

/// Dict entries with str / int keys; a repeated key keeps its last value (Python assignment).
fn dict_children(p: &Pickle, entries: &[(Id, Id)], out: &mut Vec<(String, Id)>) {
    // The key's type is part of its identity: `1` and `"1"` are different Python keys.
    let mut index: HashMap<(bool, String), usize> = HashMap::new();
    for &(k, v) in entries {
        let key = match p.get(k) {
            Value::Str(s) => (true, s.clone()),
            Value::Int(i) => (false, i.to_string()),
            Value::BigInt(s) => (false, s.clone()),
            _ => continue,
        };
        match index.get(&key) {
            Some(&at) => out[at].1 = v,
            None => {
                index.insert(key.clone(), out.len());
                out.push((key.1, v));
            }
        }
    }
}

fn indexed_children(elems: &[Id], out: &mut Vec<(String, Id)>) {
    out.extend(elems.iter().enumerate().map(|(i, &v)| (i.to_string(), v)));
}

/// A tensor read from the archive: its bytes in row-major order, in the file's dtype.
#[derive(Debug, Clone, PartialEq)]
pub struct TorchEntry {
    /// The dotted key (`model.encoder.weight`, `meta_cfg.sub.w`, ...).
    pub key: String,
    pub tensor: TensorBytes,
}

/// Loads every tensor of a torch zip checkpoint under its dotted key, floats as f32 and
/// integers as i64.
pub fn read_torch_zip(path: &Path) -> Result<TensorMap> {
    let file = std::fs::File::open(path).map_err(FormatError::io(path, "cannot read"))?;
    read_torch_zip_from(std::io::BufReader::new(file), &label_of(path))
}

/// [`read_torch_zip`] of bytes in memory; `label` names them in errors.
pub fn read_torch_zip_bytes(bytes: &[u8], label: &str) -> Result<TensorMap> {
    read_torch_zip_from(std::io::Cursor::new(bytes), label)
}

fn read_torch_zip_from(reader: impl Read + Seek, label: &str) -> Result<TensorMap> {
    let mut out = TensorMap::new();
    for_each_tensor(reader, label, |e| {
        let raw = RawTensor::from_bytes(e.tensor.dtype, e.tensor.shape, &e.tensor.bytes)
            .map_err(|reason| tensor_err(label, &e.key, reason))?;
        out.insert(e.key, raw);
        Ok(())
    })?;
    Ok(out)
}

/// Hands each tensor of a torch zip to `f` as soon as it is read, in key order, and frees each
/// storage after its last view: peak memory is the converted tensors plus one storage, not the
/// whole file twice over (a release-size checkpoint peaked at 1.3 GiB for 0.68 GiB of weights).
/// `label` names the archive in errors.
pub fn for_each_tensor(
    reader: impl Read + Seek,
    label: &str,
    mut f: impl FnMut(TorchEntry) -> Result<()>,
) -> Result<()> {
    let mut zip = zip::ZipArchive::new(reader).map_err(|e| {
        archive_err(
            label,
            format!(
                "{e} (legacy non-zip torch files are not supported; re-save with torch >= 1.6)"
            ),
        )
    })?;
    let mut pkl_names: Vec<String> = Vec::new();
    for name in zip.file_names() {
        let name = name.map_err(|e| archive_err(label, e))?;
        if name.ends_with("data.pkl") {
            pkl_names.push(name.into_owned());
        }
    }
    let pkl_name = match pkl_names.as_slice() {
        [one] => one.clone(),
        [] => return Err(archive_err(label, "no data.pkl entry")),
        _ => return Err(archive_err(label, "several data.pkl entries")),
    };
    let prefix = pkl_name.trim_end_matches("data.pkl").to_owned();

    // Storages are raw machine words; torch writes the byte order beside them.
    if let Ok(entry) = zip.by_name(&format!("{prefix}byteorder")) {
        let mut order = Vec::new();
        entry
            .take(16)
            .read_to_end(&mut order)
            .map_err(|e| archive_err(label, format!("reading byteorder: {e}")))?;
        let order = String::from_utf8_lossy(&order);
        if order.trim() != "little" {
            return Err(archive_err(
                label,
                format!(
                    "storages are {:?}-endian; only little-endian is supported",
                    order.trim()
                ),
            ));
        }
    }

    let parsed = {
        let entry = zip.by_name(&pkl_name).map_err(|e| archive_err(label, e))?;
        let mut bytes = Vec::new();
        entry
            .take(MAX_PICKLE_BYTES + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| archive_err(label, format!("reading {pkl_name}: {e}")))?;
        if bytes.len() as u64 > MAX_PICKLE_BYTES {
            return Err(pickle_err(label, "data.pkl larger than 64 MiB"));
        }
        pickle::parse(&bytes).map_err(|e| pickle_err(label, format!("{pkl_name} {e}")))?
    };

    let mut walk = Walk {
        p: &parsed,
        out: BTreeMap::new(),
        path: Vec::new(),
        visits: 0,
    };
    walk.walk(parsed.root(), "", 0)
        .map_err(|e| pickle_err(label, e))?;

    // Storages are read once each: several tensors may be views of one storage.
    let mut storages: HashMap<String, Vec<u8>> = HashMap::new();
    let mut views_left: HashMap<String, usize> = HashMap::new();
    for t in walk.out.values() {
        *views_left.entry(t.storage_key.clone()).or_default() += 1;
    }
    for (key, t) in walk.out {
        let dtype = storage_dtype(&t.class_name).ok_or_else(|| {
            tensor_err(
                label,
                &key,
                format!(
                    "storage type {}; a float, integer or bool storage is needed",
                    t.class_name
                ),
            )
        })?;
        let elem = dtype.size();
        if t.storage_numel > MAX_TENSOR_ELEMENTS {
            return Err(tensor_err(
                label,
                &key,
                format!("storage of {} elements is too large", t.storage_numel),
            ));
        }
        if !storages.contains_key(&t.storage_key) {
            let name = format!("{prefix}data/{}", t.storage_key);
            let want = t.storage_numel * elem;
            let entry = zip
                .by_name(&name)
                .map_err(|e| archive_err(label, format!("{name}: {e}")))?;
            let mut bytes = Vec::with_capacity(want.min(1 << 26));
            entry
                .take(want as u64)
                .read_to_end(&mut bytes)
                .map_err(|e| archive_err(label, format!("reading {name}: {e}")))?;
            if bytes.len() != want {
                return Err(archive_err(
                    label,
                    format!(
                        "{name}: {} bytes, expected {want} (truncated file?)",
                        bytes.len()
                    ),
                ));
            }
            storages.insert(t.storage_key.clone(), bytes);
        }
        let storage = &storages[&t.storage_key];
        let bytes = gather(storage, elem, &t).map_err(|reason| tensor_err(label, &key, reason))?;
        if let Some(n) = views_left.get_mut(&t.storage_key) {
            *n -= 1;
            if *n == 0 {
                storages.remove(&t.storage_key);
            }
        }
        f(TorchEntry {
            key,
            tensor: TensorBytes {
                dtype,
                shape: t.size,
                bytes,
            },
        })?;
    }
    Ok(())
}

/// Copies a (possibly strided) view out of its storage into row-major bytes.
fn gather(storage: &[u8], elem: usize, t: &TensorRef) -> std::result::Result<Vec<u8>, String> {
    let mut numel: usize = 1;
    for &s in &t.size {
        numel = numel.checked_mul(s).ok_or("tensor size overflows")?;
    }
    if numel > MAX_TENSOR_ELEMENTS {
        return Err(format!("tensor of {numel} elements is too large"));
    }
    if numel == 0 {
        return Ok(Vec::new());
    }
    let mut max_index = t.offset;
    for (&s, &st) in t.size.iter().zip(&t.stride) {
        max_index = (s - 1)
            .checked_mul(st)
            .and_then(|x| x.checked_add(max_index))
            .ok_or("tensor view overflows")?;
    }
    if max_index >= t.storage_numel || (max_index + 1) * elem > storage.len() {
        return Err(format!(
            "view reaches element {max_index} of a storage of {}",
            t.storage_numel
        ));
    }
    let rank = t.size.len();
    let mut out = Vec::with_capacity(numel * elem);
    let mut idx = vec![0usize; rank];
    for _ in 0..numel {
        let pos = t.offset + idx.iter().zip(&t.stride).map(|(i, s)| i * s).sum::<usize>();
        out.extend_from_slice(&storage[pos * elem..(pos + 1) * elem]);
        for d in (0..rank).rev() {
            idx[d] += 1;
            if idx[d] < t.size[d] {
                break;
            }
            idx[d] = 0;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn golden(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/golden")
            .join(name)
    }

    /// The public reader converts floats to f32; here the bytes themselves must be what torch
    /// wrote, so float64 views of a shared storage are compared bit for bit.
    #[test]
    fn raw_bytes_equal_what_torch_wrote() {
        let expected_bytes = std::fs::read(golden("pickle_expected.safetensors")).unwrap();
        let expected = safetensors::SafeTensors::deserialize(&expected_bytes).unwrap();
        let expected_p1_bytes = std::fs::read(golden("pickle_expected_p1.safetensors")).unwrap();
        let expected_p1 = safetensors::SafeTensors::deserialize(&expected_p1_bytes).unwrap();
        for (file, expected) in [
            ("pickle_p1.pt", &expected_p1),
            ("pickle_p2.pt", &expected),
            ("pickle_p4.pt", &expected),
        ] {
            let bytes = std::fs::read(golden(file)).unwrap();
            let mut raw = Vec::new();
            for_each_tensor(std::io::Cursor::new(&bytes), file, |e| {
                raw.push(e);
                Ok(())
            })
            .unwrap();
            let keys: Vec<&str> = raw.iter().map(|e| e.key.as_str()).collect();
            assert_eq!(
                raw.len(),
                expected.len(),
                "{file}: tensor count, read {keys:?}"
            );
            let mut n_f64 = 0;
            for e in &raw {
                let want = expected
                    .tensor(&e.key)
                    .unwrap_or_else(|_| panic!("{file}: unexpected key {}", e.key));
                let t = &e.tensor;
                assert_eq!(t.shape, want.shape(), "{file}: {}", e.key);
                // Bool tensors are read as their u8 bytes; everything else keeps its dtype.
                let want_dtype = match want.dtype() {
                    safetensors::Dtype::F64 => Dtype::F64,
                    safetensors::Dtype::F32 => Dtype::F32,
                    safetensors::Dtype::F16 => Dtype::F16,
                    safetensors::Dtype::BF16 => Dtype::BF16,
                    safetensors::Dtype::I64 => Dtype::I64,
                    safetensors::Dtype::I32 => Dtype::I32,
                    safetensors::Dtype::U8 | safetensors::Dtype::BOOL => Dtype::U8,
                    other => panic!("{}: fixture dtype {other:?}", e.key),
                };
                assert_eq!(t.dtype, want_dtype, "{file}: {}", e.key);
                if let Some(i) = t.bytes.iter().zip(want.data()).position(|(a, b)| a != b) {
                    panic!(
                        "{file}: {} differs at byte {i}: expected {}, actual {}",
                        e.key,
                        want.data()[i],
                        t.bytes[i]
                    );
                }
                assert_eq!(t.bytes.len(), want.data().len(), "{file}: {}", e.key);
                n_f64 += usize::from(t.dtype == Dtype::F64);
            }
            assert_eq!(n_f64, 5, "{file}: the five float64 views");
        }
    }

    #[test]
    fn gather_checks_the_view_against_the_storage() {
        let storage: Vec<u8> = (0..6).collect();
        let t = |offset, size: Vec<usize>, stride: Vec<usize>| TensorRef {
            storage_key: "0".into(),
            class_name: "ByteStorage".into(),
            storage_numel: 6,
            offset,
            size,
            stride,
        };
        assert_eq!(
            gather(&storage, 1, &t(1, vec![2, 2], vec![1, 2])).unwrap(),
            [1, 3, 2, 4]
        );
        assert_eq!(
            gather(&storage, 1, &t(4, vec![3], vec![0])).unwrap(),
            [4, 4, 4]
        );
        assert!(gather(&storage, 1, &t(5, vec![2], vec![1])).is_err());
        assert!(gather(&storage, 1, &t(0, vec![2, usize::MAX], vec![1, 1])).is_err());
        assert!(gather(&storage[..3], 1, &t(0, vec![4], vec![1])).is_err());
    }

    fn walk_of(data: &[u8]) -> std::result::Result<BTreeMap<String, TensorRef>, String> {
        let p = pickle::parse(data).map_err(|e| e.to_string())?;
        let mut w = Walk {
            p: &p,
            out: BTreeMap::new(),
            path: Vec::new(),
            visits: 0,
        };
        w.walk(p.root(), "", 0)?;
        Ok(w.out)
    }

    /// `c torch._utils _rebuild_tensor_v2 ((storage pid) offset (size) (stride)) R`
    fn tensor_pickle(key: &str, offset: u8) -> Vec<u8> {
        let mut v =
            b"ctorch._utils\n_rebuild_tensor_v2\n((X\x07\x00\x00\x00storagectorch\nFloatStorage\nX"
                .to_vec();
        v.extend((key.len() as u32).to_le_bytes());
        v.extend(key.as_bytes());
        v.extend(b"X\x03\x00\x00\x00cpuK\x08tQK");
        v.push(offset);
        v.extend(b"K\x02\x85K\x01\x85tR");
        v
    }

    #[test]
    fn walk_reports_conflicts_and_stops_at_depth_and_cycles() {
        // {"a.b": t0, "a": {"b": t1}}: two different tensors for `a.b`.
        let mut d = b"\x80\x02}(X\x03\x00\x00\x00a.b".to_vec();
        d.extend(tensor_pickle("0", 0));
        d.extend(b"X\x01\x00\x00\x00a}X\x01\x00\x00\x00b");
        d.extend(tensor_pickle("1", 0));
        d.extend(b"su.");
        let e = walk_of(&d).unwrap_err();
        assert!(
            e.contains("two different tensors flatten to the key `a.b`"),
            "{e}"
        );

        // 40 nested dicts around a tensor.
        let mut d = b"\x80\x02".to_vec();
        for _ in 0..40 {
            d.extend(b"}X\x01\x00\x00\x00k");
        }
        d.extend(tensor_pickle("0", 0));
        d.extend(b"s".repeat(40));
        d.push(b'.');
        let e = walk_of(&d).unwrap_err();
        assert!(e.contains("nested more than 32 deep"), "{e}");

        // A dict holding itself and a tensor: the cycle is skipped, the tensor found once.
        let mut d = b"\x80\x02}q\x00(X\x04\x00\x00\x00selfh\x00X\x01\x00\x00\x00t".to_vec();
        d.extend(tensor_pickle("0", 3));
        d.extend(b"u.");
        let out = walk_of(&d).unwrap();
        assert_eq!(out.keys().collect::<Vec<_>>(), ["t"]);
        assert_eq!(out["t"].offset, 3);

        // Seven levels of lists, each holding the previous one 16 times: a 1 kB pickle that
        // describes a tree of 16^7 leaves. The visit budget stops it.
        let mut d = b"\x80\x02]q\x00".to_vec();
        for _ in 0..7 {
            d.extend(b"]q\x01(");
            d.extend(b"h\x00".repeat(16));
            d.extend(b"eq\x00");
        }
        d.push(b'.');
        let e = walk_of(&d).unwrap_err();
        assert!(e.contains("more than"), "{e}");
    }

    #[test]
    fn unsupported_tensor_kinds_are_named() {
        let d = b"\x80\x02}X\x01\x00\x00\x00qctorch._utils\n_rebuild_qtensor\n)Rs.";
        let e = walk_of(d).unwrap_err();
        assert!(e.contains("`q`") && e.contains("_rebuild_qtensor"), "{e}");
    }
}
