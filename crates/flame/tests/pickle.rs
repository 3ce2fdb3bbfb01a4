//! torch zip checkpoints with config objects of unknown classes, shared storages and every
//! dtype we read, against the values torch wrote (fixtures of
//! `tools/reference/pickle_fixtures.py`).

mod common;

use candle_core::{DType, Device, Tensor};
use common::golden_dir;
use gagavatar_flame::asset::{read_tensor_file, RawData};
use gagavatar_flame::FlameError;

/// Compares a checkpoint with what the reader must return for it, by flattened key.
fn check_file(name: &str, expected: &str) {
    let got = read_tensor_file(&golden_dir().join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let want = common::load_golden(expected);
    let mut want_keys: Vec<&String> = want.keys().collect();
    want_keys.sort();
    let got_keys: Vec<&String> = got.keys().collect();
    assert_eq!(got_keys, want_keys, "{name}: key set");
    for (key, w) in &want {
        let g = &got[key];
        assert_eq!(g.shape, w.dims(), "{name}: {key} shape");
        let file_dtype = format!("{:?}", w.dtype());
        assert_eq!(g.file_dtype, file_dtype, "{name}: {key} dtype");
        let w = w.flatten_all().unwrap();
        match &g.data {
            // The reader hands out floats as f32; the expected value is torch's number rounded
            // the same way (exact for f16 / bf16 / f32, the nearest f32 for f64).
            RawData::Float(v) => {
                let e = w.to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
                assert_eq!(v.len(), e.len(), "{name}: {key} length");
                for (i, (a, b)) in v.iter().zip(&e).enumerate() {
                    assert!(
                        a.to_bits() == b.to_bits(),
                        "{name}: {key}[{i}]: expected {b}, actual {a}"
                    );
                }
            }
            RawData::Int(v) => {
                let e = w.to_dtype(DType::I64).unwrap().to_vec1::<i64>().unwrap();
                assert_eq!(v.len(), e.len(), "{name}: {key} length");
                for (i, (a, b)) in v.iter().zip(&e).enumerate() {
                    assert_eq!(a, b, "{name}: {key}[{i}]: expected {b}, actual {a}");
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
            Err(e @ FlameError::Pickle { .. }) => {
                assert!(e.to_string().contains(needle), "{name}: {e}")
            }
            Err(e) => panic!("{name}: expected a pickle error, got {e}"),
            Ok(m) => panic!("{name}: read {} tensors", m.len()),
        }
    }
}

#[test]
fn loaded_tensors_feed_candle() {
    // The reader's output is usable as-is: the float64 transposed view round-trips.
    let got = read_tensor_file(&golden_dir().join("pickle_p2.pt")).unwrap();
    let t = &got["model.views.transposed"];
    let RawData::Float(v) = &t.data else {
        panic!("float tensor expected")
    };
    let x = Tensor::from_vec(v.clone(), t.shape.as_slice(), &Device::Cpu).unwrap();
    let back = x
        .t()
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let base: Vec<f32> = (0..48).map(|i| (i as f64 * 0.1 - 1.3) as f32).collect();
    assert_eq!(back, base);
}
