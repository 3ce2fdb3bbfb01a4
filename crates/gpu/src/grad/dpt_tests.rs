//! The DPT head's training forward and backward ([`GpuDptGrad`]) against candle's `DptHead`
//! and autograd, against f64 central differences of the CPU module, and the align-corners
//! resize's transpose alone against candle's.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use gagavatar_net::dpt::DptHead;
use gagavatar_train::bench::synthetic_batch;
use gagavatar_train::{TrainConfig, TrainState};

use super::dpt::{resize_ac_backward, GpuDptGrad};
use crate::conv::At;
use crate::testutil::{assert_close_rel, flat, gpu, seeded};
use crate::Tuning;

/// F_local relative to its largest value: the same f32 layers summed in another order.
const FORWARD_RTOL: f64 = 1e-5;

/// Weight gradients relative to each array's largest: up to eleven layers' backward between
/// `F_local` and a weight, sums over every pixel of a level.
const GRAD_RTOL: f64 = 2e-4;

/// Directional derivative (GPU, f32) along random weight directions against f64 central
/// differences of the CPU module, relative to the derivative's size. The step is small enough
/// that no ReLU's input crosses zero inside it.
const FD_RTOL: f64 = 1e-4;
const FD_STEP: f64 = 1e-6;

/// The resize transpose alone: sums of a few products.
const RESIZE_RTOL: f64 = 1e-6;

const DPT_PREFIX: &str = "base_model.";
const BACKBONE_PREFIX: &str = "base_model.dino_model.";

struct Case {
    state: TrainState,
    /// The four backbone outputs `[g^2, vit_dim]` and the DINO input `[3, d, d]`, host rows.
    tokens: [Vec<f32>; 4],
    image: Vec<f32>,
    /// candle's F_local, in the training graph.
    f_local: Tensor,
    /// A random upstream gradient of F_local.
    upstream: Vec<f32>,
}

fn case() -> Case {
    let state = TrainState::new(
        TrainConfig::preset("tiny").unwrap(),
        None,
        None,
        &Device::Cpu,
    )
    .unwrap();
    let batch = synthetic_batch(&state.cfg, 1, &Device::Cpu).unwrap();
    let (_, trace) = state
        .model
        .reconstruct_features(&batch.source_image, &batch.source_transform, None)
        .unwrap();
    let upstream = seeded(trace.f_local.elem_count(), 7);
    Case {
        tokens: trace.dino.each_ref().map(flat),
        image: flat(&trace.input_518),
        f_local: trace.f_local,
        upstream,
        state,
    }
}

/// Every DPT weight (outside the backbone) by checkpoint key.
fn dpt_weights(state: &TrainState) -> HashMap<String, Vec<f32>> {
    state
        .vars()
        .unwrap()
        .into_iter()
        .filter(|(k, _)| k.starts_with(DPT_PREFIX) && !k.starts_with(BACKBONE_PREFIX))
        .map(|(k, v)| (k, flat(v.as_tensor())))
        .collect()
}

fn gpu_dpt(c: &Case) -> Option<GpuDptGrad> {
    let g = gpu()?;
    Some(
        GpuDptGrad::new(
            g,
            &Tuning::default(),
            &c.state.cfg.model,
            &dpt_weights(&c.state),
        )
        .unwrap(),
    )
}

fn tokens(c: &Case) -> [&[f32]; 4] {
    c.tokens.each_ref().map(|t| t.as_slice())
}

#[test]
fn dpt_head_matches_candle_forward_and_backward() {
    let c = case();
    let Some(mut dpt) = gpu_dpt(&c) else {
        return;
    };
    let g = gpu().unwrap();
    dpt.forward(g, tokens(&c), &c.image).unwrap();
    assert_close_rel(
        "F_local",
        &flat(&c.f_local),
        &dpt.read_f_local(g).unwrap(),
        FORWARD_RTOL,
    );
    let u = Tensor::from_slice(&c.upstream, c.f_local.dims(), &Device::Cpu).unwrap();
    let grads = (&c.f_local * u)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    dpt.backward(g, &c.upstream).unwrap();
    let vars: HashMap<String, Var> = c.state.vars().unwrap().into_iter().collect();
    let got = dpt.read_grads(g).unwrap();
    let trained: Vec<&String> = vars
        .keys()
        .filter(|k| k.starts_with(DPT_PREFIX) && !k.starts_with(BACKBONE_PREFIX))
        .filter(|k| grads.get(vars[*k].as_tensor()).is_some())
        .collect();
    assert_eq!(
        got.len(),
        trained.len(),
        "one gradient per DPT weight that candle trains: got {:?}",
        got.iter().map(|(k, _)| k).collect::<Vec<_>>()
    );
    for (key, v) in &got {
        let w = grads
            .get(vars[key].as_tensor())
            .unwrap_or_else(|| panic!("candle has no gradient of {key}"));
        assert_close_rel(&format!("d {key}"), &flat(w), v, GRAD_RTOL);
    }
    // A second backward of the same sample adds to the sums; new weights start them again.
    dpt.backward(g, &c.upstream).unwrap();
    let twice = dpt.read_grads(g).unwrap();
    for ((key, once), (_, twice)) in got.iter().zip(&twice) {
        let doubled: Vec<f32> = once.iter().map(|v| 2.0 * v).collect();
        assert_close_rel(&format!("2 x d {key}"), &doubled, twice, 1e-6);
    }
    let w = dpt_weights(&c.state);
    dpt.set_weights(g, &|k| w.get(k).map(|v| v.as_slice()))
        .unwrap();
    assert!(dpt.read_grads(g).is_err(), "no backward since new weights");
    dpt.forward(g, tokens(&c), &c.image).unwrap();
    dpt.backward(g, &c.upstream).unwrap();
    for ((key, once), (_, again)) in got.iter().zip(dpt.read_grads(g).unwrap()) {
        assert_close_rel(&format!("d {key} after set_weights"), once, &again, 1e-6);
    }
}

/// The GPU backward's directional derivative along random directions of every weight against
/// f64 central differences of the CPU module (`DptHead` with the same weights in f64),
/// `L = <F_local, upstream>`.
#[test]
fn dpt_backward_matches_f64_central_differences() {
    let c = case();
    let Some(mut dpt) = gpu_dpt(&c) else {
        return;
    };
    let g = gpu().unwrap();
    let cfg = &c.state.cfg.model;
    let w32 = dpt_weights(&c.state);
    let mut keys: Vec<&String> = w32.keys().collect();
    keys.sort();
    let shapes: HashMap<String, Vec<usize>> = c
        .state
        .vars()
        .unwrap()
        .into_iter()
        .map(|(k, v)| (k, v.as_tensor().dims().to_vec()))
        .collect();
    let dev = Device::Cpu;
    let g2 = cfg.grid() * cfg.grid();
    let feats: [Tensor; 4] = c.tokens.each_ref().map(|t| {
        Tensor::from_slice(t, (1, g2, cfg.vit_dim), &dev)
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
    });
    let image = Tensor::from_slice(&c.image, (1, 3, cfg.dino_size, cfg.dino_size), &dev)
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap();
    let upstream: Vec<f64> = c.upstream.iter().map(|v| f64::from(*v)).collect();
    let loss = |w: &HashMap<String, Vec<f64>>| -> f64 {
        let tensors: HashMap<String, Tensor> = w
            .iter()
            .map(|(k, v)| {
                (
                    k.strip_prefix(DPT_PREFIX).unwrap().to_string(),
                    Tensor::from_slice(v, shapes[k].as_slice(), &dev).unwrap(),
                )
            })
            .collect();
        let head = DptHead::new(cfg, VarBuilder::from_tensors(tensors, DType::F64, &dev)).unwrap();
        let out: Vec<f64> = head
            .forward(&feats, &image)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        out.iter().zip(&upstream).map(|(a, b)| a * b).sum()
    };
    dpt.forward(g, tokens(&c), &c.image).unwrap();
    dpt.backward(g, &c.upstream).unwrap();
    let grads: HashMap<String, Vec<f32>> = dpt.read_grads(g).unwrap().into_iter().collect();
    for seed in 0..2u64 {
        let dirs: HashMap<&String, Vec<f64>> = keys
            .iter()
            .enumerate()
            .map(|(i, k)| {
                let v = seeded(w32[*k].len(), 1000 * seed + i as u64 + 1);
                (*k, v.iter().map(|x| f64::from(*x)).collect())
            })
            .collect();
        let shifted = |t: f64| -> HashMap<String, Vec<f64>> {
            keys.iter()
                .map(|k| {
                    let v = w32[*k]
                        .iter()
                        .zip(&dirs[k])
                        .map(|(w, d)| f64::from(*w) + t * d)
                        .collect();
                    ((*k).clone(), v)
                })
                .collect()
        };
        let numeric = (loss(&shifted(FD_STEP)) - loss(&shifted(-FD_STEP))) / (2.0 * FD_STEP);
        // Weights without a gradient (refinenet.0's unused first unit) do not move L.
        let analytic: f64 = keys
            .iter()
            .filter_map(|k| Some((grads.get(*k)?, &dirs[k])))
            .map(|(gr, d)| {
                gr.iter()
                    .zip(d)
                    .map(|(a, b)| f64::from(*a) * b)
                    .sum::<f64>()
            })
            .sum();
        let err = (numeric - analytic).abs() / numeric.abs().max(1e-6);
        eprintln!("direction {seed}: analytic {analytic}, numeric {numeric}, relative {err:e}");
        assert!(
            err <= FD_RTOL,
            "direction {seed}: expected {numeric} (f64 central differences), got {analytic} \
             (relative error {err:e})"
        );
    }
}

/// `resize_ac_backward` is the transpose of the forward resize: `<resize(x), dy> = <x, dx>`
/// for candle's align-corners upsampling, at DPT's sizes (19 -> 37: not a factor of two) and
/// at degenerate ones.
#[test]
fn align_corners_resize_backward_is_the_forward_transposed() {
    let Some(g) = gpu() else {
        return;
    };
    for (c, h, w, oh, ow) in [
        (3, 5, 5, 9, 9),
        (2, 10, 10, 19, 19),
        (2, 19, 19, 37, 37),
        (1, 4, 7, 8, 14),
        (1, 1, 1, 3, 3),
        (1, 6, 6, 6, 6),
    ] {
        let dy = seeded(c * oh * ow, (h * 100 + oh) as u64);
        let dyv = Tensor::from_slice(&dy, (1, c, oh, ow), &Device::Cpu).unwrap();
        let x = Var::from_tensor(
            &Tensor::from_slice(&seeded(c * h * w, 3), (1, c, h, w), &Device::Cpu).unwrap(),
        )
        .unwrap();
        let y = gagavatar_ops::resize(
            x.as_tensor(),
            oh,
            ow,
            gagavatar_ops::ResizeMode::AlignCorners,
        )
        .unwrap();
        let want = flat(
            (y * dyv)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap()
                .get(x.as_tensor())
                .unwrap(),
        );
        let dyb = g.buffer_with("dy", &dy);
        let dxb = g.buffer("dx", 4 * (c * h * w) as u64);
        let step =
            resize_ac_backward(g, (c, h, w), (oh, ow), At::new(&dyb), At::new(&dxb)).unwrap();
        g.submit(&[step]);
        let got = g.read_f32(&dxb, c * h * w).unwrap();
        assert_close_rel(
            &format!("resize gradient {h}x{w} -> {oh}x{ow}"),
            &want,
            &got,
            RESIZE_RTOL,
        );
    }
}

/// [`GpuDptGrad`] against candle's `DptHead` and autograd at `cfg`'s size, with the checkpoint
/// initialisation's seeded weights (no training state: release size stays a few seconds on
/// the CPU), random backbone outputs, DINO input and upstream gradient.
fn compare_seeded(cfg: &gagavatar_net::ModelConfig) {
    let Some(g) = gpu() else {
        return;
    };
    let dev = Device::Cpu;
    let is_dpt = |k: &str| k.starts_with(DPT_PREFIX) && !k.starts_with(BACKBONE_PREFIX);
    let seeded_w = gagavatar_net::checkpoint::init_weights_where(cfg, 3, &is_dpt).unwrap();
    let varmap = candle_nn::VarMap::new();
    let head = DptHead::new(
        cfg,
        VarBuilder::from_varmap(&varmap, DType::F32, &dev).pp("base_model"),
    )
    .unwrap();
    for (key, var) in varmap.data().lock().unwrap().iter() {
        let (shape, v) = &seeded_w[key];
        var.set(&Tensor::from_vec(v.clone(), shape.as_slice(), &dev).unwrap())
            .unwrap();
    }
    let (g2, d, s) = (cfg.grid() * cfg.grid(), cfg.dino_size, cfg.plane_size());
    let tokens: Vec<Vec<f32>> = (0..4).map(|k| seeded(g2 * cfg.vit_dim, 20 + k)).collect();
    let image: Vec<f32> = seeded(3 * d * d, 30).iter().map(|v| 2.0 * v).collect();
    let upstream = seeded(cfg.dpt_features * s * s, 31);
    let feats: [Tensor; 4] =
        [0, 1, 2, 3].map(|k| Tensor::from_slice(&tokens[k], (1, g2, cfg.vit_dim), &dev).unwrap());
    let img = Tensor::from_slice(&image, (1, 3, d, d), &dev).unwrap();
    let f_local = head.forward(&feats, &img).unwrap();
    let u = Tensor::from_slice(&upstream, f_local.dims(), &dev).unwrap();
    let grads = (&f_local * u)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();

    let host: HashMap<String, Vec<f32>> = seeded_w.into_iter().map(|(k, (_, v))| (k, v)).collect();
    let mut dpt = GpuDptGrad::new(g, &Tuning::default(), cfg, &host).unwrap();
    let t: [&[f32]; 4] = [0, 1, 2, 3].map(|k| tokens[k].as_slice());
    dpt.forward(g, t, &image).unwrap();
    let label = &cfg.name;
    assert_close_rel(
        &format!("{label} F_local"),
        &flat(&f_local),
        &dpt.read_f_local(g).unwrap(),
        FORWARD_RTOL,
    );
    dpt.backward(g, &upstream).unwrap();
    let vars: HashMap<String, Var> = varmap
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    let got = dpt.read_grads(g).unwrap();
    let trained = vars
        .values()
        .filter(|v| grads.get(v.as_tensor()).is_some())
        .count();
    assert_eq!(
        got.len(),
        trained,
        "{label}: one gradient per trained weight"
    );
    for (key, v) in &got {
        let w = grads
            .get(vars[key].as_tensor())
            .unwrap_or_else(|| panic!("candle has no gradient of {key}"));
        assert_close_rel(&format!("{label} d {key}"), &flat(w), v, GRAD_RTOL);
    }
}

#[test]
fn seeded_dpt_head_matches_candle() {
    compare_seeded(&gagavatar_net::ModelConfig::tiny());
}

/// Release size (four 37x37 maps of 768 channels in, F_local 256 x 296 x 296 out): the device
/// check runs it; by hand, `cargo test --release -p gagavatar-gpu release_dpt -- --ignored
/// --nocapture`.
#[test]
#[ignore = "release size: many minutes on lavapipe"]
fn release_dpt_head_matches_candle() {
    compare_seeded(&gagavatar_net::ModelConfig::release());
}
