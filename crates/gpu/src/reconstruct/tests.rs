//! `reconstruct` on the GPU against the CPU path (`GagAvatar::reconstruct_traced`).

use candle_core::{DType, Device, Tensor};
use gagavatar_net::model::GagAvatar;
use gagavatar_net::ModelConfig;
use gagavatar_splat::testscene::Rng;
use gagavatar_splat::Camera;

use super::GpuReconstruct;
use crate::testutil::{max_diff, seeded_model, shared_gpu};
use crate::tuning::Tuning;

/// The ViT's outputs and F_local: sums of a few hundred f32 products per layer through 4-12
/// blocks, in another order than the CPU's (the bound).
const FEATURE_TOL: f64 = 1e-4;
/// Each Gaussian attribute, relative to the attribute's largest magnitude (the bound).
const GAUSSIAN_REL_TOL: f64 = 1e-4;

fn flat(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn photo(cfg: &ModelConfig, seed: u64) -> (Tensor, Tensor) {
    let size = cfg.image_size;
    let mut rng = Rng::new(seed);
    // A smooth image with texture: random values would make every DPT level mostly noise.
    let img: Vec<f32> = (0..3 * size * size)
        .map(|i| {
            let (c, y, x) = (i / (size * size), (i / size) % size, i % size);
            let v = 0.5
                + 0.3 * ((x as f64 * 0.2 + c as f64).sin() * (y as f64 * 0.15).cos())
                + 0.1 * rng.uniform();
            v as f32
        })
        .collect();
    let img = Tensor::from_vec(img, (1, 3, size, size), &Device::Cpu).unwrap();
    let tm = Camera::look_at_origin_matrix(9.0, std::f64::consts::PI + 0.2, -0.1);
    let v: Vec<f32> = tm.iter().flatten().map(|&x| x as f32).collect();
    (img, Tensor::from_vec(v, (1, 3, 4), &Device::Cpu).unwrap())
}

/// `[1, G, C]` tokens as the GPU's channel-major `[C, G]`.
fn channel_major(t: &Tensor) -> Vec<f32> {
    flat(&t.squeeze(0).unwrap().t().unwrap().contiguous().unwrap())
}

/// The bounds of one comparison: features (absolute) and Gaussians (relative).
#[derive(Clone, Copy)]
struct Tols {
    features: f64,
    gaussians: f64,
}

const F32_TOLS: Tols = Tols {
    features: FEATURE_TOL,
    gaussians: GAUSSIAN_REL_TOL,
};

/// f16 inputs on the tensor cores (f32 sums): each product rounds both factors to 11 bits,
/// through 12 ViT blocks and DPT; bounds for a sanity check, the measured figures are printed.
const MMA_TOLS: Tols = Tols {
    features: 0.1,
    gaussians: 0.05,
};

fn check_features(what: &str, want: &[f32], got: &[f32], tol: f64) {
    let (d, i, w, g) = max_diff(want, got);
    let mean = want
        .iter()
        .zip(got)
        .map(|(a, b)| (*a as f64 - *b as f64).abs())
        .sum::<f64>()
        / want.len().max(1) as f64;
    eprintln!("{what}: max abs difference {d:e}, mean {mean:e} (tolerance {tol:e})");
    assert!(
        d <= tol,
        "{what}: max abs difference {d:e} > {tol:e} at index {i}: expected {w}, got {g}"
    );
}

fn check_relative(what: &str, want: &Tensor, got: &Tensor, tol: f64) {
    assert_eq!(want.dims(), got.dims(), "{what}: shapes");
    let (want, got) = (flat(want), flat(got));
    let scale = want
        .iter()
        .fold(0f64, |m, v| m.max(v.abs() as f64))
        .max(1e-30);
    let (d, i, w, g) = max_diff(&want, &got);
    eprintln!(
        "{what}: max abs difference {d:e}, {:e} of the largest value {scale:e} (tolerance \
         {tol:e})",
        d / scale
    );
    assert!(
        d <= tol * scale,
        "{what}: max abs difference {d:e} > {tol:e} x {scale:e} at index {i}: expected {w}, \
         got {g}"
    );
}

fn compare(model: &GagAvatar, tuning: &Tuning, seed: u64, label: &str, tols: Tols) {
    let Some(g) = shared_gpu() else { return };
    let cfg = &model.cfg;
    let (img, tm) = photo(cfg, seed);
    let (want, trace) = model.reconstruct_traced(&img, &tm).unwrap();
    let before = g.allocated_bytes();
    let rec = GpuReconstruct::new(g.clone(), tuning, model).unwrap();
    eprintln!(
        "{label}: GPU buffers of the pass (weights, activations, the avatar; tests running \
         beside it on the same device add theirs): {:.0} MiB",
        (g.allocated_bytes() - before) as f64 / (1 << 20) as f64
    );
    let got = rec.reconstruct(&img, &tm).unwrap();
    let outs = rec.dino.download(&g).unwrap();
    for (k, (t, o)) in trace.dino.iter().zip(&outs).enumerate() {
        let what = format!("{label}: dino output {k}");
        check_features(&what, &channel_major(t), o, tols.features);
    }
    check_features(
        &format!("{label}: F_local"),
        &flat(&trace.f_local),
        &rec.dpt.download(&g).unwrap(),
        tols.features,
    );
    for (name, w, gt) in [
        ("lifted xyz", &want.lifted_xyz, &got.lifted_xyz),
        ("colors", &want.colors, &got.colors),
        ("opacities", &want.opacities, &got.opacities),
        ("scales", &want.scales, &got.scales),
        ("rotations", &want.rotations, &got.rotations),
    ] {
        check_relative(&format!("{label}: {name}"), w, gt, tols.gaussians);
    }
}

/// The tiny model, and the two ablations that change the generators' wiring.
#[test]
fn tiny_reconstruct_matches_the_cpu() {
    for (label, one_plane, no_fid) in [
        ("tiny", false, false),
        ("tiny one_plane", true, false),
        ("tiny no_fid_in_expression", false, true),
    ] {
        let mut cfg = ModelConfig::tiny();
        cfg.one_plane = one_plane;
        cfg.no_fid_in_expression = no_fid;
        let model = seeded_model(&cfg, 7);
        compare(&model, &Tuning::default(), 3, label, F32_TOLS);
    }
}

/// Attention over more tokens than one workgroup of queries and one tile of keys, at the
/// release's head width (64): the tiny preset has 26 tokens of 16 channels per head.
#[test]
fn many_tokens_and_wide_heads_match_the_cpu() {
    let mut cfg = ModelConfig::tiny();
    cfg.dino_size = 14 * 10;
    cfg.vit_dim = 128;
    cfg.vit_heads = 2;
    let model = seeded_model(&cfg, 11);
    // LayerNorm with the default threads per token, one (a workgroup of 256 tokens, the last
    // one part full) and 256 (a token per workgroup).
    for ln in ["", "ln_slices=1", "ln_slices=256"] {
        let mut t = Tuning::default();
        t.apply(ln).unwrap();
        compare(
            &model,
            &t,
            4,
            &format!("101 tokens, heads of 64 {ln}"),
            F32_TOLS,
        );
    }
}

/// Another tiling (and split-K on every layer that allows it): the same results.
#[test]
fn tiny_reconstruct_with_other_tiles_matches_the_cpu() {
    let mut t = Tuning::default();
    t.apply("conv_split_k=16,conv_small_bm=16,conv_small_bn=16,conv_small_tm=2,conv_small_tn=2")
        .unwrap();
    let model = seeded_model(&ModelConfig::tiny(), 9);
    compare(&model, &t, 5, "tiny, other tiles", F32_TOLS);
}

/// Release size (DINOv2 ViT-B/14 at 518, 180,255 Gaussians) with seeded weights: by hand,
/// `cargo test --release -p gagavatar-gpu release_reconstruct -- --ignored --nocapture`.
#[test]
#[ignore = "release size: minutes on lavapipe"]
fn release_reconstruct_matches_the_cpu() {
    let model = seeded_model(&ModelConfig::release(), 1);
    compare(&model, &Tuning::default(), 2, "release", F32_TOLS);
}

/// The tensor-core convolutions (f16 inputs, f32 sums) where the device has them (not
/// lavapipe), tiny and release size; the measured differences are printed for the notes.
#[test]
fn mma_reconstruct_is_close_to_the_cpu() {
    if crate::testutil::mma_gpu().is_none() {
        return;
    }
    let mut t = Tuning::default();
    t.apply("mma=1").unwrap();
    for (label, cfg) in [
        ("tiny f16", ModelConfig::tiny()),
        ("release f16", ModelConfig::release()),
    ] {
        compare(&seeded_model(&cfg, 1), &t, 2, label, MMA_TOLS);
    }
}

#[test]
fn bad_inputs_are_errors() {
    let Some(g) = shared_gpu() else { return };
    let cfg = ModelConfig::tiny();
    let model = seeded_model(&cfg, 7);
    let rec = GpuReconstruct::new(g, &Tuning::default(), &model).unwrap();
    let (img, tm) = photo(&cfg, 1);
    let small = img.narrow(3, 0, 10).unwrap();
    let err = rec.run(&small, &tm).unwrap_err().to_string();
    assert!(err.contains("source image"), "{err}");
    let two = Tensor::cat(&[&img, &img], 0).unwrap();
    assert!(rec.run(&two, &tm).is_err(), "a batch of two is refused");
    let nan = (img.clone() * f64::NAN).unwrap();
    let err = rec.run(&nan, &tm).unwrap_err().to_string();
    assert!(err.contains("not finite"), "{err}");
    let bad_tm = tm.narrow(2, 0, 3).unwrap();
    let err = rec.run(&img, &bad_tm).unwrap_err().to_string();
    assert!(err.contains("transform"), "{err}");
}
