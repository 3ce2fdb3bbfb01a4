//! The ONNX reader and graph runner against the `onnx` package's reference evaluator, on the
//! tiny model `tools/reference/arcface_onnx_reference.py` writes (every supported operator).

use std::path::Path;

use candle_core::{Device, Tensor};
use gagavatar_metrics::arcface::ArcFace;

/// f32 convolutions and sums in another order than numpy's (outputs are about 1 to 25).
const TOL: f32 = 2e-4;

fn golden(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name)
}

#[test]
fn tiny_graph_matches_the_onnx_reference_evaluator() {
    let net = ArcFace::load(&golden("arcface_tiny.onnx")).unwrap();
    let n = 3 * 112 * 112;
    let x: Vec<f32> = (0..n)
        .map(|i| (0.9 * (0.37 * i as f64).sin()) as f32)
        .collect();
    let x = Tensor::from_vec(x, (1, 3, 112, 112), &Device::Cpu).unwrap();
    let y = net
        .forward(&x)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(golden("arcface_tiny.json")).unwrap())
            .unwrap();
    let want: Vec<f32> = v["output"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect();
    assert_eq!(y.len(), want.len());
    for (i, (a, b)) in y.iter().zip(&want).enumerate() {
        assert!(
            (a - b).abs() <= TOL * b.abs().max(1.0),
            "output {i}: expected {b}, got {a}"
        );
    }
}

#[test]
fn bad_files_are_clear_errors() {
    let dir = std::env::temp_dir().join(format!("gagavatar-onnx-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("x.onnx");
    std::fs::write(&p, b"\x08\x01garbage").unwrap();
    let e = ArcFace::load(&p).unwrap_err().to_string();
    assert!(e.contains("x.onnx"), "{e}");
    let bytes = std::fs::read(golden("arcface_tiny.onnx")).unwrap();
    for cut in [1, 100, bytes.len() / 2, bytes.len() - 1] {
        assert!(ArcFace::from_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
    }
    assert!(ArcFace::load(&dir.join("missing.onnx")).is_err());
    let _ = std::fs::remove_dir_all(&dir);
}
