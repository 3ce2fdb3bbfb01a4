//! The encoder (source preprocessing, DINOv2, DPT head) against the PyTorch reference goldens of
//! the `tiny` preset (`tools/reference/net_reference.py`).

use std::collections::{BTreeMap, HashMap};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use gagavatar_net::dino::{f_id, preprocess, Dinov2};
use gagavatar_net::dpt::DptHead;
use gagavatar_net::ModelConfig;

mod common;
use common::{assert_close, get, load};

// The goldens are float64 results (of float32 weights and inputs) stored as f32.
/// Resize + normalise in f32: rounding of a few multiply-adds, amplified 4.4x by 1/std
/// (5e-7 measured).
const PREPROCESS_TOL: f64 = 1e-5;
/// Features after four ViT blocks or the DPT head's ~20 convolutions computed in f32 (sums of
/// hundreds of products, polynomial exp/erf): ~1e-7 relative rounding per layer grows to a few
/// 1e-6 on O(1-10) values (3e-6 measured).
const FEATURE_TOL: f64 = 1e-4;
/// The same in f64: only the goldens' own f32 storage (half an ulp of values up to ~16) remains
/// (5e-7 measured), tight enough to catch a wrong epsilon or a swapped resize rule.
const F64_TOL: f64 = 2e-6;

fn weights(dtype: DType) -> VarBuilder<'static> {
    VarBuilder::from_tensors(load("tiny_weights.safetensors"), dtype, &Device::Cpu)
}

fn io() -> HashMap<String, Tensor> {
    load("tiny_io.safetensors")
}

fn tiny() -> ModelConfig {
    ModelConfig::tiny()
}

fn dino_golden(io: &HashMap<String, Tensor>) -> [Tensor; 4] {
    [0, 1, 2, 3].map(|k| get(io, &format!("dino_{k}")).clone())
}

#[test]
fn preprocess_matches_golden() {
    let io = io();
    let x = preprocess(get(&io, "source_image"), &tiny()).expect("preprocess");
    assert_close("input_518", &x, get(&io, "input_518"), PREPROCESS_TOL);
}

#[test]
fn dinov2_matches_golden() {
    let io = io();
    let dino = Dinov2::new(&tiny(), weights(DType::F32).pp("base_model.dino_model")).expect("load");
    let outs = dino.forward(get(&io, "input_518")).expect("forward");
    for (k, (out, want)) in outs.iter().zip(dino_golden(&io).iter()).enumerate() {
        assert_close(&format!("dino_{k}"), out, want, FEATURE_TOL);
    }
    let id = f_id(&outs[3]).expect("f_id");
    assert_close("f_id", &id, get(&io, "f_id"), FEATURE_TOL);
}

#[test]
fn dpt_head_matches_golden() {
    let io = io();
    let head = DptHead::new(&tiny(), weights(DType::F32).pp("base_model")).expect("load");
    let f_local = head
        .forward(&dino_golden(&io), get(&io, "input_518"))
        .expect("forward");
    assert_close("f_local", &f_local, get(&io, "f_local"), FEATURE_TOL);
}

/// The whole encoder chained in f64 (weights and source image widened): preprocess, ViT, head.
#[test]
fn encoder_runs_in_f64() {
    let io = io();
    let cfg = tiny();
    let vb = weights(DType::F64);
    let dino = Dinov2::new(&cfg, vb.pp("base_model.dino_model")).expect("load dino");
    let head = DptHead::new(&cfg, vb.pp("base_model")).expect("load head");
    let image = get(&io, "source_image")
        .to_dtype(DType::F64)
        .expect("to f64");
    let x = preprocess(&image, &cfg).expect("preprocess");
    assert_eq!(x.dtype(), DType::F64);
    let feats = dino.forward(&x).expect("dino");
    let f_local = head.forward(&feats, &x).expect("head");
    assert_eq!(f_local.dtype(), DType::F64);
    assert_close("f64 input_518", &x, get(&io, "input_518"), F64_TOL);
    for (k, out) in feats.iter().enumerate() {
        assert_close(
            &format!("f64 dino_{k}"),
            out,
            get(&io, &format!("dino_{k}")),
            F64_TOL,
        );
    }
    let id = f_id(&feats[3]).expect("f_id");
    assert_close("f64 f_id", &id, get(&io, "f_id"), F64_TOL);
    assert_close("f64 f_local", &f_local, get(&io, "f_local"), F64_TOL);
}

/// Names and shapes the modules request under `base_model.`.
fn requested(cfg: &ModelConfig) -> BTreeMap<String, Vec<usize>> {
    let map = VarMap::new();
    let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
    Dinov2::new(cfg, vb.pp("base_model.dino_model")).expect("dino");
    DptHead::new(cfg, vb.pp("base_model")).expect("head");
    let data = map.data().lock().expect("varmap lock");
    data.iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect()
}

#[test]
fn modules_request_exactly_the_base_model_keys() {
    let want: BTreeMap<String, Vec<usize>> = load("tiny_weights.safetensors")
        .into_iter()
        .filter(|(k, _)| k.starts_with("base_model."))
        .map(|(k, v)| (k, v.dims().to_vec()))
        .collect();
    let got = requested(&tiny());
    for (k, shape) in &want {
        assert_eq!(got.get(k), Some(shape), "checkpoint key {k}");
    }
    for k in got.keys() {
        assert!(
            want.contains_key(k),
            "requested key {k} is not in the checkpoint"
        );
    }
}

#[test]
fn release_key_count_matches_the_checkpoint() {
    // The release state dict has 7 DINO tensors outside the blocks, 14 per block, 12 blocks,
    // and 60 DPT-head tensors: 235 `base_model.` keys (spec/official_state_dict.tsv).
    let got = requested(&ModelConfig::release());
    assert_eq!(got.len(), 7 + 14 * 12 + 60);
    assert_eq!(got["base_model.dino_model.pos_embed"], [1, 1370, 768]);
    assert_eq!(got["base_model.resize_layers.1.weight"], [512, 512, 2, 2]);
    assert_eq!(got["base_model.layer_rn.3.weight"], [256, 1027, 3, 3]);
}

/// The modules with every requested weight drawn from N(0, 0.1^2), so that a bug mixing rows,
/// batch items or channels changes the outputs.
fn random_modules(cfg: &ModelConfig) -> (Dinov2, DptHead) {
    let tensors: HashMap<String, Tensor> = requested(cfg)
        .into_iter()
        .map(|(k, dims)| {
            let t = Tensor::randn(0f32, 0.1, dims, &Device::Cpu).expect("randn");
            (k, t)
        })
        .collect();
    let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
    (
        Dinov2::new(cfg, vb.pp("base_model.dino_model")).expect("dino"),
        DptHead::new(cfg, vb.pp("base_model")).expect("head"),
    )
}

#[test]
fn bad_inputs_are_errors() {
    let cfg = tiny();
    let (dino, head) = random_modules(&cfg);
    let s = cfg.dino_size;
    let z = |dims: &[usize]| Tensor::zeros(dims, DType::F32, &Device::Cpu).expect("zeros");
    // Sizes the position embedding does not cover, wrong channel counts, wrong rank.
    for dims in [
        vec![1, 3, s + 14, s + 14],
        vec![1, 3, s - 1, s - 1],
        vec![1, 3, s, s + 14],
        vec![1, 4, s, s],
        vec![3, s, s],
    ] {
        let err = dino.forward(&z(&dims));
        assert!(err.is_err(), "Dinov2 accepted {dims:?}");
    }
    for dims in [vec![1, 3, 32, 32], vec![1, 1, 64, 64], vec![3, 64, 64]] {
        assert!(
            preprocess(&z(&dims), &cfg).is_err(),
            "preprocess accepted {dims:?}"
        );
    }
    let g2 = cfg.grid() * cfg.grid();
    let good = [0, 1, 2, 3].map(|_| z(&[1, g2, cfg.vit_dim]));
    let image = z(&[1, 3, s, s]);
    assert!(head.forward(&good, &image).is_ok());
    let mut wrong_tokens = good.clone();
    wrong_tokens[2] = z(&[1, g2 + 1, cfg.vit_dim]);
    assert!(head.forward(&wrong_tokens, &image).is_err());
    let mut wrong_width = good.clone();
    wrong_width[0] = z(&[1, g2, cfg.vit_dim + 1]);
    assert!(head.forward(&wrong_width, &image).is_err());
    let wrong_batch = [0, 1, 2, 3].map(|_| z(&[2, g2, cfg.vit_dim]));
    assert!(head.forward(&wrong_batch, &image).is_err());
    assert!(head.forward(&good, &z(&[1, 3, s + 14, s + 14])).is_err());
    assert!(f_id(&z(&[1, 0, cfg.vit_dim])).is_err());
}

/// Batch items are independent: item 1 of a batch of two equals the same image alone.
#[test]
fn batch_items_are_independent() {
    let cfg = tiny();
    let (dino, head) = random_modules(&cfg);
    let s = cfg.dino_size;
    let x = Tensor::randn(0f32, 1.0, (2, 3, s, s), &Device::Cpu).expect("randn");
    let both = dino.forward(&x).expect("dino batch");
    let one_x = x.narrow(0, 1, 1).expect("narrow");
    let one = dino.forward(&one_x).expect("dino single");
    for k in 0..4 {
        let b1 = both[k].narrow(0, 1, 1).expect("narrow");
        assert_close(&format!("batch dino_{k}"), &b1, &one[k], 1e-5);
    }
    let fb = head.forward(&both, &x).expect("head batch");
    let f1 = head.forward(&one, &one_x).expect("head single");
    assert_close(
        "batch f_local",
        &fb.narrow(0, 1, 1).expect("narrow"),
        &f1,
        1e-5,
    );
}

/// The DPT head is trained: every parameter the forward uses gets a non-zero gradient.
#[test]
fn dpt_head_is_differentiable() {
    let cfg = tiny();
    let map = VarMap::new();
    let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
    let head = DptHead::new(&cfg, vb.pp("base_model")).expect("head");
    let vars: Vec<(String, candle_core::Var)> = {
        let data = map.data().lock().expect("varmap lock");
        data.iter().map(|(k, v)| (k.clone(), v.clone())).collect()
    };
    for (_, var) in &vars {
        let r = Tensor::randn(0f32, 0.1, var.dims(), &Device::Cpu).expect("randn");
        var.set(&r).expect("set");
    }
    let g2 = cfg.grid() * cfg.grid();
    let feats = [0, 1, 2, 3]
        .map(|_| Tensor::randn(0f32, 1.0, (1, g2, cfg.vit_dim), &Device::Cpu).expect("randn"));
    let s = cfg.dino_size;
    let image = Tensor::randn(0f32, 1.0, (1, 3, s, s), &Device::Cpu).expect("randn");
    let loss = head
        .forward(&feats, &image)
        .and_then(|f| f.sqr())
        .and_then(|f| f.sum_all())
        .expect("forward");
    let grads = loss.backward().expect("backward");
    for (name, var) in &vars {
        // Spec section 4: refinenet.0 has no skip input, so its resConfUnit1 never runs.
        let unused = name.starts_with("base_model.refinenet.0.resConfUnit1.");
        let norm = grads
            .get(var.as_tensor())
            .map(|g| {
                g.abs()
                    .and_then(|a| a.sum_all())
                    .and_then(|a| a.to_scalar::<f32>())
            })
            .transpose()
            .expect("gradient norm");
        match (unused, norm) {
            (true, n) => assert!(
                n.is_none_or(|n| n == 0.0),
                "{name}: unused but has gradient"
            ),
            (false, Some(n)) => assert!(n > 0.0 && n.is_finite(), "{name}: gradient sum {n}"),
            (false, None) => panic!("{name}: no gradient"),
        }
    }
}
