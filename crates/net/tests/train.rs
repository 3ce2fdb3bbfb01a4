//! The network as a trainable model (`gagavatar_net::train`, `GagAvatar::train_forward`) on
//! the `tiny` preset: which parameters are variables and which receive gradients, autograd
//! against central finite differences in f64, the trainable path against the inference path
//! and the PyTorch goldens, no stale weight copies, seeded noise, the frozen-backbone rule, the
//! ablation switches, and export back to the checkpoint layout.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use gagavatar_net::checkpoint::{
    build_model, expected_keys, init_weights, load_model, write_tensors,
};
use gagavatar_net::model::{GagAvatar, TrainOutput};
use gagavatar_net::style_unet::Noise;
use gagavatar_net::train::{
    export_weights, is_trainable_key, trainable_model, trainable_model_as, BACKBONE_PREFIX,
    NOISE_BUFFER_PREFIX,
};
use gagavatar_net::ModelConfig;
use gagavatar_splat::testscene::Rng;

mod common;
use common::{assert_close, get, load, to_vec_f64};

/// Trainable (live weights, differentiable ops) vs inference (transposed copies, fused
/// kernels) in f32: the same arithmetic up to rounding and the fused kernels' polynomial
/// exp/erf. Features measured <= 5e-6, except the lifted rotations (1.1e-5: normalising a
/// short raw quaternion amplifies its rounding).
const PATH_FEATURE_TOL: f64 = 5e-5;
/// The same on the splatted and rendered images (thousands of Gaussians per pixel, ~40 convs;
/// 1.7e-5 measured on coarse).
const PATH_IMAGE_TOL: f64 = 2e-4;
/// The reference goldens' bars (as `tests/model.rs`): features 1e-4, images 1e-3.
const FEATURE_TOL: f64 = 1e-4;
const IMAGE_TOL: f64 = 1e-3;
/// Central finite-difference step on one scalar weight in f64. The loss (~1e-4, a difference of
/// O(0.1) terms) carries ~1e-17 of rounding, i.e. ~1e-11 of noise in the numeric derivative;
/// the step is small enough that no splat threshold (alpha >= 1/255, tile radii) or ReLU kink
/// of the tested scalars lies within it.
const FD_STEP: f64 = 1e-6;
/// Relative error allowed between autograd and the finite difference. Measured: ~1e-8 for
/// gradients of ~1e-3; 2.2e-5 for the smallest tested gradient (2.3e-7, the expression
/// rotations, normalised across all points), where the ~5e-12 noise above dominates.
const FD_REL_TOL: f64 = 1e-4;

fn tiny_weights() -> HashMap<String, Tensor> {
    load("tiny_weights.safetensors")
}

/// The golden scene: source image and camera, target vertices and camera, batch 1.
struct Scene {
    image: Tensor,
    source: Tensor,
    vertices: Tensor,
    target: Tensor,
}

impl Scene {
    fn golden(dtype: DType) -> Self {
        let io = load("tiny_io.safetensors");
        let f = |k: &str| get(&io, k).to_dtype(dtype).unwrap();
        Self {
            image: f("source_image"),
            source: f("source_transform"),
            vertices: f("target_points"),
            target: f("target_transform"),
        }
    }

    /// Two pairs: the golden one, and a mirrored source driving shrunk vertices seen from the
    /// source camera.
    fn pair(dtype: DType) -> Self {
        let a = Self::golden(dtype);
        let flipped = {
            let w = a.image.dim(3).unwrap();
            let idx: Vec<u32> = (0..w as u32).rev().collect();
            let idx = Tensor::new(idx.as_slice(), &Device::Cpu).unwrap();
            a.image.index_select(&idx, 3).unwrap()
        };
        Self {
            image: Tensor::cat(&[&a.image, &flipped], 0).unwrap(),
            source: Tensor::cat(&[&a.source, &a.target], 0).unwrap(),
            vertices: Tensor::cat(&[&a.vertices, &(&a.vertices * 0.9).unwrap()], 0).unwrap(),
            target: Tensor::cat(&[&a.target, &a.source], 0).unwrap(),
        }
    }

    fn run(&self, model: &GagAvatar, noise: Noise) -> TrainOutput {
        model
            .train_forward(
                &self.image,
                &self.source,
                &self.vertices,
                &self.target,
                noise,
            )
            .unwrap()
    }
}

/// Seeded values in [-1, 1) shaped like `like`.
fn random_like(like: &Tensor, seed: u64) -> Tensor {
    let mut rng = Rng::new(seed);
    let v: Vec<f64> = (0..like.elem_count())
        .map(|_| rng.range(-1.0, 1.0))
        .collect();
    Tensor::from_vec(v, like.dims(), &Device::Cpu)
        .unwrap()
        .to_dtype(like.dtype())
        .unwrap()
}

/// Fixed random weightings of fine, coarse and the lifted points: a loss whose gradient
/// reaches every output value (an L1 to an image would do the same, with kinks).
struct Loss {
    fine: Tensor,
    coarse: Tensor,
    points: Tensor,
}

impl Loss {
    fn new(out: &TrainOutput) -> Self {
        Self {
            fine: random_like(&out.fine, 1),
            coarse: random_like(&out.coarse, 2),
            points: random_like(&out.avatar.lifted_xyz, 3),
        }
    }

    fn eval(&self, out: &TrainOutput) -> Tensor {
        let term = |t: &Tensor, w: &Tensor| {
            (t * w)
                .unwrap()
                .sum_all()
                .unwrap()
                .affine(1.0 / t.elem_count() as f64, 0.0)
                .unwrap()
        };
        let l = (term(&out.fine, &self.fine) + term(&out.coarse, &self.coarse)).unwrap();
        (l + term(&out.avatar.lifted_xyz, &self.points)).unwrap()
    }
}

fn vars(map: &VarMap) -> BTreeMap<String, Var> {
    map.data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect()
}

/// Sum of |gradient| of `var` (0 when it has none).
fn grad_norm(grads: &GradStore, var: &Var) -> f64 {
    grads
        .get(var.as_tensor())
        .map_or(0.0, |g| to_vec_f64(&g.abs().unwrap().sum_all().unwrap())[0])
}

/// Keys of the VarMap whose gradient is absent or zero; panics on a non-finite one.
fn without_gradient(map: &VarMap, grads: &GradStore) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    for (k, v) in vars(map) {
        let n = grad_norm(grads, &v);
        assert!(n.is_finite(), "{k}: gradient sum {n}");
        if n == 0.0 {
            out.insert(k);
        }
    }
    out
}

/// Keys that are in the checkpoint but that no forward computation reads (spec 4 and 8).
fn never_used(key: &str) -> bool {
    // Masked-image modelling token (pretraining only); `refinenet.0` has no skip input, so its
    // first residual unit never runs; the U-Net's `toRGB.k` feed an output the release
    // commented out.
    key == "base_model.dino_model.mask_token"
        || key.starts_with("base_model.refinenet.0.resConfUnit1.")
        || key.starts_with("upsampler.toRGB.")
}

/// Bit-identical values (same shape), failing with the first differing index.
fn assert_same(what: &str, actual: &Tensor, expected: &Tensor) {
    assert_eq!(actual.dims(), expected.dims(), "{what}: shape");
    let (a, e) = (to_vec_f64(actual), to_vec_f64(expected));
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != e[i].to_bits()) {
        panic!("{what}: flat index {i}: expected {}, actual {}", e[i], a[i]);
    }
}

fn with(cfg: &ModelConfig, edit: impl FnOnce(&mut ModelConfig)) -> ModelConfig {
    let mut c = cfg.clone();
    edit(&mut c);
    c
}

#[test]
fn presets_freeze_only_the_pretrained_backbone() {
    let release = ModelConfig::release();
    assert!(release.backbone_frozen());
    assert!(!ModelConfig::tiny().backbone_frozen());
    assert!(!ModelConfig::small().backbone_frozen());
    assert!(with(&ModelConfig::tiny(), |c| c.freeze_backbone = Some(true)).backbone_frozen());
    assert!(!with(&release, |c| c.freeze_backbone = Some(false)).backbone_frozen());
    // The release's trained set, from its key list alone (no weights built).
    let keys = expected_keys(&release).unwrap();
    let trained: Vec<&String> = keys
        .keys()
        .filter(|k| is_trainable_key(&release, k))
        .collect();
    let count =
        |ks: &[&String]| -> usize { ks.iter().map(|k| keys[*k].iter().product::<usize>()).sum() };
    assert!(trained.iter().all(|k| !k.starts_with(BACKBONE_PREFIX)));
    assert!(trained.iter().all(|k| !k.starts_with(NOISE_BUFFER_PREFIX)));
    let dino: Vec<&String> = keys
        .keys()
        .filter(|k| k.starts_with(BACKBONE_PREFIX))
        .collect();
    eprintln!(
        "release: {} trained tensors ({} values); backbone {} tensors ({} values)",
        trained.len(),
        count(&trained),
        dino.len(),
        count(&dino)
    );
    assert_eq!(
        trained.len() + dino.len() + 15,
        keys.len(),
        "every release key is trained, backbone or one of the 15 noise buffers"
    );
    assert!(!is_trainable_key(
        &release,
        "percep_loss.alex.lin0.model.1.weight"
    ));
}

/// Every parameter of the tiny model is a variable, and a loss on fine + coarse + lifted points
/// reaches all of them except the exact set of keys the forward never reads.
#[test]
fn every_trained_parameter_gets_a_gradient() {
    let cfg = ModelConfig::tiny();
    let (model, map) = trainable_model(&cfg, Some(tiny_weights()), 0, &Device::Cpu).unwrap();
    assert!(model.dino.is_trainable());
    let keys = expected_keys(&cfg).unwrap();
    let want: BTreeSet<String> = keys
        .keys()
        .filter(|k| !k.starts_with(NOISE_BUFFER_PREFIX))
        .cloned()
        .collect();
    let have: BTreeSet<String> = vars(&map).into_keys().collect();
    assert_eq!(
        have, want,
        "the VarMap holds every key but the noise buffers"
    );

    let scene = Scene::pair(DType::F32);
    let out = scene.run(&model, Noise::Seeded(7));
    assert_eq!(out.fine.dims(), &[2, 3, 64, 64]);
    assert_eq!(out.coarse.dims(), &[2, 32, 64, 64]);
    assert_eq!(out.avatar.lifted_xyz.dims(), &[2, 2 * 40 * 40, 3]);
    let loss = Loss::new(&out).eval(&out);
    let grads = loss.backward().unwrap();
    let none = without_gradient(&map, &grads);
    let expected: BTreeSet<String> = have.iter().filter(|k| never_used(k)).cloned().collect();
    eprintln!("no gradient: {none:?}");
    assert_eq!(none, expected, "parameters without a gradient");
}

/// The release's rule on tiny sizes: the backbone is fixed (not in the VarMap, fused kernels,
/// outside the graph), everything else trains, and updating every variable leaves the backbone
/// bit-identical.
#[test]
fn a_frozen_backbone_is_outside_the_varmap_and_the_graph() {
    let cfg = with(&ModelConfig::tiny(), |c| c.freeze_backbone = Some(true));
    let init = tiny_weights();
    let (model, map) = trainable_model(&cfg, Some(init.clone()), 0, &Device::Cpu).unwrap();
    assert!(!model.dino.is_trainable());
    let have: BTreeSet<String> = vars(&map).into_keys().collect();
    let want: BTreeSet<String> = expected_keys(&cfg)
        .unwrap()
        .into_keys()
        .filter(|k| !k.starts_with(BACKBONE_PREFIX) && !k.starts_with(NOISE_BUFFER_PREFIX))
        .collect();
    assert_eq!(have, want);

    let scene = Scene::pair(DType::F32);
    let (_, trace) = model
        .reconstruct_traced(&scene.image, &scene.source)
        .unwrap();
    for (k, t) in trace.dino.iter().enumerate() {
        assert!(
            !t.track_op(),
            "DINO output {k} is in the graph: gradients could reach the backbone"
        );
    }
    assert!(trace.f_local.track_op(), "the DPT head must train");
    let out = scene.run(&model, Noise::Seeded(7));
    let grads = Loss::new(&out).eval(&out).backward().unwrap();
    let none = without_gradient(&map, &grads);
    let expected: BTreeSet<String> = have.iter().filter(|k| never_used(k)).cloned().collect();
    assert_eq!(none, expected, "parameters without a gradient");

    // An optimiser-like step on every variable.
    for (k, v) in vars(&map) {
        let step = match grads.get(v.as_tensor()) {
            Some(g) => (g * 1e-2).unwrap(),
            None => v.as_tensor().ones_like().unwrap(),
        };
        v.set(&(v.as_tensor() - step).unwrap())
            .unwrap_or_else(|e| panic!("{k}: {e}"));
    }
    let (_, after) = model
        .reconstruct_traced(&scene.image, &scene.source)
        .unwrap();
    for k in 0..4 {
        assert_same(
            &format!("dino_{k} after the step"),
            &after.dino[k],
            &trace.dino[k],
        );
    }
    let exported = export_weights(&model, &map).unwrap();
    let mut n = 0;
    for (k, t) in &exported {
        if k.starts_with(BACKBONE_PREFIX) {
            assert_same(k, t, &init[k]);
            n += 1;
        }
    }
    let backbone = expected_keys(&cfg)
        .unwrap()
        .into_keys()
        .filter(|k| k.starts_with(BACKBONE_PREFIX))
        .count();
    assert_eq!(n, backbone, "every backbone tensor is exported");
}

/// Autograd against central finite differences of the whole training loss (reconstruct, splat,
/// render) in f64, on the scalar with the largest gradient in a weight of every module.
#[test]
fn gradients_match_finite_differences() {
    let cfg = ModelConfig::tiny();
    let (model, map) =
        trainable_model_as(&cfg, Some(tiny_weights()), 0, DType::F64, &Device::Cpu).unwrap();
    let scene = Scene::golden(DType::F64);
    let noise = Noise::Seeded(3);
    let out = scene.run(&model, noise);
    let loss_fn = Loss::new(&out);
    let grads = loss_fn.eval(&out).backward().unwrap();
    let eval = || -> f64 { to_vec_f64(&loss_fn.eval(&scene.run(&model, noise)))[0] };
    let vars = vars(&map);
    let d = "base_model.dino_model.";
    let names = [
        // ViT in train mode: attention, MLP, layer norms, layer scale, embeddings.
        format!("{d}patch_embed.proj.weight"),
        format!("{d}pos_embed"),
        format!("{d}cls_token"),
        format!("{d}blocks.0.norm1.weight"),
        format!("{d}blocks.1.attn.qkv.weight"),
        format!("{d}blocks.2.attn.proj.bias"),
        format!("{d}blocks.1.ls1.gamma"),
        format!("{d}blocks.3.mlp.fc1.weight"),
        format!("{d}blocks.2.mlp.fc2.weight"),
        format!("{d}norm.bias"),
        // DPT head.
        "base_model.projects.1.weight".into(),
        "base_model.resize_layers.0.weight".into(),
        "base_model.resize_layers.3.weight".into(),
        "base_model.layer_rn.2.weight".into(),
        "base_model.refinenet.2.resConfUnit1.conv2.weight".into(),
        "base_model.output_conv.bias".into(),
        // Generators.
        "head_base".into(),
        "gs_generator_g.feature_layers.0.weight".into(),
        "gs_generator_g.rotation_layers.2.weight".into(),
        "gs_generator_g.opacity_layers.2.bias".into(),
        "gs_generator_l0.gaussian_conv.0.weight".into(),
        "gs_generator_l0.gaussian_conv.6.bias".into(),
        "gs_generator_l1.gaussian_conv.6.weight".into(),
        // StyleUNet.
        "upsampler.conv_body_first.weight".into(),
        "upsampler.conv_body_down.2.conv2.weight".into(),
        "upsampler.final_linear.weight".into(),
        "upsampler.conv_body_up.1.skip.weight".into(),
        "upsampler.condition_scale.0.2.weight".into(),
        "upsampler.stylegan_decoder.style_mlp.1.weight".into(),
        "upsampler.stylegan_decoder.constant_input.weight".into(),
        "upsampler.stylegan_decoder.style_convs.1.modulated_conv.weight".into(),
        "upsampler.stylegan_decoder.style_convs.2.weight".into(),
        "upsampler.stylegan_decoder.to_rgbs.0.bias".into(),
    ];
    let mut worst = (String::new(), 0f64);
    for name in &names {
        let var = vars
            .get(name)
            .unwrap_or_else(|| panic!("{name} not in the VarMap"));
        let g = to_vec_f64(
            grads
                .get(var.as_tensor())
                .unwrap_or_else(|| panic!("{name}: none")),
        );
        let (i, &analytic) = g
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
            .unwrap();
        let orig = var.as_tensor().detach().copy().unwrap();
        let flat = to_vec_f64(&orig);
        let at = |delta: f64| -> f64 {
            let mut v = flat.clone();
            v[i] += delta;
            var.set(&Tensor::from_vec(v, orig.dims(), &Device::Cpu).unwrap())
                .unwrap();
            eval()
        };
        let numeric = (at(FD_STEP) - at(-FD_STEP)) / (2.0 * FD_STEP);
        var.set(&orig).unwrap();
        let rel = (analytic - numeric).abs() / analytic.abs().max(1e-12);
        eprintln!("{name}[{i}]: autograd {analytic:.9e}, numeric {numeric:.9e}, rel {rel:.2e}");
        if rel > worst.1 {
            worst = (format!("{name}[{i}]"), rel);
        }
        assert!(
            rel < FD_REL_TOL,
            "{name} index {i}: autograd {analytic:e}, finite difference {numeric:e} (rel {rel:.2e})"
        );
    }
    eprintln!("worst relative error: {} {:.2e}", worst.0, worst.1);
}

/// The trainable path (variables, differentiable ops) computes what the inference path
/// computes, and both match the PyTorch reference goldens.
#[test]
fn trainable_path_equals_inference_path_and_the_reference() {
    let cfg = ModelConfig::tiny();
    let io = load("tiny_io.safetensors");
    let inference = build_model(&cfg, tiny_weights(), &Device::Cpu).unwrap();
    let (train, _map) = trainable_model(&cfg, Some(tiny_weights()), 0, &Device::Cpu).unwrap();
    assert!(!inference.dino.is_trainable() && train.dino.is_trainable());
    let scene = Scene::golden(DType::F32);
    let (a_inf, t_inf) = inference
        .reconstruct_traced(&scene.image, &scene.source)
        .unwrap();
    let (a_tr, t_tr) = train
        .reconstruct_traced(&scene.image, &scene.source)
        .unwrap();
    for k in 0..4 {
        let what = format!("dino_{k}");
        assert_close(
            &format!("{what} train vs inference"),
            &t_tr.dino[k],
            &t_inf.dino[k],
            PATH_FEATURE_TOL,
        );
        assert_close(
            &format!("{what} train vs reference"),
            &t_tr.dino[k],
            &io[&what],
            FEATURE_TOL,
        );
    }
    assert_close(
        "f_local train vs inference",
        &t_tr.f_local,
        &t_inf.f_local,
        PATH_FEATURE_TOL,
    );
    assert_close(
        "f_local train vs reference",
        &t_tr.f_local,
        &io["f_local"],
        FEATURE_TOL,
    );
    for (what, a, b) in [
        ("lifted_xyz", &a_tr.lifted_xyz, &a_inf.lifted_xyz),
        ("colors", &a_tr.colors, &a_inf.colors),
        ("opacities", &a_tr.opacities, &a_inf.opacities),
        ("scales", &a_tr.scales, &a_inf.scales),
        ("rotations", &a_tr.rotations, &a_inf.rotations),
    ] {
        assert_close(
            &format!("{what} train vs inference"),
            a,
            b,
            PATH_FEATURE_TOL,
        );
    }
    let out = scene.run(&train, Noise::Fixed);
    let frame = inference
        .drive(&a_inf, &scene.vertices, &scene.target, Noise::Fixed)
        .unwrap();
    assert_close(
        "coarse train vs inference",
        &out.coarse,
        &frame.coarse,
        PATH_IMAGE_TOL,
    );
    assert_close(
        "fine train vs inference",
        &out.fine,
        &frame.fine,
        PATH_IMAGE_TOL,
    );
    assert_close(
        "coarse train vs reference",
        &out.coarse,
        &io["coarse"],
        IMAGE_TOL,
    );
    assert_close("fine train vs reference", &out.fine, &io["fine"], IMAGE_TOL);
}

/// No module keeps a stale copy: after `Var::set` of every variable to another model's
/// weights, the forward is bit-identical to that model built directly.
#[test]
fn var_updates_reach_the_next_forward() {
    let cfg = ModelConfig::tiny();
    let (model, map) = trainable_model(&cfg, None, 1, &Device::Cpu).unwrap();
    let (other, other_map) = trainable_model(&cfg, None, 2, &Device::Cpu).unwrap();
    let scene = Scene::golden(DType::F32);
    let noise = Noise::Seeded(11);
    let before = scene.run(&model, noise);
    let target = scene.run(&other, noise);
    let d = to_vec_f64(&(&before.fine - &target.fine).unwrap().abs().unwrap())
        .into_iter()
        .fold(0.0, gagavatar_testkit::max_or_nan);
    assert!(
        d > 1e-3,
        "the two seeds give nearly the same image ({d:.2e})"
    );
    let others = vars(&other_map);
    for (k, v) in vars(&map) {
        v.set(others[&k].as_tensor()).unwrap();
    }
    let after = scene.run(&model, noise);
    assert_same(
        "lifted_xyz after set",
        &after.avatar.lifted_xyz,
        &target.avatar.lifted_xyz,
    );
    assert_same("coarse after set", &after.coarse, &target.coarse);
    assert_same("fine after set", &after.fine, &target.fine);
    // One weight at a time: a change in the ViT's first linear layer reaches the image.
    let k = "base_model.dino_model.blocks.0.attn.qkv.weight";
    let v = &vars(&map)[k];
    v.set(&(v.as_tensor() * 1.5).unwrap()).unwrap();
    let changed = scene.run(&model, noise);
    let d = to_vec_f64(&(&changed.fine - &after.fine).unwrap().abs().unwrap())
        .into_iter()
        .fold(0.0, gagavatar_testkit::max_or_nan);
    assert!(d > 1e-6, "scaling {k} changed the image by only {d:.2e}");
}

#[test]
fn seeded_noise_is_reproducible_per_sample() {
    let cfg = ModelConfig::tiny();
    let (model, _map) = trainable_model(&cfg, None, 4, &Device::Cpu).unwrap();
    let pair = Scene::pair(DType::F32);
    let one = Scene::golden(DType::F32);
    let a = pair.run(&model, Noise::Seeded(5));
    let b = pair.run(&model, Noise::Seeded(5));
    assert_same("same seed", &a.fine, &b.fine);
    let c = pair.run(&model, Noise::Seeded(6));
    let d = to_vec_f64(&(&a.fine - &c.fine).unwrap().abs().unwrap())
        .into_iter()
        .fold(0.0, gagavatar_testkit::max_or_nan);
    assert!(d > 1e-4, "another seed changes the image by only {d:.2e}");
    // Sample 0 draws the same noise alone or in a batch.
    let single = one.run(&model, Noise::Seeded(5));
    assert_close(
        "sample 0 alone vs in a batch",
        &single.fine,
        &a.fine.narrow(0, 0, 1).unwrap(),
        1e-6,
    );
}

/// Each ablation keeps the key set and changes the output exactly as documented.
#[test]
fn ablations_change_the_output_as_documented() {
    let base = ModelConfig::tiny();
    let keys = expected_keys(&base).unwrap();
    let scene = Scene::golden(DType::F32);
    let noise = Noise::Seeded(9);
    let (full, _) = trainable_model(&base, Some(tiny_weights()), 0, &Device::Cpu).unwrap();
    let reference = scene.run(&full, noise);
    let v = base.n_vertices;
    let s2 = base.plane_size() * base.plane_size();

    // One plane: the l0 half of everything, no l1 Gaussians, l1 untrained.
    let cfg = with(&base, |c| c.one_plane = true);
    assert_eq!(expected_keys(&cfg).unwrap(), keys);
    assert_eq!(cfg.n_gaussians(), v + s2);
    let (model, map) = trainable_model(&cfg, Some(tiny_weights()), 0, &Device::Cpu).unwrap();
    let out = scene.run(&model, noise);
    assert_eq!(out.avatar.lifted_xyz.dims(), &[1, s2, 3]);
    assert_same(
        "one plane: lifted = l0",
        &out.avatar.lifted_xyz,
        &reference.avatar.lifted_xyz.narrow(1, 0, s2).unwrap(),
    );
    assert_same(
        "one plane: colours = expression + l0",
        &out.avatar.colors,
        &reference.avatar.colors.narrow(1, 0, v + s2).unwrap(),
    );
    let grads = Loss::new(&out).eval(&out).backward().unwrap();
    let none = without_gradient(&map, &grads);
    let expected: BTreeSet<String> = vars(&map)
        .into_keys()
        .filter(|k| never_used(k) || k.starts_with("gs_generator_l1."))
        .collect();
    assert_eq!(none, expected, "one plane: parameters without a gradient");

    // Without F_id: the expression Gaussians come from zeros in F_id's place; the lifted ones
    // are unchanged.
    let cfg = with(&base, |c| c.no_fid_in_expression = true);
    assert_eq!(expected_keys(&cfg).unwrap(), keys);
    let (model, _) = trainable_model(&cfg, Some(tiny_weights()), 0, &Device::Cpu).unwrap();
    let (avatar, trace) = model
        .reconstruct_traced(&scene.image, &scene.source)
        .unwrap();
    let zeros = trace.f_id.zeros_like().unwrap();
    let expr = model
        .gen_g
        .forward(&model.head_base, &zeros, &trace.dir_encoding)
        .unwrap();
    assert_same(
        "no F_id: expression colours",
        &avatar.colors.narrow(1, 0, v).unwrap(),
        &expr.colors,
    );
    assert_same(
        "no F_id: lifted colours unchanged",
        &avatar.colors.narrow(1, v, 2 * s2).unwrap(),
        &reference.avatar.colors.narrow(1, v, 2 * s2).unwrap(),
    );
    let d = to_vec_f64(
        &(avatar.colors.narrow(1, 0, v).unwrap()
            - reference.avatar.colors.narrow(1, 0, v).unwrap())
        .unwrap()
        .abs()
        .unwrap(),
    )
    .into_iter()
    .fold(0.0, gagavatar_testkit::max_or_nan);
    assert!(
        d > 1e-4,
        "F_id changes the expression colours by only {d:.2e}"
    );

    // Without the neural renderer: fine is the coarse RGB; the renderer gets no gradient.
    let cfg = with(&base, |c| c.no_neural_renderer = true);
    assert_eq!(expected_keys(&cfg).unwrap(), keys);
    let (model, map) = trainable_model(&cfg, Some(tiny_weights()), 0, &Device::Cpu).unwrap();
    let out = scene.run(&model, noise);
    assert_same(
        "no renderer: coarse unchanged",
        &out.coarse,
        &reference.coarse,
    );
    assert_same(
        "no renderer: fine = coarse RGB",
        &out.fine,
        &out.coarse.narrow(1, 0, 3).unwrap(),
    );
    let grads = Loss::new(&out).eval(&out).backward().unwrap();
    let none = without_gradient(&map, &grads);
    let expected: BTreeSet<String> = vars(&map)
        .into_keys()
        .filter(|k| never_used(k) || k.starts_with("upsampler."))
        .collect();
    assert_eq!(none, expected, "no renderer: parameters without a gradient");
}

/// Configurations stored before the ablation and freezing options existed still parse, with
/// every option off.
#[test]
fn old_configurations_parse_with_the_options_off() {
    let cfg = ModelConfig::tiny();
    let mut json: serde_json::Value = serde_json::to_value(&cfg).unwrap();
    let obj = json.as_object_mut().unwrap();
    for k in [
        "one_plane",
        "no_fid_in_expression",
        "no_neural_renderer",
        "freeze_backbone",
    ] {
        obj.remove(k);
    }
    let back: ModelConfig = serde_json::from_value(json).unwrap();
    assert_eq!(back, cfg);
    let on = with(&cfg, |c| {
        c.one_plane = true;
        c.freeze_backbone = Some(true);
    });
    let back: ModelConfig = serde_json::from_str(&serde_json::to_string(&on).unwrap()).unwrap();
    assert_eq!(back, on);
}

/// A trained model exports in the release key layout, loads back through `load_model` (with
/// its configuration) and computes the same images.
#[test]
fn exported_weights_load_back() {
    let dir = std::env::temp_dir().join(format!("gagavatar-net-train-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = Scene::golden(DType::F32);
    for freeze in [false, true] {
        let cfg = with(&ModelConfig::tiny(), |c| {
            c.freeze_backbone = Some(freeze);
            c.one_plane = freeze;
        });
        let (model, map) = trainable_model(&cfg, None, 8, &Device::Cpu).unwrap();
        // Move every variable so the export cannot pass by reading the initial weights.
        for (_, v) in vars(&map) {
            let t = (v.as_tensor() * 0.97).unwrap();
            v.set(&t).unwrap();
        }
        let exported = export_weights(&model, &map).unwrap();
        let keys = expected_keys(&cfg).unwrap();
        assert_eq!(
            exported.keys().collect::<Vec<_>>(),
            keys.keys().collect::<Vec<_>>()
        );
        let path = dir.join(format!("trained-{freeze}.safetensors"));
        write_tensors(&path, &exported, Some(&cfg)).unwrap();
        let loaded = load_model(&path, None, &Device::Cpu).unwrap();
        assert_eq!(loaded.cfg, cfg);
        let out = scene.run(&model, Noise::Fixed);
        let avatar = loaded.reconstruct(&scene.image, &scene.source).unwrap();
        let frame = loaded
            .drive(&avatar, &scene.vertices, &scene.target, Noise::Fixed)
            .unwrap();
        assert_close(
            &format!("freeze {freeze}: coarse"),
            &frame.coarse,
            &out.coarse,
            PATH_IMAGE_TOL,
        );
        assert_close(
            &format!("freeze {freeze}: fine"),
            &frame.fine,
            &out.fine,
            PATH_IMAGE_TOL,
        );
        // Untrained keys (noise buffers; the backbone when frozen) are exported as initialised.
        let init = init_weights(&cfg, 8).unwrap();
        for (k, t) in &exported {
            if !is_trainable_key(&cfg, k) {
                let (shape, v) = &init[k];
                let want = Tensor::from_vec(v.clone(), shape.as_slice(), &Device::Cpu).unwrap();
                assert_same(k, t, &want);
            }
        }
        std::fs::remove_file(&path).unwrap();
    }
    let _ = std::fs::remove_dir(&dir);
}

#[test]
fn mismatched_batches_are_errors() {
    let cfg = ModelConfig::tiny();
    let (model, _) = trainable_model(&cfg, None, 0, &Device::Cpu).unwrap();
    let one = Scene::golden(DType::F32);
    let pair = Scene::pair(DType::F32);
    let r = model.train_forward(
        &one.image,
        &one.source,
        &pair.vertices,
        &pair.target,
        Noise::Fixed,
    );
    assert!(r.is_err(), "one source for two targets accepted");
    let mut bad = tiny_weights();
    bad.remove("head_base");
    match trainable_model(&cfg, Some(bad), 0, &Device::Cpu) {
        Ok(_) => panic!("weights without head_base accepted"),
        Err(e) => assert!(e.to_string().contains("head_base"), "{e}"),
    }
}
