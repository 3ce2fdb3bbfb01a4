//! Candle autograd through the forward pass and the landmarks vs f64 central finite differences.

use candle_core::{DType, Device, Tensor, Var};
use gagavatar_flame::{rodrigues, synthesize, FlameConfig, FlameModel, FlameParams};

/// Central differences with h = 1e-5 in f64: truncation O(h^2) ~ 1e-10 and cancellation
/// ~1e-16 * |L| / h ~ 1e-9 on this objective, so agreement to 1e-6 (relative, floor 1) is tight.
const FD_STEP: f64 = 1e-5;
const FD_TOL: f64 = 1e-6;

struct Inputs {
    shape: Vec<f64>,
    exp: Vec<f64>,
    pose: Vec<f64>,
    eye: Vec<f64>,
}

fn objective_weights(model: &FlameModel, n: usize, seed: u64) -> Tensor {
    // Fixed pseudo-random weights so every coordinate contributes differently.
    let mut s = seed;
    let w: Vec<f64> = (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        })
        .collect();
    Tensor::from_vec(w, n, &model.device).unwrap()
}

/// L = <w_v, vertices> + <w_l, landmarks68> + <w_f, full landmarks>.
fn objective(model: &FlameModel, p: &FlameParams, wv: &Tensor, wl: &Tensor, wf: &Tensor) -> Tensor {
    let out = model.forward(p).unwrap();
    let lm = model.landmarks(&out.vertices, &p.pose).unwrap();
    let a = (out.vertices.flatten_all().unwrap() * wv)
        .unwrap()
        .sum_all()
        .unwrap();
    let b = (lm.lmk68.flatten_all().unwrap() * wl)
        .unwrap()
        .sum_all()
        .unwrap();
    let c = (lm.full.flatten_all().unwrap() * wf)
        .unwrap()
        .sum_all()
        .unwrap();
    ((a + b).unwrap() + c).unwrap()
}

fn params(model: &FlameModel, x: &Inputs) -> FlameParams {
    let t = |v: &[f64]| Tensor::from_vec(v.to_vec(), (1, v.len()), &model.device).unwrap();
    FlameParams {
        shape: t(&x.shape),
        expression: t(&x.exp),
        pose: t(&x.pose),
        eye: t(&x.eye),
    }
}

fn check_point(x: Inputs, label: &str) {
    let asset = synthesize(0);
    let config = FlameConfig {
        n_shape: 20,
        n_exp: 10,
        ..FlameConfig::default()
    };
    let model = FlameModel::new(&asset, config, &Device::Cpu, DType::F64).unwrap();
    let wv = objective_weights(&model, model.n_vertices * 3, 1);
    let wl = objective_weights(&model, 68 * 3, 2);
    let wf = objective_weights(&model, 70 * 3, 3);

    let vars = [
        Var::from_vec(x.shape.clone(), (1, 20), &model.device).unwrap(),
        Var::from_vec(x.exp.clone(), (1, 10), &model.device).unwrap(),
        Var::from_vec(x.pose.clone(), (1, 6), &model.device).unwrap(),
        Var::from_vec(x.eye.clone(), (1, 6), &model.device).unwrap(),
    ];
    let p = FlameParams {
        shape: vars[0].as_tensor().clone(),
        expression: vars[1].as_tensor().clone(),
        pose: vars[2].as_tensor().clone(),
        eye: vars[3].as_tensor().clone(),
    };
    let grads = objective(&model, &p, &wv, &wl, &wf).backward().unwrap();
    let names = ["shape", "expression", "pose", "eye"];
    let mut worst = 0.0f64;
    for (vi, var) in vars.iter().enumerate() {
        let g = grads
            .get(var.as_tensor())
            .unwrap_or_else(|| panic!("{label}: no gradient for {}", names[vi]))
            .flatten_all()
            .unwrap()
            .to_vec1::<f64>()
            .unwrap();
        let base = [&x.shape, &x.exp, &x.pose, &x.eye][vi].clone();
        for i in 0..base.len() {
            let eval = |delta: f64| {
                let mut v = base.clone();
                v[i] += delta;
                let mut xs = Inputs {
                    shape: x.shape.clone(),
                    exp: x.exp.clone(),
                    pose: x.pose.clone(),
                    eye: x.eye.clone(),
                };
                match vi {
                    0 => xs.shape = v,
                    1 => xs.exp = v,
                    2 => xs.pose = v,
                    _ => xs.eye = v,
                }
                objective(&model, &params(&model, &xs), &wv, &wl, &wf)
                    .to_scalar::<f64>()
                    .unwrap()
            };
            let fd = (eval(FD_STEP) - eval(-FD_STEP)) / (2.0 * FD_STEP);
            let err = (g[i] - fd).abs() / fd.abs().max(1.0);
            worst = worst.max(err);
            assert!(
                err <= FD_TOL,
                "{label}: d/d{}[{i}]: expected (finite difference) {fd}, actual (autograd) {}, rel err {err:e}",
                names[vi],
                g[i]
            );
        }
    }
    println!("{label}: worst relative gradient error {worst:e}");
}

#[test]
fn gradients_match_finite_differences_at_a_generic_pose() {
    check_point(
        Inputs {
            shape: (0..20).map(|i| ((i * 7 % 11) as f64 - 5.0) * 0.2).collect(),
            exp: (0..10).map(|i| ((i * 3 % 7) as f64 - 3.0) * 0.3).collect(),
            // Global yaw 0.2 rad keeps the contour row (11 deg) away from a rounding boundary,
            // where the row switch makes the landmark objective discontinuous.
            pose: vec![0.05, 0.2, -0.03, 0.25, 0.02, -0.04],
            eye: vec![0.1, -0.2, 0.03, 0.12, -0.18, 0.01],
        },
        "generic",
    );
}

#[test]
fn gradients_match_finite_differences_at_zero_pose() {
    // r = 0 is where the +1e-8 inside the norm matters: the gradient must stay finite and right.
    check_point(
        Inputs {
            shape: vec![0.0; 20],
            exp: vec![0.0; 10],
            pose: vec![0.0; 6],
            eye: vec![0.0; 6],
        },
        "zero",
    );
}

#[test]
fn rodrigues_at_tiny_angles_is_first_order_and_differentiable() {
    let r = [1e-7, -2e-7, 3e-7];
    let var = Var::from_vec(r.to_vec(), (1, 3), &Device::Cpu).unwrap();
    let m = rodrigues(var.as_tensor()).unwrap();
    let mv = m.flatten_all().unwrap().to_vec1::<f64>().unwrap();
    // R ~ I + [r]x to first order (the epsilon perturbs the skew part by O(1e-8) relative).
    let skew = [0.0, -r[2], r[1], r[2], 0.0, -r[0], -r[1], r[0], 0.0];
    for i in 0..9 {
        let want = if i % 4 == 0 { 1.0 } else { 0.0 } + skew[i];
        assert!(
            (mv[i] - want).abs() < 1e-12,
            "R[{i}]: expected {want}, actual {}",
            mv[i]
        );
    }
    // d R_21 / d r_x at tiny angle: close to 1 (up to the epsilon's relative effect ~ 1e-8/|r|).
    let grads = m
        .narrow(1, 2, 1)
        .unwrap()
        .narrow(2, 1, 1)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let g = grads
        .get(var.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    assert!(g.iter().all(|x| x.is_finite()), "{g:?}");
    assert!((g[0] - 1.0).abs() < 0.1, "dR21/drx = {}", g[0]);
}
