//! PSNR and SSIM against the reference (tools/reference/train_reference.py, which also matched
//! torchmetrics 1.4.2, the release's version, to 1e-16 on SSIM) and against closed forms.

mod common;

use candle_core::{Device, Tensor};
use common::*;
use gagavatar_train::metrics::{
    psnr, psnr_per_image, ssim, ssim_gray, ssim_per_image, ssim_per_image_with, SsimWindows,
};

/// Both sides accumulate in f64 from the same f32 inputs; only the summation order differs.
const TOL_F64: f64 = 1e-10;

#[test]
fn golden_psnr_and_ssim() {
    let io = load("metrics.safetensors");
    let (a, b) = (get(&io, "a"), get(&io, "b"));
    assert_close_slices(
        "psnr",
        &psnr_per_image(a, b).unwrap(),
        &to_f64(get(&io, "psnr")),
        TOL_F64,
    );
    for (windows, tag) in [
        (SsimWindows::Reflect, "reflect"),
        (SsimWindows::Valid, "valid"),
    ] {
        assert_close_slices(
            &format!("ssim {tag}"),
            &ssim_per_image_with(a, b, windows, false).unwrap(),
            &to_f64(get(&io, &format!("ssim_{tag}"))),
            TOL_F64,
        );
        assert_close_slices(
            &format!("luma ssim {tag}"),
            &ssim_per_image_with(a, b, windows, true).unwrap(),
            &to_f64(get(&io, &format!("ssim_gray_{tag}"))),
            TOL_F64,
        );
    }
    // The defaults are reflect padding; batch values are means of the per-image ones.
    let per = to_f64(get(&io, "ssim_reflect"));
    assert_close_slices(
        "ssim default",
        &ssim_per_image(a, b).unwrap(),
        &per,
        TOL_F64,
    );
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert_close_slices("ssim batch", &[ssim(a, b).unwrap()], &[mean(&per)], TOL_F64);
    let gray = to_f64(get(&io, "ssim_gray_reflect"));
    assert_close_slices(
        "luma batch",
        &[ssim_gray(a, b).unwrap()],
        &[mean(&gray)],
        TOL_F64,
    );
    let p = to_f64(get(&io, "psnr"));
    assert_close_slices("psnr batch", &[psnr(a, b).unwrap()], &[mean(&p)], TOL_F64);
}

fn constant(v: f32, dims: &[usize]) -> Tensor {
    Tensor::full(v, dims, &Device::Cpu).unwrap()
}

#[test]
fn closed_forms() {
    // A uniform offset of 0.1: mse 0.01, PSNR exactly 20 dB.
    let dims = [2, 3, 16, 20];
    let p = psnr(&constant(0.5, &dims), &constant(0.6, &dims)).unwrap();
    assert!(
        (p - 20.0).abs() < 1e-5,
        "psnr of a 0.1 offset: expected 20, got {p}"
    );
    // Constant images: sigma terms vanish, SSIM = (2 a b + C1) / (a^2 + b^2 + C1).
    let (x, y) = (0.5f64, 0.6f64);
    let c1 = 1e-4;
    let want = (2.0 * x * y + c1) / (x * x + y * y + c1);
    for windows in [SsimWindows::Reflect, SsimWindows::Valid] {
        let s = ssim_per_image_with(&constant(0.5, &dims), &constant(0.6, &dims), windows, false)
            .unwrap();
        for (i, v) in s.iter().enumerate() {
            // 0.6 is not exact in f32: the expected value moves by ~1e-8.
            assert!(
                (v - want).abs() < 1e-7,
                "image {i} {windows:?}: expected {want}, got {v}"
            );
        }
    }
    // Identical images: PSNR +inf, SSIM 1.
    let io = load("metrics.safetensors");
    let a = get(&io, "a");
    assert_eq!(psnr(a, a).unwrap(), f64::INFINITY);
    for (i, v) in ssim_per_image(a, a).unwrap().iter().enumerate() {
        assert!(
            (v - 1.0).abs() < 1e-12,
            "image {i}: SSIM of identical images {v}"
        );
    }
}

#[test]
fn values_are_clamped_to_unit_range() {
    let dims = [1, 3, 16, 16];
    let over = constant(1.7, &dims);
    let one = constant(1.0, &dims);
    assert_eq!(psnr(&over, &one).unwrap(), f64::INFINITY);
    let s = ssim(&constant(-3.0, &dims), &constant(0.0, &dims)).unwrap();
    assert!((s - 1.0).abs() < 1e-12, "clamped to equal images, SSIM {s}");
}

#[test]
fn bad_inputs_are_errors() {
    let ok = constant(0.5, &[1, 3, 16, 16]);
    let msg = |r: gagavatar_train::Result<f64>| r.expect_err("must fail").to_string();
    // NaN.
    let mut v = vec![0.5f32; 3 * 16 * 16];
    v[17] = f32::NAN;
    let nan = Tensor::from_vec(v, (1, 3, 16, 16), &Device::Cpu).unwrap();
    assert!(msg(psnr(&nan, &ok)).contains("NaN"));
    assert!(msg(ssim(&ok, &nan)).contains("NaN"));
    // Shape mismatch and wrong rank.
    assert!(msg(psnr(&ok, &constant(0.5, &[1, 3, 16, 15]))).contains("differs"));
    assert!(msg(ssim(
        &constant(0.5, &[3, 16, 16]),
        &constant(0.5, &[3, 16, 16])
    ))
    .contains("[B, C, H, W]"));
    // Too small for the window.
    let small = constant(0.5, &[1, 3, 8, 8]);
    assert!(ssim_per_image_with(&small, &small, SsimWindows::Valid, false).is_err());
    assert!(ssim_per_image_with(&small, &small, SsimWindows::Reflect, false).is_ok());
    let tiny = constant(0.5, &[1, 3, 5, 5]);
    assert!(ssim(&tiny, &tiny).is_err());
    // Luma needs RGB.
    let gray = constant(0.5, &[1, 1, 16, 16]);
    assert!(msg(ssim_gray(&gray, &gray)).contains("3 channels"));
}
