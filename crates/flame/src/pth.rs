//! Reading torch zip checkpoints (`torch.save` since PyTorch 1.6) whose pickle is a tree of
//! dicts with tensor leaves, flattened to `a.b.c` keys.
//!
//! candle's `read_all`/`PthTensors` only look one dict level deep (optionally under one key) and
//! silently skip storages they do not know (`IntStorage`, ...), which would turn a perfectly
//! readable int32 `f` into a confusing "missing key". So this module walks the tree itself. It
//! uses candle's pickle `Stack`, which only builds a data tree (classes are recorded by name,
//! never imported or called): nothing in the file is executed.

use std::collections::HashMap;
use std::io::Read;
use std::path::Path;

use candle_core::pickle::{Object, Stack};

use crate::asset::{RawTensor, TensorMap};
use crate::error::{FlameError, Result};

/// Largest pickle accepted. The FLAME pickle is a few kilobytes; a limit keeps a hostile file
/// from making the parser build an enormous object tree.
const MAX_PICKLE_BYTES: u64 = 64 << 20;
/// Largest tensor accepted (elements); FLAME's biggest (shapedirs) has 6.0 M.
const MAX_TENSOR_ELEMENTS: usize = 1 << 28;
/// Nesting depth for dicts; the release uses 2.
const MAX_DEPTH: usize = 16;

fn archive_err(path: &Path, reason: impl std::fmt::Display) -> FlameError {
    FlameError::Archive {
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

fn pickle_err(path: &Path, reason: impl std::fmt::Display) -> FlameError {
    FlameError::Pickle {
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

/// Storage class name -> (candle dtype, bytes per element).
fn storage_dtype(class_name: &str) -> Option<(candle_core::DType, usize)> {
    use candle_core::DType;
    Some(match class_name {
        "FloatStorage" => (DType::F32, 4),
        "DoubleStorage" => (DType::F64, 8),
        "HalfStorage" => (DType::F16, 2),
        "BFloat16Storage" => (DType::BF16, 2),
        "LongStorage" => (DType::I64, 8),
        "IntStorage" => (DType::I32, 4),
        "ShortStorage" => (DType::I16, 2),
        "ByteStorage" => (DType::U8, 1),
        _ => return None,
    })
}

/// A tensor leaf as described by the pickle, before its bytes are read.
struct TensorRef {
    storage_key: String,
    class_name: String,
    storage_numel: usize,
    offset: usize,
    size: Vec<usize>,
    stride: Vec<usize>,
}

fn as_usize(obj: &Object) -> Option<usize> {
    match obj {
        Object::Int(v) if *v >= 0 => Some(*v as usize),
        Object::Long(v) if *v >= 0 => usize::try_from(*v).ok(),
        _ => None,
    }
}

fn as_usize_tuple(obj: &Object) -> Option<Vec<usize>> {
    match obj {
        Object::Tuple(items) | Object::List(items) => items.iter().map(as_usize).collect(),
        _ => None,
    }
}

/// Recognises `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)`, possibly
/// wrapped in `_rebuild_parameter` or `torch._tensor._rebuild_from_type_v2`.
fn tensor_ref(obj: &Object) -> std::result::Result<Option<TensorRef>, String> {
    let Object::Reduce { callable, args } = obj else {
        return Ok(None);
    };
    let Object::Class {
        module_name,
        class_name,
    } = callable.as_ref()
    else {
        return Ok(None);
    };
    let args = match args.as_ref() {
        Object::Tuple(a) => a,
        _ => return Ok(None),
    };
    match (module_name.as_str(), class_name.as_str()) {
        ("torch._utils", "_rebuild_parameter")
        | ("torch._utils", "_rebuild_parameter_with_state") => {
            return match args.first() {
                Some(inner) => tensor_ref(inner),
                None => Err("empty _rebuild_parameter".into()),
            };
        }
        ("torch._tensor", "_rebuild_from_type_v2") => {
            // (func, type, args, state): rebuild `func(*args)`.
            return match (args.first(), args.get(2)) {
                (Some(func), Some(inner_args)) => tensor_ref(&Object::Reduce {
                    callable: Box::new(func.clone()),
                    args: Box::new(inner_args.clone()),
                }),
                _ => Err("malformed _rebuild_from_type_v2".into()),
            };
        }
        ("torch._utils", "_rebuild_tensor_v2") | ("torch._utils", "_rebuild_tensor") => {}
        _ => return Ok(None),
    }
    if args.len() < 4 {
        return Err("_rebuild_tensor_v2 with fewer than 4 arguments".into());
    }
    let Object::PersistentLoad(pid) = &args[0] else {
        return Err("tensor storage is not a persistent reference".into());
    };
    let pid = match pid.as_ref() {
        Object::Tuple(p) if p.len() >= 5 => p,
        _ => return Err("malformed storage reference".into()),
    };
    let storage_class = match &pid[1] {
        Object::Class { class_name, .. } => class_name.clone(),
        other => return Err(format!("storage type is not a class: {other:?}")),
    };
    let storage_key = match &pid[2] {
        Object::Unicode(s) => s.clone(),
        _ => return Err("storage key is not a string".into()),
    };
    let storage_numel = as_usize(&pid[4]).ok_or("storage size is not an integer")?;
    let offset = as_usize(&args[1]).ok_or("storage offset is not an integer")?;
    let size = as_usize_tuple(&args[2]).ok_or("tensor size is not a tuple of integers")?;
    let stride = as_usize_tuple(&args[3]).ok_or("tensor stride is not a tuple of integers")?;
    if size.len() != stride.len() {
        return Err("size and stride ranks differ".into());
    }
    Ok(Some(TensorRef {
        storage_key,
        class_name: storage_class,
        storage_numel,
        offset,
        size,
        stride,
    }))
}

/// Walks nested dicts, collecting tensor leaves under dotted keys. Non-tensor leaves (numbers,
/// strings, configs) are ignored: they are not part of what we load.
fn collect(
    obj: &Object,
    prefix: &str,
    depth: usize,
    out: &mut Vec<(String, TensorRef)>,
) -> std::result::Result<(), String> {
    if depth > MAX_DEPTH {
        return Err("dicts nested too deeply".into());
    }
    match obj {
        Object::Dict(items) => {
            for (k, v) in items {
                let key = match k {
                    Object::Unicode(s) => s.clone(),
                    Object::Int(i) => i.to_string(),
                    Object::Long(i) => i.to_string(),
                    _ => continue,
                };
                let full = if prefix.is_empty() {
                    key
                } else {
                    format!("{prefix}.{key}")
                };
                collect(v, &full, depth + 1, out)?;
            }
            Ok(())
        }
        other => {
            if let Some(t) = tensor_ref(other).map_err(|e| format!("`{prefix}`: {e}"))? {
                out.push((prefix.to_owned(), t));
            }
            Ok(())
        }
    }
}

/// Loads every tensor of a torch zip checkpoint under its dotted key.
pub fn read_torch_zip(path: &Path) -> Result<TensorMap> {
    let file = std::fs::File::open(path).map_err(|source| FlameError::Io {
        path: path.to_owned(),
        source,
    })?;
    let mut zip = zip::ZipArchive::new(std::io::BufReader::new(file)).map_err(|e| {
        archive_err(
            path,
            format!(
                "{e} (legacy non-zip torch files are not supported; re-save with torch >= 1.6)"
            ),
        )
    })?;
    let mut pkl_names: Vec<String> = Vec::new();
    for name in zip.file_names() {
        let name = name.map_err(|e| archive_err(path, e))?;
        if name.ends_with("data.pkl") {
            pkl_names.push(name.into_owned());
        }
    }
    let pkl_name = match pkl_names.as_slice() {
        [one] => one.clone(),
        [] => return Err(archive_err(path, "no data.pkl entry")),
        _ => return Err(archive_err(path, "several data.pkl entries")),
    };
    let prefix = pkl_name.trim_end_matches("data.pkl").to_owned();

    let obj = {
        let entry = zip.by_name(&pkl_name).map_err(|e| archive_err(path, e))?;
        let mut bytes = Vec::new();
        entry
            .take(MAX_PICKLE_BYTES + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| archive_err(path, format!("reading {pkl_name}: {e}")))?;
        if bytes.len() as u64 > MAX_PICKLE_BYTES {
            return Err(pickle_err(path, "data.pkl larger than 64 MiB"));
        }
        let mut stack = Stack::empty();
        stack
            .read_loop(&mut bytes.as_slice())
            .map_err(|e| pickle_err(path, e))?;
        stack.finalize().map_err(|e| pickle_err(path, e))?
    };

    let mut refs = Vec::new();
    collect(&obj, "", 0, &mut refs).map_err(|e| pickle_err(path, e))?;

    // Storages are read once each: several tensors may be views of one storage.
    let mut storages: HashMap<String, Vec<u8>> = HashMap::new();
    let mut out = TensorMap::new();
    for (key, t) in refs {
        let (dtype, elem) = storage_dtype(&t.class_name).ok_or_else(|| FlameError::DType {
            key: key.clone(),
            expected: "a float or integer storage",
            found: t.class_name.clone(),
        })?;
        if t.storage_numel > MAX_TENSOR_ELEMENTS {
            return Err(FlameError::Invalid {
                key,
                reason: format!("storage of {} elements is too large", t.storage_numel),
            });
        }
        if !storages.contains_key(&t.storage_key) {
            let name = format!("{prefix}data/{}", t.storage_key);
            let want = t.storage_numel * elem;
            let entry = zip
                .by_name(&name)
                .map_err(|e| archive_err(path, format!("{name}: {e}")))?;
            let mut bytes = Vec::with_capacity(want.min(1 << 26));
            entry
                .take(want as u64)
                .read_to_end(&mut bytes)
                .map_err(|e| archive_err(path, format!("reading {name}: {e}")))?;
            if bytes.len() != want {
                return Err(archive_err(
                    path,
                    format!(
                        "{name}: {} bytes, expected {want} (truncated file?)",
                        bytes.len()
                    ),
                ));
            }
            storages.insert(t.storage_key.clone(), bytes);
        }
        let storage = &storages[&t.storage_key];
        let tensor = gather(storage, elem, &t).map_err(|reason| FlameError::Invalid {
            key: key.clone(),
            reason,
        })?;
        let raw = RawTensor::from_bytes(&key, dtype, t.size.clone(), &tensor)?;
        out.insert(key, raw);
    }
    Ok(out)
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
    if max_index >= t.storage_numel {
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
