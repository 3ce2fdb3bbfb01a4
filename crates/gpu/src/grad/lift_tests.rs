//! The lifting generators' training forward and backward ([`GpuLiftGrad`]) against candle's
//! `ConvGsGenerator` and autograd, and the backward against f64 central differences of the
//! CPU module.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use gagavatar_net::gs_generator::ConvGsGenerator;
use gagavatar_train::bench::synthetic_batch;
use gagavatar_train::{LiftedGaussians, TrainConfig, TrainState};

use super::lift::{GpuLiftGrad, LiftInput};
use crate::testutil::{assert_close_rel, flat, gpu, seeded};
use crate::Tuning;

/// Forward values relative to each attribute's largest: the same f32 convolutions summed in
/// another order.
const FORWARD_RTOL: f64 = 1e-5;

/// Gradients relative to each array's largest: four convolutions' backward, sums over every
/// plane pixel for the weights.
const GRAD_RTOL: f64 = 1e-4;

/// Directional derivative (GPU, f32) against f64 central differences of the CPU module,
/// relative to the derivative's size (measured worst 1.7e-6 on lavapipe). The step is small
/// enough that no ReLU's input crosses zero inside it: at 1e-4 the kinks alone gave 1e-3.
const FD_RTOL: f64 = 1e-4;
const FD_STEP: f64 = 1e-6;

struct Case {
    state: TrainState,
    f_local: Tensor,
    enc: Tensor,
    points: Tensor,
    dir: Tensor,
    /// Random upstream gradients of the lifted Gaussians (the layouts of LiftedGaussians).
    upstream: LiftedGaussians,
}

fn case(cfg: TrainConfig) -> Case {
    let state = TrainState::new(cfg, None, None, &Device::Cpu).unwrap();
    let batch = synthetic_batch(&state.cfg, 1, &Device::Cpu).unwrap();
    let (_, trace) = state
        .model
        .reconstruct_features(&batch.source_image, &batch.source_transform, None)
        .unwrap();
    let m = &state.cfg.model;
    let s = m.plane_size();
    let n = if m.one_plane { 1 } else { 2 } * s * s;
    let upstream = LiftedGaussians {
        means: seeded(3 * n, 1),
        features: seeded(m.color_dim * n, 2),
        opacities: seeded(n, 3),
        scales: seeded(3 * n, 4),
        rotations: seeded(4 * n, 5),
        point: None,
    };
    Case {
        f_local: trace.f_local.detach(),
        enc: trace.dir_encoding,
        points: trace.plane_points,
        dir: trace.plane_dir,
        state,
        upstream,
    }
}

/// candle's lifted Gaussians of `f_local` (as the reconstruction computes them).
fn candle_lift(c: &Case, f_local: &Tensor) -> [Tensor; 5] {
    let model = &c.state.model;
    let dir = c.dir.unsqueeze(1).unwrap();
    let l0 = model.gen_l0.forward(f_local, &c.enc).unwrap();
    let x0 = (&c.points + l0.distance.broadcast_mul(&dir).unwrap()).unwrap();
    let mut parts = vec![(x0, l0.attrs)];
    if !c.state.cfg.model.one_plane {
        let l1 = model.gen_l1.forward(f_local, &c.enc).unwrap();
        let x1 = (&c.points - l1.distance.broadcast_mul(&dir).unwrap()).unwrap();
        parts.push((x1, l1.attrs));
    }
    let cat = |f: &dyn Fn(&(Tensor, gagavatar_net::gs_generator::GaussianAttributes)) -> Tensor| {
        let v: Vec<Tensor> = parts.iter().map(f).collect();
        Tensor::cat(&v, 1).unwrap()
    };
    [
        cat(&|p| p.0.clone()),
        cat(&|p| p.1.colors.clone()),
        cat(&|p| p.1.opacities.clone()),
        cat(&|p| p.1.scales.clone()),
        cat(&|p| p.1.rotations.clone()),
    ]
}

fn gpu_lift(c: &Case) -> Option<GpuLiftGrad> {
    let g = gpu()?;
    Some(
        GpuLiftGrad::new(
            g,
            &Tuning::default(),
            &c.state.cfg.model,
            &c.state.lifting_weights().unwrap(),
        )
        .unwrap(),
    )
}

fn up(c: &Case) -> [&Vec<f32>; 5] {
    let u = &c.upstream;
    [&u.means, &u.features, &u.opacities, &u.scales, &u.rotations]
}

fn check_against_candle(cfg: TrainConfig) {
    let c = case(cfg);
    let Some(mut lift) = gpu_lift(&c) else {
        return;
    };
    let g = gpu().unwrap();
    let fv = Var::from_tensor(&c.f_local).unwrap();
    let want = candle_lift(&c, fv.as_tensor());
    let got = lift
        .forward(
            g,
            LiftInput::Host(&flat(&c.f_local)),
            &flat(&c.enc),
            &flat(&c.points),
            &flat(&c.dir),
        )
        .unwrap();
    let names = ["means", "features", "opacities", "scales", "rotations"];
    let got_v = [
        &got.means,
        &got.features,
        &got.opacities,
        &got.scales,
        &got.rotations,
    ];
    for ((name, w), gv) in names.iter().zip(&want).zip(got_v) {
        assert_close_rel(&format!("lifted {name}"), &flat(w), gv, FORWARD_RTOL);
    }
    // L = sum_k <attr_k, upstream_k>: its gradients through candle and through the GPU.
    let mut loss = Tensor::zeros((), DType::F32, &Device::Cpu).unwrap();
    for (w, u) in want.iter().zip(up(&c)) {
        let u = Tensor::from_slice(u, w.dims(), &Device::Cpu).unwrap();
        loss = (loss + (w * u).unwrap().sum_all().unwrap()).unwrap();
    }
    let grads = loss.backward().unwrap();
    let d_f = lift.backward(g, &c.upstream).unwrap();
    assert_close_rel(
        "d F_local",
        &flat(grads.get(fv.as_tensor()).unwrap()),
        &d_f,
        GRAD_RTOL,
    );
    let vars: std::collections::HashMap<String, Var> =
        c.state.vars().unwrap().into_iter().collect();
    let got = lift.read_grads(g).unwrap();
    let expected = if c.state.cfg.model.one_plane { 8 } else { 16 };
    assert_eq!(got.len(), expected, "weight gradients returned");
    for (key, v) in &got {
        let w = grads.get(vars[key].as_tensor()).unwrap();
        assert_close_rel(&format!("d {key}"), &flat(w), v, GRAD_RTOL);
    }
    // A second backward of the same sample adds to the sums.
    lift.backward(g, &c.upstream).unwrap();
    for ((key, once), (_, twice)) in got.iter().zip(lift.read_grads(g).unwrap()) {
        let doubled: Vec<f32> = once.iter().map(|v| 2.0 * v).collect();
        assert_close_rel(&format!("2 x d {key}"), &doubled, &twice, 1e-6);
    }
}

#[test]
fn lifting_generators_match_candle_forward_and_backward() {
    check_against_candle(TrainConfig::preset("tiny").unwrap());
}

#[test]
fn one_plane_lifting_generator_matches_candle() {
    let mut cfg = TrainConfig::preset("tiny").unwrap();
    cfg.model.one_plane = true;
    check_against_candle(cfg);
}

/// The GPU backward's directional derivative along random `F_local` directions against f64
/// central differences of the CPU module (`ConvGsGenerator` with the same weights in f64),
/// `L = sum_k <attr_k, upstream_k>`.
#[test]
fn lifting_backward_matches_f64_central_differences() {
    let c = case(TrainConfig::preset("tiny").unwrap());
    let Some(mut lift) = gpu_lift(&c) else {
        return;
    };
    let g = gpu().unwrap();
    let cfg = &c.state.cfg.model;
    let vars = c.state.vars().unwrap();
    let gens: Vec<ConvGsGenerator> = (0..if cfg.one_plane { 1 } else { 2 })
        .map(|l| {
            let prefix = format!("gs_generator_l{l}.");
            let w: HashMap<String, Tensor> = vars
                .iter()
                .filter_map(|(k, v)| {
                    let rest = k.strip_prefix(&prefix)?;
                    Some((
                        rest.to_string(),
                        v.as_tensor().to_dtype(DType::F64).unwrap(),
                    ))
                })
                .collect();
            ConvGsGenerator::new(cfg, VarBuilder::from_tensors(w, DType::F64, &Device::Cpu))
                .unwrap()
        })
        .collect();
    let f64t = |t: &Tensor| t.to_dtype(DType::F64).unwrap();
    let (enc, points, dir) = (
        f64t(&c.enc),
        f64t(&c.points),
        f64t(&c.dir).unsqueeze(1).unwrap(),
    );
    let upstream: Vec<Vec<f64>> = up(&c)
        .iter()
        .map(|u| u.iter().map(|v| f64::from(*v)).collect())
        .collect();
    let loss = |f_local: &Tensor| -> f64 {
        let mut total = 0.0;
        let n = points.dim(1).unwrap();
        for (l, gen) in gens.iter().enumerate() {
            let out = gen.forward(f_local, &enc).unwrap();
            let sign = if l == 0 { 1.0 } else { -1.0 };
            let xyz =
                (&points + (out.distance.broadcast_mul(&dir).unwrap() * sign).unwrap()).unwrap();
            let a = &out.attrs;
            for (k, t) in [&xyz, &a.colors, &a.opacities, &a.scales, &a.rotations]
                .iter()
                .enumerate()
            {
                let v: Vec<f64> = t.flatten_all().unwrap().to_vec1().unwrap();
                let w = v.len() / n;
                total += v
                    .iter()
                    .zip(&upstream[k][l * n * w..(l + 1) * n * w])
                    .map(|(x, y)| x * y)
                    .sum::<f64>();
            }
        }
        total
    };
    let f0 = f64t(&c.f_local);
    lift.forward(
        g,
        LiftInput::Host(&flat(&c.f_local)),
        &flat(&c.enc),
        &flat(&c.points),
        &flat(&c.dir),
    )
    .unwrap();
    let d_f = lift.backward(g, &c.upstream).unwrap();
    for seed in 0..3u64 {
        let v: Vec<f64> = seeded(d_f.len(), 100 + seed)
            .iter()
            .map(|x| f64::from(*x))
            .collect();
        let vt = Tensor::from_slice(&v, f0.dims(), &Device::Cpu).unwrap();
        let shifted = |t: f64| (&f0 + (&vt * t).unwrap()).unwrap();
        let numeric = (loss(&shifted(FD_STEP)) - loss(&shifted(-FD_STEP))) / (2.0 * FD_STEP);
        let analytic: f64 = d_f.iter().zip(&v).map(|(a, b)| f64::from(*a) * b).sum();
        let err = (numeric - analytic).abs() / numeric.abs().max(1e-6);
        eprintln!("direction {seed}: analytic {analytic}, numeric {numeric}, relative {err:e}");
        assert!(
            err <= FD_RTOL,
            "direction {seed}: expected {numeric} (f64 central differences), got {analytic} \
             (relative error {err:e})"
        );
    }
}
