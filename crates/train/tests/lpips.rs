//! LPIPS (AlexNet) against `tools/reference/lpips_reference.py` (float64 PyTorch written from
//! the definition, seeded narrow weights under the `lpips` package's key names), and the
//! loader's errors.

mod common;

use std::collections::HashMap;

use candle_core::{Device, Tensor};
use common::{assert_close_slices, data_path, get, to_f64};
use gagavatar_train::lpips::Lpips;
use gagavatar_train::TrainError;

/// f32 features and sums against a float64 reference: distances of order 0.1 agree to ~1e-7;
/// 1e-6 leaves room for other summation orders.
const LPIPS_TOL: f64 = 1e-6;
/// The near-duplicate pair's distance (~4e-4) must also agree relatively, which the absolute
/// tolerance alone would not show.
const SMALL_REL_TOL: f64 = 1e-3;

/// Reads a fixture, naming its regeneration script when it cannot.
fn load(name: &str) -> HashMap<String, Tensor> {
    let path = data_path(name);
    candle_core::safetensors::load(&path, &Device::Cpu).unwrap_or_else(|e| {
        panic!(
            "cannot read fixture {} ({e}); regenerate with \
             `python3 tools/reference/lpips_reference.py --out crates/train/tests/data`",
            path.display()
        )
    })
}

fn net() -> Lpips {
    Lpips::load(&data_path("lpips_weights.safetensors"), &Device::Cpu).unwrap()
}

#[test]
fn distances_match_reference() {
    let io = load("lpips.safetensors");
    let net = net();
    assert_eq!(net.widths(), vec![16, 32, 48, 32, 32]);
    let (a, b) = (get(&io, "in0"), get(&io, "in1"));
    let layers = net.layer_distances(a, b).unwrap();
    assert_eq!(layers.dims(), &[5, 3]);
    assert_close_slices(
        "per-layer distances [5, 3]",
        &to_f64(&layers),
        &to_f64(get(&io, "layers")),
        LPIPS_TOL,
    );
    let actual = net.distances(a, b).unwrap();
    let expected = to_f64(get(&io, "distance"));
    assert_close_slices("distances", &actual, &expected, LPIPS_TOL);
    let rel = (actual[1] - expected[1]).abs() / expected[1];
    assert!(
        rel <= SMALL_REL_TOL,
        "pair 1: expected {}, actual {}, relative error {rel:.3e}",
        expected[1],
        actual[1]
    );
    assert!(
        expected[0] > 0.1 && expected[1] > 0.0,
        "fixture pairs must differ"
    );
    // Identical images: exactly zero.
    assert_eq!(
        actual[2], 0.0,
        "pair 2 (identical): expected 0, actual {}",
        actual[2]
    );
}

#[test]
fn single_image_matches_its_batch_row() {
    let io = load("lpips.safetensors");
    let net = net();
    let (a, b) = (get(&io, "in0"), get(&io, "in1"));
    let one = net
        .distances(&a.narrow(0, 0, 1).unwrap(), &b.narrow(0, 0, 1).unwrap())
        .unwrap();
    let expected = to_f64(get(&io, "distance"));
    assert_close_slices("pair 0 alone", &one, &expected[..1], LPIPS_TOL);
}

fn weights() -> HashMap<String, Tensor> {
    load("lpips_weights.safetensors")
}

fn load_err(w: &HashMap<String, Tensor>) -> String {
    match Lpips::from_tensors(w, &Device::Cpu, None) {
        Ok(_) => panic!("expected an error"),
        Err(e) => {
            assert!(matches!(e, TrainError::Weights { .. }), "{e:?}");
            e.to_string()
        }
    }
}

#[test]
fn missing_keys_are_named() {
    let mut w = weights();
    w.remove("net.slice3.6.bias");
    w.remove("lin4.model.1.weight");
    let msg = load_err(&w);
    assert!(msg.contains("`net.slice3.6.bias` is missing"), "{msg}");
    assert!(msg.contains("`lin4.model.1.weight` is missing"), "{msg}");
}

#[test]
fn misshapen_keys_are_named() {
    let mut w = weights();
    w.insert(
        "lin2.model.1.weight".into(),
        Tensor::zeros((1, 47, 1, 1), candle_core::DType::F32, &Device::Cpu).unwrap(),
    );
    let msg = load_err(&w);
    assert!(
        msg.contains("`lin2.model.1.weight` has shape [1, 47, 1, 1], expected [1, 48, 1, 1]"),
        "{msg}"
    );
    let mut w = weights();
    // A conv whose input width does not chain with the previous layer.
    w.insert(
        "net.slice2.3.weight".into(),
        Tensor::zeros((32, 15, 5, 5), candle_core::DType::F32, &Device::Cpu).unwrap(),
    );
    let msg = load_err(&w);
    assert!(
        msg.contains("`net.slice2.3.weight` has shape [32, 15, 5, 5], expected [C, 16, 5, 5]"),
        "{msg}"
    );
}

#[test]
fn the_lins_alias_loads_the_same_network() {
    let w: HashMap<String, Tensor> = weights()
        .into_iter()
        .map(|(k, v)| match k.strip_prefix("lin") {
            Some(rest) if !k.starts_with("lins.") => {
                (format!("lins.{}", &rest[..1]) + &rest[1..], v)
            }
            _ => (k, v),
        })
        .collect();
    assert!(w.contains_key("lins.0.model.1.weight"));
    let net = Lpips::from_tensors(&w, &Device::Cpu, None).unwrap();
    let io = load("lpips.safetensors");
    let d = net.distances(get(&io, "in0"), get(&io, "in1")).unwrap();
    assert_close_slices(
        "lins.* distances",
        &d,
        &to_f64(get(&io, "distance")),
        LPIPS_TOL,
    );
}

#[test]
fn bad_inputs_are_errors() {
    let net = net();
    let small = Tensor::zeros((1, 3, 30, 64), candle_core::DType::F32, &Device::Cpu).unwrap();
    let msg = net.distances(&small, &small).unwrap_err().to_string();
    assert!(msg.contains("H, W >= 31"), "{msg}");
    let a = Tensor::zeros((1, 3, 32, 32), candle_core::DType::F32, &Device::Cpu).unwrap();
    let b = Tensor::zeros((1, 3, 32, 40), candle_core::DType::F32, &Device::Cpu).unwrap();
    let msg = net.distances(&a, &b).unwrap_err().to_string();
    assert!(msg.contains("differs"), "{msg}");
    let missing = data_path("no_such_lpips.safetensors");
    assert!(Lpips::load(&missing, &Device::Cpu).is_err());
}
