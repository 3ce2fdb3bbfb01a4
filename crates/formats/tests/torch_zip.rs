//! torch zip checkpoints with config objects of unknown classes, shared storages and every
//! dtype we read, against the values torch wrote (fixtures of
//! `tools/reference/pickle_fixtures.py`); our writer's checkpoint equals a byte-level golden
//! (which `torch.load` reads: `tools/reference/writer_goldens_check.py`).

mod common;
#[path = "common/golden.rs"]
mod golden;

use std::path::PathBuf;

use gagavatar_formats::pickle::{DictKey, PyValue};
use gagavatar_formats::tensor::{RawData, TensorMap};
use gagavatar_formats::torch_zip::{read_torch_zip, write_torch_zip};
use gagavatar_formats::FormatError;

fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden")
}

fn read_tensor_file(path: &std::path::Path) -> Result<TensorMap, FormatError> {
    read_torch_zip(path)
}

/// A golden safetensors file: key -> (shape, dtype name, values as f64).
fn load_golden(name: &str) -> Vec<(String, Vec<usize>, String, Vec<f64>)> {
    let bytes = std::fs::read(golden_dir().join(name)).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let mut out = Vec::new();
    for (k, v) in st.tensors() {
        use safetensors::Dtype as S;
        let d = v.data();
        let vals: Vec<f64> = match v.dtype() {
            S::F64 => d
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                .collect(),
            S::F32 => d
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64)
                .collect(),
            S::F16 => d
                .chunks_exact(2)
                .map(|c| gagavatar_formats::numpy::f16_to_f64(u16::from_le_bytes([c[0], c[1]])))
                .collect(),
            S::BF16 => d
                .chunks_exact(2)
                .map(|c| f32::from_bits(u32::from(u16::from_le_bytes([c[0], c[1]])) << 16) as f64)
                .collect(),
            S::I64 => d
                .chunks_exact(8)
                .map(|c| i64::from_le_bytes(c.try_into().unwrap()) as f64)
                .collect(),
            S::I32 => d
                .chunks_exact(4)
                .map(|c| i32::from_le_bytes(c.try_into().unwrap()) as f64)
                .collect(),
            S::I16 => d
                .chunks_exact(2)
                .map(|c| i16::from_le_bytes([c[0], c[1]]) as f64)
                .collect(),
            S::U8 | S::BOOL => d.iter().map(|&b| b as f64).collect(),
            other => panic!("{k}: fixture dtype {other:?}"),
        };
        // torch bools are read as their bytes.
        let dtype = match v.dtype() {
            S::BOOL => "U8".to_string(),
            other => format!("{other:?}"),
        };
        out.push((k, v.shape().to_vec(), dtype, vals));
    }
    out
}

/// Compares a checkpoint with what the reader must return for it, by flattened key.
fn check_file(name: &str, expected: &str) {
    let got = read_tensor_file(&golden_dir().join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let want = load_golden(expected);
    let mut want_keys: Vec<&String> = want.iter().map(|w| &w.0).collect();
    want_keys.sort();
    let got_keys: Vec<&String> = got.keys().collect();
    assert_eq!(got_keys, want_keys, "{name}: key set");
    for (key, shape, dtype, e) in &want {
        let g = &got[key];
        assert_eq!(&g.shape, shape, "{name}: {key} shape");
        assert_eq!(&g.file_dtype, dtype, "{name}: {key} dtype");
        match &g.data {
            // The reader hands out floats as f32; the expected value is torch's number rounded
            // the same way (exact for f16 / bf16 / f32, the nearest f32 for f64).
            RawData::Float(v) => {
                assert_eq!(v.len(), e.len(), "{name}: {key} length");
                for (i, (a, b)) in v.iter().zip(e).enumerate() {
                    let b = *b as f32;
                    assert!(
                        a.to_bits() == b.to_bits(),
                        "{name}: {key}[{i}]: expected {b}, actual {a}"
                    );
                }
            }
            RawData::Int(v) => {
                assert_eq!(v.len(), e.len(), "{name}: {key} length");
                for (i, (a, b)) in v.iter().zip(e).enumerate() {
                    assert_eq!(
                        *a as f64, *b,
                        "{name}: {key}[{i}]: expected {b}, actual {a}"
                    );
                }
            }
        }
    }
}

#[test]
fn protocol_2_checkpoint_with_config_objects() {
    check_file("pickle_p2.pt", "pickle_expected.safetensors");
}

#[test]
fn protocol_4_checkpoint_with_config_objects() {
    check_file("pickle_p4.pt", "pickle_expected.safetensors");
}

#[test]
fn protocol_1_checkpoint_with_config_objects() {
    check_file("pickle_p1.pt", "pickle_expected_p1.safetensors");
}

#[test]
fn shared_storage_views_and_config_tensors_are_where_torch_put_them() {
    // Independent of the fixture's expected file: a few values written out by hand.
    let got = read_tensor_file(&golden_dir().join("pickle_p4.pt")).unwrap();
    let floats = |k: &str| match &got[k].data {
        RawData::Float(v) => v.clone(),
        RawData::Int(_) => panic!("{k} is an integer tensor"),
    };
    // base = arange(48) * 0.1 - 1.3 in float64; views.strided = base.view(6, 8)[1:5, 2:7:2].
    let base = |i: usize| (i as f64 * 0.1 - 1.3) as f32;
    let strided: Vec<f32> = [10, 12, 14, 18, 20, 22, 26, 28, 30, 34, 36, 38]
        .iter()
        .map(|&i| base(i))
        .collect();
    assert_eq!(got["model.views.strided"].shape, [4, 3]);
    assert_eq!(floats("model.views.strided"), strided);
    assert_eq!(got["model.views.expanded"].shape, [3, 2]);
    assert_eq!(
        floats("model.views.expanded"),
        [40, 41, 40, 41, 40, 41].map(base)
    );
    // The EasyDict-like config holds row 1 of model.0.weight (same storage, offset 3).
    assert_eq!(
        floats("meta_cfg.TRAIN.sub.w"),
        floats("model.0.weight")[3..6]
    );
    assert_eq!(floats("meta_cfg.CUSTOM.state_t"), [6.0]);
    assert_eq!(floats("meta_cfg.CUSTOM.item_t"), [7.0]);
    // Not collected: the custom callable's argument (99) and NEWOBJ_EX's argument (98).
    assert!(got.keys().all(|k| !k.starts_with("meta_cfg.KW")));
    match &got["model.1.num_batches_tracked"].data {
        RawData::Int(v) => assert_eq!(v, &[7]),
        RawData::Float(_) => panic!("num_batches_tracked is int64"),
    }
    assert!(got["model.1.num_batches_tracked"].shape.is_empty());
}

#[test]
fn truncated_and_garbled_pickles_are_pickle_errors() {
    for (name, needle) in [
        ("pickle_truncated.pt", "truncated"),
        ("pickle_garbled.pt", "unknown opcode 0xff"),
    ] {
        match read_tensor_file(&golden_dir().join(name)) {
            Err(e @ FormatError::Pickle { .. }) => {
                assert!(e.to_string().contains(needle), "{name}: {e}")
            }
            Err(e) => panic!("{name}: expected a pickle error, got {e}"),
            Ok(m) => panic!("{name}: read {} tensors", m.len()),
        }
    }
}

#[test]
fn transposed_views_are_gathered_in_row_major_order() {
    // model.views.transposed is base.view(6, 8).t(): element [i][j] is base[j * 8 + i].
    let got = read_tensor_file(&golden_dir().join("pickle_p2.pt")).unwrap();
    let t = &got["model.views.transposed"];
    let RawData::Float(v) = &t.data else {
        panic!("float tensor expected")
    };
    assert_eq!(t.shape, [8, 6]);
    let base = |i: usize| (i as f64 * 0.1 - 1.3) as f32;
    for i in 0..8 {
        for j in 0..6 {
            assert_eq!(v[i * 6 + j], base(j * 8 + i), "[{i}][{j}]");
        }
    }
}

// ---- byte-level golden of the writer -----------------------------------------------------

/// The golden checkpoint and its expected JSON (also read by
/// `tools/reference/writer_goldens_check.py`).
const TORCH_GOLDEN: &str = "written/checkpoint.pt";
const TORCH_GOLDEN_JSON: &str = "written/checkpoint_expected.json";
const TORCH_BLESS: &str = "GAGAVATAR_BLESS=1 cargo test -p gagavatar-formats --test torch_zip \
                           written_checkpoint_matches_golden";

/// A quiet NaN with a payload, which a checkpoint must keep bit for bit.
const NAN_WITH_PAYLOAD: u32 = 0x7fc0_0001;
/// The bits of 1.0f32: full-mantissa values are made by adding to them.
const ONE_BITS: u32 = 0x3f80_0000;

/// The golden's state dict in the order written (key order, as `write_torch_checkpoint` writes
/// a `BTreeMap`): shapes of rank 0 to 4, one empty, values dyadic, full-mantissa and special.
fn golden_tensors() -> Vec<(&'static str, Vec<usize>, Vec<f32>)> {
    vec![
        (
            "backbone.conv.bias",
            vec![6],
            vec![
                -0.0,
                f32::from_bits(1),
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::from_bits(NAN_WITH_PAYLOAD),
                f32::MAX,
            ],
        ),
        (
            "backbone.conv.weight",
            vec![2, 1, 2, 2],
            (0..8).map(|i| i as f32 * 0.25 - 1.0).collect(),
        ),
        ("head.empty", vec![0, 3], vec![]),
        (
            "head.linear.weight",
            vec![3, 4],
            (0..12u32)
                .map(|i| f32::from_bits(ONE_BITS + i * 7919) - 1.5)
                .collect(),
        ),
        ("head.scale", vec![], vec![3.5]),
    ]
}

/// A `meta_cfg` with every kind of value a configuration holds: nested dicts, lists, strings
/// (one non-ASCII), ints of every pickle width (LONG1 included), floats, bools and None.
fn golden_meta_cfg() -> PyValue {
    let s = |k: &str| DictKey::Str(k.to_owned());
    PyValue::Dict(vec![
        (s("name"), PyValue::Str("golden".into())),
        (
            s("MODEL"),
            PyValue::Dict(vec![
                (s("feat_dim"), PyValue::Int(64)),
                (
                    s("sizes"),
                    PyValue::List(vec![
                        PyValue::Int(0),
                        PyValue::Int(300),
                        PyValue::Int(70_000),
                        PyValue::Int(-5),
                        PyValue::Int(1 << 40),
                        PyValue::Int(-(1 << 40)),
                    ]),
                ),
                (s("lr"), PyValue::Float(1e-4)),
                (s("scale"), PyValue::Float(-0.5)),
                (s("use_pe"), PyValue::Bool(true)),
                (s("flip"), PyValue::Bool(false)),
                (s("style"), PyValue::None),
                (s("empty"), PyValue::List(vec![])),
            ]),
        ),
        (
            s("DATASET"),
            PyValue::Dict(vec![(s("path"), PyValue::Str("data/caf\u{e9}".into()))]),
        ),
    ])
}

/// Plain configuration data as JSON (the expected JSON's `meta_cfg`).
fn plain_json(v: &PyValue) -> serde_json::Value {
    use serde_json::Value as Json;
    match v {
        PyValue::None => Json::Null,
        PyValue::Bool(b) => Json::Bool(*b),
        PyValue::Int(i) => Json::from(*i),
        PyValue::Float(f) => Json::from(*f),
        PyValue::Str(s) => Json::String(s.clone()),
        PyValue::List(items) => Json::Array(items.iter().map(plain_json).collect()),
        PyValue::Dict(entries) => Json::Object(
            entries
                .iter()
                .map(|(k, item)| (key_text(k), plain_json(item)))
                .collect(),
        ),
        other => panic!("not configuration data: {}", other.kind()),
    }
}

/// A configuration key as JSON writes it (configurations have string keys only).
fn key_text(k: &DictKey) -> String {
    match k {
        DictKey::Str(s) => s.clone(),
        DictKey::Int(i) => panic!("configuration key {i} is not a string"),
    }
}

fn hex_of(bytes: impl IntoIterator<Item = u8>) -> String {
    bytes.into_iter().map(|b| format!("{b:02x}")).collect()
}

#[test]
fn written_checkpoint_matches_golden() {
    let tensors = golden_tensors();
    let cfg = golden_meta_cfg();
    let shapes: Vec<(&str, &[usize])> = tensors
        .iter()
        .map(|(k, shape, _)| (*k, shape.as_slice()))
        .collect();
    let dir = common::TempDir::new("torch-golden");
    let path = dir.path().join("checkpoint.pt");
    write_torch_zip(&path, &shapes, Some(&cfg), |i| Ok(tensors[i].2.clone())).unwrap();
    // What our reader sees, before the bytes.
    let back = read_torch_zip(&path).unwrap();
    for (key, shape, values) in &tensors {
        let got = &back[&format!("model.{key}")];
        assert_eq!(&got.shape, shape, "{key}");
        let RawData::Float(v) = &got.data else {
            panic!("{key}: not a float tensor")
        };
        let bits = |x: &[f32]| x.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(v), bits(values), "{key}");
    }
    golden::check_bytes(
        &golden_dir().join(TORCH_GOLDEN),
        &std::fs::read(&path).unwrap(),
        TORCH_BLESS,
    );

    // Tensors as little-endian float32 hex (NaN payloads and -0.0 survive JSON that way).
    let expected = serde_json::json!({
        "about": "model: key order and, per tensor, its shape and little-endian float32 bytes \
                  (hex); meta_cfg: the configuration, with dict keys in pickle order as listed \
                  in meta_cfg_key_order",
        "model_order": tensors.iter().map(|t| t.0).collect::<Vec<_>>(),
        "model": tensors
            .iter()
            .map(|(k, shape, values)| {
                let hex = hex_of(values.iter().flat_map(|x| x.to_le_bytes()));
                ((*k).to_owned(), serde_json::json!({ "shape": shape, "hex": hex }))
            })
            .collect::<serde_json::Map<_, _>>(),
        "meta_cfg": plain_json(&cfg),
        "meta_cfg_key_order": key_orders(&cfg),
    });
    golden::check_json(
        &golden_dir().join(TORCH_GOLDEN_JSON),
        &expected,
        TORCH_BLESS,
    );
}

/// The key order of every dict in `v`, depth first: `[[path, [keys]], ...]` (JSON objects need
/// not keep an order; the pickle's order is part of what Python must see).
fn key_orders(v: &PyValue) -> serde_json::Value {
    fn walk(v: &PyValue, path: &str, out: &mut Vec<serde_json::Value>) {
        match v {
            PyValue::Dict(entries) => {
                let keys: Vec<String> = entries.iter().map(|(k, _)| key_text(k)).collect();
                out.push(serde_json::json!([path, keys]));
                for (k, item) in entries {
                    walk(item, &format!("{path}/{}", key_text(k)), out);
                }
            }
            PyValue::List(items) => {
                for (i, item) in items.iter().enumerate() {
                    walk(item, &format!("{path}/{i}"), out);
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk(v, "", &mut out);
    serde_json::Value::Array(out)
}
