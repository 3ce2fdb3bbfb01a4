//! Goldens from the independent dense PyTorch reference (`tools/reference/splat_reference.py`):
//! image, final transmittance, radii and every gradient, in f64 (strict) and f32 (hot path).

use candle_core::{DType, Device, Tensor, Var};
use gagavatar_splat::{splat, Camera, Gaussians};
use std::collections::HashMap;
use std::path::PathBuf;

/// f64 image vs the f64 reference: same arithmetic, only a few operations differ in order.
const F64_IMAGE_TOL: f64 = 1e-12;
/// f64 gradients, relative to the largest magnitude of that tensor: the backward recovers
/// transmittance by division where autograd stores it, which differs at the 1e-13 level.
const F64_GRAD_REL_TOL: f64 = 1e-11;
/// f32 image: up to ~60 composited terms of f32 rounding each, plus the fast exp (4 ulp);
/// measured up to 9e-6.
const F32_IMAGE_TOL: f64 = 5e-5;
/// f32 gradients, relative to the largest magnitude of that tensor: f32 rounding through the
/// back-to-front transmittance recovery (divisions by 1 - alpha down to 0.01); measured up to
/// 7e-6.
const F32_GRAD_REL_TOL: f64 = 5e-5;

fn golden(name: &str) -> HashMap<String, Tensor> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name);
    candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("loading {}: {e}", path.display()))
}

fn vec64(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn camera(g: &HashMap<String, Tensor>) -> Camera {
    let tm = vec64(&g["transform_matrix"]);
    let mut m = [[0.0; 4]; 3];
    for r in 0..3 {
        for c in 0..4 {
            m[r][c] = tm[r * 4 + c];
        }
    }
    let size: Vec<i64> = g["image_size"].to_vec1().unwrap();
    let focal = vec64(&g["focal"])[0];
    Camera::from_transform_matrix(&m, focal, size[0] as usize, size[1] as usize).unwrap()
}

fn compare(what: &str, got: &[f64], want: &[f64], tol_abs: f64) -> f64 {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let mut worst = 0.0f64;
    for (i, (&a, &b)) in got.iter().zip(want).enumerate() {
        let err = (a - b).abs();
        assert!(
            err <= tol_abs,
            "{what}[{i}]: expected {b:.12e}, got {a:.12e} (|diff| {err:.3e} > {tol_abs:.3e})"
        );
        worst = worst.max(err);
    }
    worst
}

fn check(name: &str, dtype: DType) {
    let g = golden(name);
    let cam = camera(&g);
    let names = [
        "means",
        "features",
        "opacities",
        "scales",
        "rotations",
        "background",
    ];
    let vars: Vec<Var> = names
        .iter()
        .map(|n| Var::from_tensor(&g[*n].to_dtype(dtype).unwrap()).unwrap())
        .collect();
    let out = splat(
        &Gaussians {
            means: vars[0].as_tensor(),
            features: vars[1].as_tensor(),
            opacities: vars[2].as_tensor(),
            scales: vars[3].as_tensor(),
            rotations: vars[4].as_tensor(),
        },
        vars[5].as_tensor(),
        std::slice::from_ref(&cam),
    )
    .unwrap();
    let (img_tol, grad_rel) = if dtype == DType::F64 {
        (F64_IMAGE_TOL, F64_GRAD_REL_TOL)
    } else {
        (F32_IMAGE_TOL, F32_GRAD_REL_TOL)
    };
    let tag = format!("{name} {dtype:?}");
    let e_img = compare(
        &format!("{tag} image"),
        &vec64(&out.image),
        &vec64(&g["image"]),
        img_tol,
    );
    let e_t = compare(
        &format!("{tag} final_t"),
        &vec64(&out.transmittance),
        &vec64(&g["final_t"]),
        img_tol,
    );
    let radii: Vec<u32> = out.radii.flatten_all().unwrap().to_vec1().unwrap();
    let want_radii: Vec<i64> = g["radii"].to_vec1().unwrap();
    for (i, (&a, &b)) in radii.iter().zip(&want_radii).enumerate() {
        assert_eq!(a as i64, b, "{tag} radii[{i}]: expected {b}, got {a}");
    }
    let grad_img = g["grad_image"].to_dtype(dtype).unwrap();
    let dims = out.image.dims().to_vec();
    let loss = (out.image * grad_img.reshape(dims).unwrap())
        .unwrap()
        .sum_all()
        .unwrap();
    let grads = loss.backward().unwrap();
    let mut report = format!("{tag}: image {e_img:.2e}, final_t {e_t:.2e}");
    for (var, n) in vars.iter().zip(names) {
        let want = vec64(&g[&format!("grad_{n}")]);
        let got = vec64(grads.get(var.as_tensor()).expect("gradient"));
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-12);
        let worst = compare(&format!("{tag} grad_{n}"), &got, &want, grad_rel * scale);
        report.push_str(&format!(", grad_{n} {:.2e} (rel)", worst / scale));
    }
    println!("{report}");
}

#[test]
fn tiny_f64() {
    check("splat_tiny.safetensors", DType::F64);
}
#[test]
fn tiny_f32() {
    check("splat_tiny.safetensors", DType::F32);
}
#[test]
fn mixed_f64() {
    check("splat_mixed.safetensors", DType::F64);
}
#[test]
fn mixed_f32() {
    check("splat_mixed.safetensors", DType::F32);
}
#[test]
fn avatar_f64() {
    check("splat_avatar.safetensors", DType::F64);
}
#[test]
fn avatar_f32() {
    check("splat_avatar.safetensors", DType::F32);
}
