//! Fixture helpers shared by the training crate's integration tests.
// Each test binary uses a different subset of these.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};

pub fn data_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// Reads a fixture, naming the regeneration script when it cannot.
pub fn load(name: &str) -> HashMap<String, Tensor> {
    let path = data_path(name);
    match candle_core::safetensors::load(&path, &Device::Cpu) {
        Ok(m) => m,
        Err(e) => panic!(
            "cannot read fixture {} ({e}); regenerate with \
             `python3 tools/reference/train_reference.py --out crates/train/tests/data`",
            path.display()
        ),
    }
}

pub fn get<'a>(io: &'a HashMap<String, Tensor>, name: &str) -> &'a Tensor {
    io.get(name)
        .unwrap_or_else(|| panic!("fixture has no `{name}`"))
}

pub fn to_f64(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1::<f64>())
        .expect("tensor to vec")
}

pub fn scalar(t: &Tensor) -> f64 {
    let v = to_f64(t);
    assert_eq!(v.len(), 1, "expected one value, got {}", v.len());
    v[0]
}

/// `|a - e| <= tol * max(1, |e|)` everywhere (absolute below 1, relative above); fails with the
/// worst index, expected and actual value. Returns the worst scaled error.
pub fn assert_close_slices(what: &str, actual: &[f64], expected: &[f64], tol: f64) -> f64 {
    assert_eq!(actual.len(), expected.len(), "{what}: length");
    let mut worst = (0usize, 0f64);
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        let d = (a - e).abs() / e.abs().max(1.0);
        let d = if d.is_nan() { f64::INFINITY } else { d };
        if d > worst.1 {
            worst = (i, d);
        }
    }
    let (i, d) = worst;
    eprintln!("{what}: max scaled error {d:.3e} at index {i}");
    assert!(
        d <= tol,
        "{what}: index {i}: expected {}, actual {} (scaled error {d:.3e} > {tol:.0e})",
        expected[i],
        actual[i]
    );
    d
}

pub fn assert_close(what: &str, actual: &Tensor, expected: &Tensor, tol: f64) -> f64 {
    assert_eq!(actual.dims(), expected.dims(), "{what}: shape");
    assert_close_slices(what, &to_f64(actual), &to_f64(expected), tol)
}

/// Like [`assert_close`] but relative to the largest expected magnitude (for gradients, whose
/// entries span many orders of magnitude).
pub fn assert_close_to_max(what: &str, actual: &Tensor, expected: &Tensor, tol: f64) -> f64 {
    assert_eq!(actual.dims(), expected.dims(), "{what}: shape");
    let (a, e) = (to_f64(actual), to_f64(expected));
    let scale = e.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-300);
    let mut worst = (0usize, 0f64);
    for (i, (x, y)) in a.iter().zip(&e).enumerate() {
        let d = (x - y).abs() / scale;
        let d = if d.is_nan() { f64::INFINITY } else { d };
        if d > worst.1 {
            worst = (i, d);
        }
    }
    let (i, d) = worst;
    eprintln!("{what}: max error {d:.3e} of the largest magnitude {scale:.3e}, at index {i}");
    assert!(
        d <= tol,
        "{what}: index {i}: expected {}, actual {} (error {d:.3e} of max {scale:.3e} > {tol:.0e})",
        e[i],
        a[i]
    );
    d
}

/// The project's seeded generator; tests seed it with `Rng::from_state`. (Not every test file
/// that includes this module draws numbers.)
#[allow(unused_imports)]
pub use gagavatar_splat::rng::Rng;
