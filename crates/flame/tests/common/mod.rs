//! Shared helpers for the integration tests.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};

pub fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests")
        .join("golden")
}

pub fn load_golden(name: &str) -> HashMap<String, Tensor> {
    let path = golden_dir().join(name);
    candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("cannot read golden {}: {e}", path.display()))
}

pub fn flat_f64(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap()
}

pub fn get<'a>(g: &'a HashMap<String, Tensor>, key: &str) -> &'a Tensor {
    g.get(key)
        .unwrap_or_else(|| panic!("golden has no `{key}`"))
}

/// Compares element-wise; on failure reports the first offending index and the worst one.
pub fn assert_close(what: &str, expected: &[f64], actual: &[f64], tol: f64) -> f64 {
    assert_eq!(expected.len(), actual.len(), "{what}: length differs");
    let mut worst = (0usize, 0.0f64);
    let mut first_bad = None;
    for (i, (e, a)) in expected.iter().zip(actual).enumerate() {
        let d = (e - a).abs();
        if (d.is_nan() || d > tol) && first_bad.is_none() {
            first_bad = Some(i);
        }
        if d > worst.1 || d.is_nan() {
            worst = (i, d);
        }
    }
    if let Some(i) = first_bad {
        panic!(
            "{what}: index {i}: expected {}, actual {} (|diff| {:e} > tol {tol:e}); worst index {}: expected {}, actual {}",
            expected[i],
            actual[i],
            (expected[i] - actual[i]).abs(),
            worst.0,
            expected[worst.0],
            actual[worst.0]
        );
    }
    worst.1
}
