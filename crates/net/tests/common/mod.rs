//! Golden-file helpers shared by the network's integration tests.
// Each test binary uses a different subset of these.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};

pub fn golden_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name)
}

/// Reads a golden safetensors file, naming the regeneration script when it cannot.
pub fn load(name: &str) -> HashMap<String, Tensor> {
    let path = golden_path(name);
    match candle_core::safetensors::load(&path, &Device::Cpu) {
        Ok(m) => m,
        Err(e) => panic!(
            "cannot read golden {} ({e}); generate it with tools/reference/net_reference.py",
            path.display()
        ),
    }
}

pub fn get<'a>(io: &'a HashMap<String, Tensor>, name: &str) -> &'a Tensor {
    io.get(name)
        .unwrap_or_else(|| panic!("golden tiny_io.safetensors has no `{name}`"))
}

pub fn to_vec_f64(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1::<f64>())
        .expect("tensor to vec")
}

/// Largest absolute difference (NaN counts as infinite); fails with its index, expected and
/// actual value.
pub fn assert_close(what: &str, actual: &Tensor, expected: &Tensor, tol: f64) -> f64 {
    assert_eq!(actual.dims(), expected.dims(), "{what}: shape");
    let a = to_vec_f64(actual);
    let e = to_vec_f64(expected);
    let mut worst = (0usize, 0f64);
    for (i, (x, y)) in a.iter().zip(&e).enumerate() {
        let d = (x - y).abs();
        if d.is_nan() || d > worst.1 {
            worst = (i, if d.is_nan() { f64::INFINITY } else { d });
        }
    }
    let (i, d) = worst;
    eprintln!("{what}: max abs error {d:.3e} at flat index {i}");
    assert!(
        d <= tol,
        "{what}: flat index {i} of {:?}: expected {}, actual {} (|diff| {d:.3e} > {tol:.0e})",
        actual.dims(),
        e[i],
        a[i]
    );
    d
}
