//! Bad inputs and bad model files give clear errors, never panics.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use gagavatar_metrics::{
    default_asset_dir, FaceRect, FaceResNet, IdentityNet, MetricsError, ShapePredictor,
    RESNET_FILE, SHAPE_PREDICTOR_FILE,
};
use image::{GrayImage, RgbImage};

fn scratch(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("gagavatar_metrics_{}_{name}", std::process::id()))
}

fn tensors(file: &str) -> HashMap<String, Tensor> {
    candle_core::safetensors::load(default_asset_dir().join(file), &Device::Cpu).unwrap()
}

fn weights_reason(e: MetricsError) -> String {
    match e {
        MetricsError::Weights { reason, .. } => reason,
        other => panic!("expected a weights error, got {other}"),
    }
}

/// Writes `t` to a scratch file, loads it with `load`, removes the file, returns the weights
/// error's reason.
fn load_err<T: std::fmt::Debug>(
    t: &HashMap<String, Tensor>,
    name: &str,
    load: impl Fn(&Path) -> gagavatar_metrics::Result<T>,
) -> String {
    let p = scratch(name);
    candle_core::safetensors::save(t, &p).unwrap();
    let r = load(&p);
    let _ = std::fs::remove_file(&p);
    weights_reason(r.unwrap_err())
}

#[test]
fn missing_or_garbage_files_are_named() {
    let missing = Path::new("/nonexistent/model.safetensors");
    let e = FaceResNet::load(missing).unwrap_err().to_string();
    assert!(e.contains("/nonexistent/model.safetensors"), "{e}");
    let junk = scratch("junk.safetensors");
    std::fs::write(&junk, b"not a safetensors file").unwrap();
    assert!(ShapePredictor::load(&junk).is_err());
    let _ = std::fs::remove_file(&junk);
    assert!(IdentityNet::load(Path::new("/nonexistent")).is_err());
}

#[test]
fn resnet_keys_and_shapes_are_checked_strictly() {
    let good = tensors(RESNET_FILE);

    let mut t = good.clone();
    t.remove("fc.weight");
    let r = load_err(&t, "missing.safetensors", FaceResNet::load);
    assert!(r.contains("missing `fc.weight`"), "{r}");

    let mut t = good.clone();
    t.insert(
        "extra.weight".into(),
        Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
    );
    let r = load_err(&t, "extra.safetensors", FaceResNet::load);
    assert!(r.contains("unexpected `extra.weight`"), "{r}");

    let mut t = good.clone();
    t.insert(
        "stages.1.0.conv1.weight".into(),
        Tensor::zeros((64, 32, 3, 2), DType::F32, &Device::Cpu).unwrap(),
    );
    let r = load_err(&t, "shape.safetensors", FaceResNet::load);
    assert!(r.contains("stages.1.0.conv1.weight` has shape"), "{r}");

    let mut t = good;
    t.insert(
        "fc.weight".into(),
        Tensor::zeros((128, 256), DType::U32, &Device::Cpu).unwrap(),
    );
    let r = load_err(&t, "dtype.safetensors", FaceResNet::load);
    assert!(r.contains("not a float"), "{r}");
}

#[test]
fn predictor_tables_are_checked() {
    let good = tensors(SHAPE_PREDICTOR_FILE);

    let mut t = good.clone();
    let idx = t["split_idx1"].clone();
    let bad = (idx + 10_000.0).unwrap();
    t.insert("split_idx1".into(), bad);
    let r = load_err(&t, "sp_idx.safetensors", ShapePredictor::load);
    assert!(r.contains("feature pixel"), "{r}");

    let mut t = good.clone();
    t.remove("deltas");
    let r = load_err(&t, "sp_missing.safetensors", ShapePredictor::load);
    assert!(r.contains("missing `deltas`"), "{r}");

    let mut t = good;
    let leaves = t["leaf_values"].clone();
    let nan = leaves.affine(1.0, f64::NAN).unwrap();
    t.insert("leaf_values".into(), nan);
    let r = load_err(&t, "sp_nan.safetensors", ShapePredictor::load);
    assert!(r.contains("non-finite"), "{r}");
}

#[test]
fn bad_faces_and_images_are_errors() {
    let net = IdentityNet::load(&default_asset_dir()).unwrap();
    let img = RgbImage::from_pixel(200, 160, image::Rgb([90, 120, 150]));
    let input = |e: MetricsError| match e {
        MetricsError::Input { reason, .. } => reason,
        other => panic!("expected an input error, got {other}"),
    };

    // Entirely outside the image (on each side).
    for r in [
        FaceRect::new(-100, 10, -1, 100).unwrap(),
        FaceRect::new(200, 10, 300, 100).unwrap(),
        FaceRect::new(10, -90, 100, -1).unwrap(),
        FaceRect::new(10, 160, 100, 250).unwrap(),
    ] {
        let m = input(net.embed(&img, r).unwrap_err());
        assert!(m.contains("does not overlap"), "{m}");
    }
    // Tiny.
    let m = input(
        net.embed(&img, FaceRect::new(50, 50, 55, 80).unwrap())
            .unwrap_err(),
    );
    assert!(m.contains("smallest face side"), "{m}");
    // Empty image.
    let e = net
        .predictor()
        .predict(&GrayImage::new(0, 0), FaceRect::new(0, 0, 20, 20).unwrap());
    assert!(e.is_err());
    // Rectangles: inverted, NaN, out of range.
    assert!(FaceRect::new(50, 50, 40, 80).is_err());
    assert!(FaceRect::from_box(f64::NAN, 0.0, 10.0, 10.0).is_err());
    assert!(FaceRect::from_box(0.0, 0.0, 1e30, 10.0).is_err());
    // A chip of the wrong size.
    let m = input(net.embed_chip(&RgbImage::new(150, 149)).unwrap_err());
    assert!(m.contains("150x150"), "{m}");
    // A flat grey image still gives a (meaningless) finite descriptor: no panic, no NaN.
    let e = net
        .embed(&img, FaceRect::new(40, 30, 140, 130).unwrap())
        .unwrap();
    assert!(e.descriptor.iter().all(|v| v.is_finite()));
    assert!(net.embed_chips(&[]).unwrap().is_empty());
}
