//! Adam against torch.optim.Adam + LinearLR (the release's optimiser) and exact resume.

mod common;

use std::collections::HashMap;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use common::*;
use gagavatar_train::adam::{Adam, AdamConfig, SCHEDULE_STEP_KEY};

/// f32 parameters after several steps against PyTorch's f32 run (relative above 1): only the
/// order of rounding inside one update differs.
const TOL_PARAM: f64 = 1e-6;

const NAMES: [&str; 4] = [
    "enc.w",
    "upsampler.style_mlp.0.weight",
    "upsampler.final_linear.bias",
    "gs_generator_g.color_layers.0.bias",
];

fn run_golden(prefix: &str, cfg: AdamConfig) {
    let io = load("adam.safetensors");
    let vars: Vec<(String, Var)> = NAMES
        .iter()
        .map(|n| {
            (
                n.to_string(),
                Var::from_tensor(get(&io, &format!("{prefix}init.{n}"))).unwrap(),
            )
        })
        .collect();
    let mut opt = Adam::new(vars.clone(), cfg).unwrap();
    let lrs = to_f64(get(&io, &format!("{prefix}lrs")));
    for (step, want_lr) in lrs.iter().enumerate() {
        let got_lr = opt.lr("enc.w").unwrap();
        assert!(
            (got_lr - want_lr).abs() <= 1e-15 * want_lr,
            "{prefix} step {step}: lr {got_lr}, expected {want_lr}"
        );
        let low = opt.lr("upsampler.style_mlp.0.weight").unwrap();
        assert!(
            (low - 0.1 * want_lr).abs() <= 1e-15 * want_lr,
            "low-lr group at step {step}: {low}"
        );
        let mut grads = GradStore::default();
        let mut missing = Vec::new();
        for (n, v) in &vars {
            match io.get(&format!("{prefix}grad{step}.{n}")) {
                Some(g) => {
                    grads.insert(v.as_tensor(), g.clone());
                }
                None => missing.push(n.clone()),
            }
        }
        opt.step(&grads).unwrap();
        missing.sort();
        assert_eq!(
            opt.skipped(),
            missing.as_slice(),
            "{prefix} step {step}: skipped parameters"
        );
        for (n, v) in &vars {
            assert_close(
                &format!("{prefix} step {step} {n}"),
                v.as_tensor(),
                get(&io, &format!("{prefix}param{step}.{n}")),
                TOL_PARAM,
            );
        }
    }
    assert_eq!(opt.schedule_step(), lrs.len() as u64);
}

#[test]
fn golden_release_settings() {
    // lr 1e-4 (1e-5 for style_mlp / final_linear), decay over 3 steps, 6 steps run.
    run_golden("release.", AdamConfig::with_lr(1e-4, 3));
}

#[test]
fn golden_large_lr() {
    // A large rate makes every update visible far above f32 rounding.
    run_golden("large.", AdamConfig::with_lr(1e-2, 4));
}

#[test]
fn schedule_and_groups() {
    let cfg = AdamConfig::release(200_000);
    assert_eq!(
        (cfg.lr, cfg.beta1, cfg.beta2, cfg.eps),
        (1e-4, 0.0, 0.99, 1e-8)
    );
    assert_eq!(cfg.factor(0), 1.0);
    assert!((cfg.factor(100_000) - 0.55).abs() < 1e-15);
    assert!((cfg.factor(200_000) - 0.1).abs() < 1e-15);
    assert!((cfg.factor(500_000) - 0.1).abs() < 1e-15);
    assert_eq!(cfg.base_lr("upsampler.style_mlp.1.weight"), 1e-4 * 0.1);
    assert_eq!(cfg.base_lr("upsampler.final_linear.weight"), 1e-4 * 0.1);
    assert_eq!(cfg.base_lr("gs_generator_l0.gaussian_conv.0.weight"), 1e-4);
    assert_eq!(cfg.base_lr("base_model.dpt.projects.0.weight"), 1e-4);
    assert_eq!(
        AdamConfig::release(0).factor(10),
        1.0,
        "no decay without a horizon"
    );
}

fn quadratic_grads(vars: &[(String, Var)], step: usize, skip: Option<&str>) -> GradStore {
    let mut g = GradStore::default();
    for (i, (n, v)) in vars.iter().enumerate() {
        if Some(n.as_str()) == skip {
            continue;
        }
        // A step-dependent gradient so every step differs.
        let t = (v
            .as_tensor()
            .affine(1.0 + 0.1 * i as f64, 0.3 * step as f64 - 0.5))
        .unwrap();
        g.insert(v.as_tensor(), t);
    }
    g
}

fn make_vars(seed: u64) -> Vec<(String, Var)> {
    let mut rng = Rng::from_state(seed);
    NAMES
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let len = 3 + 2 * i;
            let v: Vec<f32> = (0..len).map(|_| rng.normal() as f32).collect();
            (
                n.to_string(),
                Var::from_tensor(&Tensor::from_vec(v, len, &Device::Cpu).unwrap()).unwrap(),
            )
        })
        .collect()
}

fn values(vars: &[(String, Var)]) -> Vec<Vec<u32>> {
    vars.iter()
        .map(|(_, v)| {
            v.as_tensor()
                .to_vec1::<f32>()
                .unwrap()
                .iter()
                .map(|x| x.to_bits())
                .collect()
        })
        .collect()
}

#[test]
fn resume_is_exact() {
    let cfg = AdamConfig::with_lr(1e-2, 5);
    // Uninterrupted: 7 steps (one parameter skipped at step 1).
    let straight = make_vars(3);
    let mut a = Adam::new(straight.clone(), cfg.clone()).unwrap();
    for s in 0..7 {
        a.step(&quadratic_grads(&straight, s, (s == 1).then_some("enc.w")))
            .unwrap();
    }
    // Interrupted after 4 steps: state through a safetensors file, fresh optimiser and copies.
    let first = make_vars(3);
    let mut b = Adam::new(first.clone(), cfg.clone()).unwrap();
    for s in 0..4 {
        b.step(&quadratic_grads(&first, s, (s == 1).then_some("enc.w")))
            .unwrap();
    }
    let dir = std::env::temp_dir().join(format!("gagavatar-adam-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("state.safetensors");
    let state = b.state_tensors().unwrap();
    assert_eq!(state.len(), 3 * NAMES.len() + 1);
    candle_core::safetensors::save(&state, &path).unwrap();
    let loaded = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    let second: Vec<(String, Var)> = first
        .iter()
        .map(|(n, v)| {
            (
                n.clone(),
                Var::from_tensor(&v.as_tensor().copy().unwrap()).unwrap(),
            )
        })
        .collect();
    let mut c = Adam::new(second.clone(), cfg).unwrap();
    c.load_state(&loaded).unwrap();
    assert_eq!(c.schedule_step(), 4);
    for s in 4..7 {
        c.step(&quadratic_grads(&second, s, None)).unwrap();
    }
    assert_eq!(
        values(&second),
        values(&straight),
        "resumed run differs from the straight one"
    );
}

#[test]
fn frozen_parameters_are_skipped_and_reported() {
    let vars = make_vars(4);
    let before = values(&vars);
    let mut opt = Adam::new(vars.clone(), AdamConfig::release(10)).unwrap();
    // A real backward pass in which two parameters take no part.
    let loss = (vars[0].1.as_tensor().sqr().unwrap().sum_all().unwrap()
        + vars[2].1.as_tensor().sum_all().unwrap())
    .unwrap();
    opt.step(&loss.backward().unwrap()).unwrap();
    let mut want = vec![NAMES[1].to_string(), NAMES[3].to_string()];
    want.sort();
    assert_eq!(opt.skipped(), want.as_slice());
    let after = values(&vars);
    for i in 0..4 {
        assert_eq!(
            before[i] == after[i],
            i == 1 || i == 3,
            "parameter {} changed: {}",
            NAMES[i],
            before[i] != after[i]
        );
    }
    // Only updated parameters have state.
    let st = opt.state_tensors().unwrap();
    assert!(
        st.contains_key("enc.w.exp_avg")
            && !st.contains_key("upsampler.style_mlp.0.weight.exp_avg")
    );
}

#[test]
fn bad_states_and_settings_are_errors() {
    let vars = make_vars(5);
    let mut opt = Adam::new(vars.clone(), AdamConfig::release(10)).unwrap();
    opt.step(&quadratic_grads(&vars, 0, None)).unwrap();
    let good = opt.state_tensors().unwrap();
    let dev = Device::Cpu;
    let cases: Vec<(HashMap<String, Tensor>, &str)> = vec![
        (
            {
                let mut s = good.clone();
                s.insert(
                    "enc.w.exp_avg".into(),
                    Tensor::zeros(4, DType::F32, &dev).unwrap(),
                );
                s
            },
            "has shape",
        ),
        (
            {
                let mut s = good.clone();
                s.insert(
                    "decoder.x.exp_avg".into(),
                    Tensor::zeros(4, DType::F32, &dev).unwrap(),
                );
                s
            },
            "keys of no parameter",
        ),
        (
            {
                let mut s = good.clone();
                s.remove(SCHEDULE_STEP_KEY);
                s
            },
            "is missing",
        ),
        (
            {
                let mut s = good.clone();
                s.remove("enc.w.exp_avg_sq");
                s
            },
            "only some",
        ),
        (
            {
                let mut s = good.clone();
                s.insert("enc.w.step".into(), Tensor::new(&[-3i64], &dev).unwrap());
                s
            },
            "count >= 0",
        ),
    ];
    let before = opt.state_tensors().unwrap();
    for (state, what) in cases {
        let e = opt.load_state(&state).unwrap_err().to_string();
        assert!(e.contains(what), "expected `{what}` in `{e}`");
        // Unchanged by the failed load.
        let now = opt.state_tensors().unwrap();
        for (k, v) in &before {
            assert_eq!(to_f64(v), to_f64(&now[k]), "{k} changed by a failed load");
        }
    }
    // A gradient of the wrong shape fails before anything changes.
    let mut g = GradStore::default();
    g.insert(
        vars[0].1.as_tensor(),
        Tensor::zeros(7, DType::F32, &dev).unwrap(),
    );
    assert!(opt.step(&g).unwrap_err().to_string().contains("has shape"));
    assert_eq!(opt.schedule_step(), 1);
    // Duplicate names, bad betas.
    let dup = vec![vars[0].clone(), vars[0].clone()];
    assert!(Adam::new(dup, AdamConfig::release(1)).is_err());
    let mut cfg = AdamConfig::release(1);
    cfg.beta2 = 1.0;
    assert!(Adam::new(vars, cfg).is_err());
}
