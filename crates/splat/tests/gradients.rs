//! Every gradient of the splatting op against f64 central finite differences.

use candle_core::{DType, Device, Tensor, Var};
use gagavatar_splat::testscene::Rng;
use gagavatar_splat::{splat, Camera, Gaussians};

/// Central differences in f64 with this step: small enough for O(h^2) error ~1e-10, large
/// enough that rounding noise (~1e-16 / h) stays negligible.
const FD_STEP: f64 = 1e-6;
/// Allowed |analytic - numeric| <= ABS + REL * max(|analytic|, |numeric|): FD truncation and
/// rounding error on losses of size ~10 (the analytic backward itself is exact).
const FD_ABS_TOL: f64 = 2e-5;
const FD_REL_TOL: f64 = 1e-4;

struct Scene {
    means: Vec<f64>,
    feats: Vec<f64>,
    opac: Vec<f64>,
    scales: Vec<f64>,
    rots: Vec<f64>,
    bg: Vec<f64>,
    c: usize,
    cam: Camera,
    grad_img: Vec<f64>,
}

/// A small scene kept away from the compositing thresholds: moderate opacities (no 0.99 clamp,
/// no early stop), a few overlaps, one tiny quaternion, one anisotropic Gaussian and one far to
/// the side whose EWA tan ratio is clamped.
fn scene() -> Scene {
    let mut rng = Rng::new(7);
    let (w, h, c) = (40usize, 36usize, 3usize);
    let tm = Camera::look_at_origin_matrix(9.0, 0.15, -0.1);
    let cam = Camera::from_transform_matrix(&tm, 12.0, w, h).unwrap();
    let n = 9;
    let mut s = Scene {
        means: vec![],
        feats: vec![],
        opac: vec![],
        scales: vec![],
        rots: vec![],
        bg: vec![0.2, -0.1, 0.3],
        c,
        cam,
        grad_img: (0..c * w * h).map(|_| rng.normal()).collect(),
    };
    for i in 0..n {
        s.means.extend([
            rng.range(-0.5, 0.5),
            rng.range(-0.5, 0.5),
            rng.range(-0.5, 0.5),
        ]);
        s.feats.extend((0..c).map(|_| rng.range(-0.5, 1.5)));
        s.opac.push(rng.range(0.2, 0.6));
        let base = rng.range(0.04, 0.12);
        s.scales
            .extend([base * rng.range(0.6, 1.4), base * rng.range(0.6, 1.4), base]);
        let q: Vec<f64> = (0..4).map(|_| rng.normal()).collect();
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        let qs = if i == 1 {
            2e-3
        } else {
            1.0 / norm * rng.range(0.7, 1.3)
        };
        s.rots.extend(q.iter().map(|x| x * qs));
    }
    // Very anisotropic.
    s.scales[3 * 2..3 * 2 + 3].copy_from_slice(&[0.2, 0.01, 0.02]);
    // Far to the side (x/z beyond 1.3 tan(fov/2) = 0.108 at depth ~9), big enough to reach in.
    s.means[3 * 4..3 * 4 + 3].copy_from_slice(&[-1.25, 0.1, 0.0]);
    s.scales[3 * 4..3 * 4 + 3].copy_from_slice(&[0.3, 0.25, 0.2]);
    s
}

fn t(v: &[f64], shape: &[usize]) -> Tensor {
    Tensor::from_slice(v, shape, &Device::Cpu).unwrap()
}

fn loss(s: &Scene) -> f64 {
    let n = s.opac.len();
    let out = splat(
        &Gaussians {
            means: &t(&s.means, &[n, 3]),
            features: &t(&s.feats, &[n, s.c]),
            opacities: &t(&s.opac, &[n, 1]),
            scales: &t(&s.scales, &[n, 3]),
            rotations: &t(&s.rots, &[n, 4]),
        },
        &t(&s.bg, &[s.c]),
        std::slice::from_ref(&s.cam),
    )
    .unwrap();
    let img: Vec<f64> = out.image.flatten_all().unwrap().to_vec1().unwrap();
    img.iter().zip(&s.grad_img).map(|(a, b)| a * b).sum()
}

#[test]
fn gradients_match_finite_differences() {
    let s = scene();
    let n = s.opac.len();
    let vars = [
        Var::from_slice(&s.means, (n, 3), &Device::Cpu).unwrap(),
        Var::from_slice(&s.feats, (n, s.c), &Device::Cpu).unwrap(),
        Var::from_slice(&s.opac, (n, 1), &Device::Cpu).unwrap(),
        Var::from_slice(&s.scales, (n, 3), &Device::Cpu).unwrap(),
        Var::from_slice(&s.rots, (n, 4), &Device::Cpu).unwrap(),
        Var::from_slice(&s.bg, s.c, &Device::Cpu).unwrap(),
    ];
    let out = splat(
        &Gaussians {
            means: vars[0].as_tensor(),
            features: vars[1].as_tensor(),
            opacities: vars[2].as_tensor(),
            scales: vars[3].as_tensor(),
            rotations: vars[4].as_tensor(),
        },
        vars[5].as_tensor(),
        std::slice::from_ref(&s.cam),
    )
    .unwrap();
    // Gaussian 4 must exercise the clamped EWA branch: |x/z| > 1.3 tan(fov/2).
    let (r, tr) = (&s.cam.rot, &s.cam.trans);
    let p = &s.means[12..15];
    let v: Vec<f64> = (0..3)
        .map(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + tr[i])
        .collect();
    assert!(
        (v[0] / v[2]).abs() > 1.3 / 12.0,
        "view {v:?} is not clamped"
    );
    let radii: Vec<u32> = out.radii.flatten_all().unwrap().to_vec1().unwrap();
    assert!(
        radii.iter().all(|&r| r > 0),
        "all test Gaussians must be visible: {radii:?}"
    );
    let g = t(&s.grad_img, out.image.dims());
    let l = (out.image * g).unwrap().sum_all().unwrap();
    let grads = l.backward().unwrap();
    let names = [
        "means",
        "features",
        "opacities",
        "scales",
        "rotations",
        "background",
    ];
    let mut checked = 0;
    let mut worst = 0.0f64;
    for (k, var) in vars.iter().enumerate() {
        let analytic: Vec<f64> = grads
            .get(var.as_tensor())
            .unwrap_or_else(|| panic!("no gradient for {}", names[k]))
            .to_dtype(DType::F64)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        for (i, &a) in analytic.iter().enumerate() {
            let mut plus = scene();
            let mut minus = scene();
            let field = |s: &mut Scene| -> *mut f64 {
                let v = match k {
                    0 => &mut s.means,
                    1 => &mut s.feats,
                    2 => &mut s.opac,
                    3 => &mut s.scales,
                    4 => &mut s.rots,
                    _ => &mut s.bg,
                };
                &mut v[i] as *mut f64
            };
            unsafe {
                *field(&mut plus) += FD_STEP;
                *field(&mut minus) -= FD_STEP;
            }
            let num = (loss(&plus) - loss(&minus)) / (2.0 * FD_STEP);
            let err = (a - num).abs();
            let tol = FD_ABS_TOL + FD_REL_TOL * a.abs().max(num.abs());
            worst = worst.max(err / tol);
            assert!(
                err <= tol,
                "{}[{i}]: analytic {a:.9e} vs finite difference {num:.9e} (|diff| {err:.3e} > tol {tol:.3e})",
                names[k]
            );
            checked += 1;
        }
    }
    println!("checked {checked} gradient entries, worst error/tolerance {worst:.3}");
}
