//! Writes f32 tensors as a PyTorch zip checkpoint in the release layout, `{"model": state_dict,
//! "meta_cfg": config}`, so a model trained here loads in the release's Python code with
//! `torch.load(path, map_location="cpu")` (with `weights_only` either way).
//!
//! The archive holds, under one top folder `archive/`: `data.pkl` (a protocol-2 pickle in which
//! every tensor is `torch._utils._rebuild_tensor_v2` over a persistent-id storage), one
//! `data/<key>` entry of raw little-endian f32 per storage, `byteorder` and `version`. Entries
//! are stored uncompressed and their data aligned to 64 bytes as torch writes them: torch 2.5.1
//! reads unaligned archives too (checked, mmap included), but aligned storages can be mapped
//! in place by any reader.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

use crate::atomic::write_via_temp;
use crate::error::{FormatError, Result};
use crate::pickle::plain::{DictKey, PyValue};

/// The single top folder torch's reader takes from the first entry; torch itself writes this.
const ARCHIVE: &str = "archive";
/// Alignment of each entry's data, as torch's writer pads it (for in-place mapping).
const DATA_ALIGN: u16 = 64;
/// Serialization format version torch 1.6+ writes and 2.5 reads.
const FORMAT_VERSION: &str = "3\n";
/// Unix permissions recorded for every entry (`rw-r--r--`, the zip crate's default).
const ENTRY_PERMISSIONS: u32 = 0o644;

/// Pickle opcodes used here (protocol 2; names as in CPython's `pickletools`).
mod op {
    pub const PROTO: u8 = 0x80;
    pub const STOP: u8 = b'.';
    pub const MARK: u8 = b'(';
    pub const EMPTY_DICT: u8 = b'}';
    pub const EMPTY_LIST: u8 = b']';
    pub const EMPTY_TUPLE: u8 = b')';
    pub const TUPLE: u8 = b't';
    pub const SETITEMS: u8 = b'u';
    pub const APPENDS: u8 = b'e';
    pub const GLOBAL: u8 = b'c';
    pub const REDUCE: u8 = b'R';
    pub const BINPERSID: u8 = b'Q';
    pub const LONG_BINPUT: u8 = b'r';
    pub const LONG_BINGET: u8 = b'j';
    pub const BININT1: u8 = b'K';
    pub const BININT2: u8 = b'M';
    pub const BININT: u8 = b'J';
    pub const LONG1: u8 = 0x8a;
    pub const BINFLOAT: u8 = b'G';
    pub const BINUNICODE: u8 = b'X';
    pub const NONE: u8 = b'N';
    pub const NEWTRUE: u8 = 0x88;
    pub const NEWFALSE: u8 = 0x89;
}

/// A minimal protocol-2 pickle encoder for the values a checkpoint needs. Globals are memoised
/// so each class name is written once, as torch's pickler does.
#[derive(Default)]
struct Pickler {
    out: Vec<u8>,
    globals: BTreeMap<(&'static str, &'static str), u32>,
    next_memo: u32,
}

impl Pickler {
    fn global(&mut self, module: &'static str, name: &'static str) {
        if let Some(&slot) = self.globals.get(&(module, name)) {
            self.out.push(op::LONG_BINGET);
            self.out.extend(slot.to_le_bytes());
            return;
        }
        self.out.push(op::GLOBAL);
        self.out.extend(module.as_bytes());
        self.out.push(b'\n');
        self.out.extend(name.as_bytes());
        self.out.push(b'\n');
        let slot = self.next_memo;
        self.next_memo += 1;
        self.out.push(op::LONG_BINPUT);
        self.out.extend(slot.to_le_bytes());
        self.globals.insert((module, name), slot);
    }

    fn str(&mut self, s: &str) {
        self.out.push(op::BINUNICODE);
        // Keys and configuration strings are far below BINUNICODE's 4 GiB limit.
        let n = u32::try_from(s.len()).unwrap_or(u32::MAX);
        self.out.extend(n.to_le_bytes());
        self.out.extend(s.as_bytes());
    }

    fn int(&mut self, v: i128) {
        if (0..256).contains(&v) {
            self.out.push(op::BININT1);
            self.out.push(v as u8);
        } else if (0..65536).contains(&v) {
            self.out.push(op::BININT2);
            self.out.extend((v as u16).to_le_bytes());
        } else if let Ok(v) = i32::try_from(v) {
            self.out.push(op::BININT);
            self.out.extend(v.to_le_bytes());
        } else {
            // LONG1: minimal little-endian two's complement.
            let bytes = v.to_le_bytes();
            let mut n = bytes.len();
            while n > 1 {
                let top = bytes[n - 1];
                let sign_of_next = bytes[n - 2] & 0x80;
                if (top == 0 && sign_of_next == 0) || (top == 0xff && sign_of_next != 0) {
                    n -= 1;
                } else {
                    break;
                }
            }
            self.out.push(op::LONG1);
            self.out.push(n as u8);
            self.out.extend(&bytes[..n]);
        }
    }

    fn usize(&mut self, v: usize) {
        self.int(v as i128);
    }

    fn tuple_of_usize(&mut self, vals: &[usize]) {
        if vals.is_empty() {
            self.out.push(op::EMPTY_TUPLE);
            return;
        }
        self.out.push(op::MARK);
        for &v in vals {
            self.usize(v);
        }
        self.out.push(op::TUPLE);
    }

    /// `collections.OrderedDict()`, left on the stack for SETITEMS.
    fn ordered_dict(&mut self) {
        self.global("collections", "OrderedDict");
        self.out.push(op::EMPTY_TUPLE);
        self.out.push(op::REDUCE);
    }

    /// `_rebuild_tensor_v2(storage, 0, size, stride, False, OrderedDict())` over the storage
    /// `data/<storage_key>` holding `numel` contiguous f32 values.
    fn f32_tensor(&mut self, storage_key: &str, shape: &[usize]) {
        let numel: usize = shape.iter().product();
        let mut stride = vec![1usize; shape.len()];
        for d in (0..shape.len().saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * shape[d + 1];
        }
        self.global("torch._utils", "_rebuild_tensor_v2");
        self.out.push(op::MARK);
        // Persistent id: ('storage', storage class, key, location, numel).
        self.out.push(op::MARK);
        self.str("storage");
        self.global("torch", "FloatStorage");
        self.str(storage_key);
        self.str("cpu");
        self.usize(numel);
        self.out.push(op::TUPLE);
        self.out.push(op::BINPERSID);
        self.usize(0);
        self.tuple_of_usize(shape);
        self.tuple_of_usize(&stride);
        self.out.push(op::NEWFALSE);
        self.ordered_dict();
        self.out.push(op::TUPLE);
        self.out.push(op::REDUCE);
    }

    /// Plain data (the configuration) as Python dicts, lists, strings, numbers and None.
    fn plain(&mut self, v: &PyValue, depth: usize) -> std::result::Result<(), String> {
        if depth > MAX_CONFIG_DEPTH {
            return Err(format!(
                "the configuration nests deeper than {MAX_CONFIG_DEPTH} levels"
            ));
        }
        match v {
            PyValue::None => self.out.push(op::NONE),
            PyValue::Bool(b) => self.out.push(if *b { op::NEWTRUE } else { op::NEWFALSE }),
            PyValue::Int(i) => self.int(i128::from(*i)),
            PyValue::Float(f) => {
                self.out.push(op::BINFLOAT);
                self.out.extend(f.to_be_bytes());
            }
            PyValue::Str(s) => self.str(s),
            PyValue::List(items) => {
                self.out.push(op::EMPTY_LIST);
                if !items.is_empty() {
                    self.out.push(op::MARK);
                    for item in items {
                        self.plain(item, depth + 1)?;
                    }
                    self.out.push(op::APPENDS);
                }
            }
            PyValue::Dict(entries) => {
                self.out.push(op::EMPTY_DICT);
                if !entries.is_empty() {
                    self.out.push(op::MARK);
                    for (k, item) in entries {
                        match k {
                            DictKey::Str(s) => self.str(s),
                            DictKey::Int(i) => self.int(i128::from(*i)),
                        }
                        self.plain(item, depth + 1)?;
                    }
                    self.out.push(op::SETITEMS);
                }
            }
            PyValue::Bytes(_) | PyValue::Array(_) => {
                return Err(format!(
                    "the configuration holds {}, which a checkpoint's meta_cfg does not",
                    v.kind()
                ))
            }
        }
        Ok(())
    }
}

/// Nesting of the configuration written (ours is 2 deep).
const MAX_CONFIG_DEPTH: usize = 64;

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> FormatError + '_ {
    |e| FormatError::io(path, "cannot write")(e)
}

fn write_err(path: &Path, reason: impl std::fmt::Display) -> FormatError {
    FormatError::Write {
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

/// The pickle `{"model": OrderedDict(key -> tensor), "meta_cfg": config or None}`, with tensor
/// `i` (in key order) stored as `data/<i>`.
fn checkpoint_pickle(
    tensors: &[(&str, &[usize])],
    config: Option<&PyValue>,
) -> std::result::Result<Vec<u8>, String> {
    let mut p = Pickler::default();
    p.out.extend([op::PROTO, 2]);
    p.out.push(op::EMPTY_DICT);
    p.out.push(op::MARK);
    p.str("model");
    p.ordered_dict();
    if !tensors.is_empty() {
        p.out.push(op::MARK);
        for (i, (key, shape)) in tensors.iter().enumerate() {
            p.str(key);
            p.f32_tensor(&i.to_string(), shape);
        }
        p.out.push(op::SETITEMS);
    }
    p.str("meta_cfg");
    match config {
        Some(v) => p.plain(v, 0)?,
        None => p.out.push(op::NONE),
    }
    p.out.push(op::SETITEMS);
    p.out.push(op::STOP);
    Ok(p.out)
}

/// Writes f32 tensors as a torch zip checkpoint `{"model": state_dict, "meta_cfg": config}`
/// that `torch.load` reads, atomically (temp sibling + rename). `tensors` gives each key and
/// shape in the order written; `data(i)` is asked for tensor `i`'s row-major values when it is
/// written, so only one tensor's bytes exist at a time. `meta_cfg` is plain data (dicts, lists,
/// strings, numbers, None), or None.
pub fn write_torch_zip(
    path: &Path,
    tensors: &[(&str, &[usize])],
    meta_cfg: Option<&PyValue>,
    mut data: impl FnMut(usize) -> std::result::Result<Vec<f32>, String>,
) -> Result<()> {
    let pickle = checkpoint_pickle(tensors, meta_cfg).map_err(|e| write_err(path, e))?;
    write_via_temp(
        path,
        |tmp| write_archive(tmp, path, &pickle, tensors, &mut data),
        io_err(path),
    )
}

type TensorData<'d> = &'d mut dyn FnMut(usize) -> std::result::Result<Vec<f32>, String>;

fn write_archive(
    tmp: &Path,
    path: &Path,
    pickle: &[u8],
    tensors: &[(&str, &[usize])],
    data: TensorData,
) -> Result<()> {
    let file = std::fs::File::create(tmp).map_err(io_err(path))?;
    let mut zip = zip::ZipWriter::new(std::io::BufWriter::new(file));
    // Every header field is fixed, so the archive's bytes depend on the input alone: left to
    // their defaults, the zip crate stamps the time of writing (with its `time` feature, which
    // any crate in a build can turn on) and marks entries as made on DOS on Windows.
    let opts = |len: usize| {
        zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored)
            .with_alignment(DATA_ALIGN)
            .large_file(len as u64 >= u32::MAX as u64)
            .last_modified_time(zip::DateTime::default())
            .system(zip::System::Unix)
            .unix_permissions(ENTRY_PERMISSIONS)
    };
    let entry = |zip: &mut zip::ZipWriter<_>, name: &str, bytes: &[u8]| -> Result<()> {
        zip.start_file(format!("{ARCHIVE}/{name}"), opts(bytes.len()))
            .map_err(|e| write_err(path, format!("writing the torch zip: {e}")))?;
        zip.write_all(bytes).map_err(io_err(path))
    };
    entry(&mut zip, "data.pkl", pickle)?;
    entry(&mut zip, "byteorder", b"little")?;
    for (i, (key, shape)) in tensors.iter().enumerate() {
        let v = data(i).map_err(|e| write_err(path, format!("tensor `{key}`: {e}")))?;
        let numel: usize = shape.iter().product();
        if v.len() != numel {
            return Err(write_err(
                path,
                format!("tensor `{key}` has {} values for shape {shape:?}", v.len()),
            ));
        }
        let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        entry(&mut zip, &format!("data/{i}"), &bytes)?;
    }
    entry(&mut zip, "version", FORMAT_VERSION.as_bytes())?;
    let writer = zip
        .finish()
        .map_err(|e| write_err(path, format!("writing the torch zip: {e}")))?;
    let file = writer
        .into_inner()
        .map_err(|e| io_err(path)(e.into_error()))?;
    file.sync_all().map_err(io_err(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long1_is_minimal_twos_complement() {
        // Bytes as `pickle.dumps(v, 2)` in CPython 3 gives them.
        let mut p = Pickler::default();
        p.int(1 << 31);
        assert_eq!(p.out, [0x8a, 5, 0, 0, 0, 0x80, 0]);
        let mut p = Pickler::default();
        p.int(-(1 << 31) - 1);
        assert_eq!(p.out, [0x8a, 5, 0xff, 0xff, 0xff, 0x7f, 0xff]);
        let mut p = Pickler::default();
        p.int(-1);
        assert_eq!(p.out, [b'J', 0xff, 0xff, 0xff, 0xff]);
        let mut p = Pickler::default();
        p.int(300);
        assert_eq!(p.out, [b'M', 0x2c, 0x01]);
    }

    #[test]
    fn written_checkpoints_read_back() {
        let dir = std::env::temp_dir().join(format!("gagavatar-tzw-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("w.pt");
        let cfg = PyValue::Dict(vec![
            (DictKey::Str("name".into()), PyValue::Str("tiny".into())),
            (
                DictKey::Str("sizes".into()),
                PyValue::List(vec![PyValue::Int(1 << 40)]),
            ),
        ]);
        let shapes: [(&str, &[usize]); 2] = [("a.w", &[2, 3]), ("b", &[])];
        write_torch_zip(&path, &shapes, Some(&cfg), |i| {
            Ok(if i == 0 {
                (0..6).map(|x| x as f32 * 0.5).collect()
            } else {
                vec![7.0]
            })
        })
        .unwrap();
        let back = crate::torch_zip::read::read_torch_zip(&path).unwrap();
        let keys: Vec<&String> = back.keys().collect();
        assert_eq!(keys, ["model.a.w", "model.b"]);
        assert_eq!(back["model.a.w"].shape, [2, 3]);
        assert_eq!(
            back["model.a.w"].data,
            crate::tensor::RawData::Float(vec![0.0, 0.5, 1.0, 1.5, 2.0, 2.5])
        );
        // torch's reader takes the top folder from the first entry and needs `version`;
        // storages are 64-byte aligned so `torch.load(mmap=True)` can map them.
        {
            use std::io::Read;
            let mut zip = zip::ZipArchive::new(std::fs::File::open(&path).unwrap()).unwrap();
            let names: Vec<String> = zip.file_names().map(|s| s.unwrap().into_owned()).collect();
            assert_eq!(names.first().map(String::as_str), Some("archive/data.pkl"));
            assert!(names.iter().all(|n| n.starts_with("archive/")), "{names:?}");
            let n_data = names
                .iter()
                .filter(|n| n.starts_with("archive/data/"))
                .count();
            assert_eq!(n_data, 2);
            for i in 0..zip.len() {
                let f = zip.by_index(i).unwrap();
                let start = f.data_start().unwrap();
                assert_eq!(start % 64, 0, "{:?} data starts at {start}", f.name());
            }
            let mut read = |name: &str| {
                let mut v = Vec::new();
                zip.by_name(name).unwrap().read_to_end(&mut v).unwrap();
                v
            };
            assert_eq!(read("archive/version"), b"3\n");
            assert_eq!(read("archive/byteorder"), b"little");
            let pkl = read("archive/data.pkl");
            let has = |needle: &[u8]| pkl.windows(needle.len()).any(|w| w == needle);
            assert!(has(b"meta_cfg") && has(b"sizes"), "config in data.pkl");
        }
        // A wrong value count fails and leaves nothing at the path.
        std::fs::remove_file(&path).unwrap();
        let e = write_torch_zip(&path, &shapes, None, |_| Ok(vec![1.0])).unwrap_err();
        assert!(
            e.to_string().contains("has 1 values for shape [2, 3]"),
            "{e}"
        );
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
