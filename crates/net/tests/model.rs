//! Whole-model parity with the PyTorch reference (`tools/reference/net_reference.py`) on the
//! `tiny` preset, key layout against the release's state dict, and bad inputs.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use gagavatar_net::checkpoint::{check_keys, expected_keys, init_weights};
use gagavatar_net::model::GagAvatar;
use gagavatar_net::style_unet::Noise;
use gagavatar_net::{ModelConfig, NetError};

mod common;
use common::{assert_close as compare, load};

/// Features and Gaussian attributes: f32 network vs the f64 reference through a few dozen
/// layers of O(1) activations; the bar is 1e-4.
const FEATURE_TOL: f64 = 1e-4;
/// Images after splatting / the renderer: 1e-3 (the bar), allowing f32 accumulation
/// over thousands of Gaussians per pixel and the renderer's depth.
const IMAGE_TOL: f64 = 1e-3;

fn tiny_model() -> (GagAvatar, HashMap<String, Tensor>) {
    let w = load("tiny_weights.safetensors");
    let cfg = ModelConfig::tiny();
    check_keys(&cfg, &w).expect("golden weights have exactly the tiny keys");
    let vb = VarBuilder::from_tensors(w, DType::F32, &Device::Cpu);
    (
        GagAvatar::new(&cfg, vb).unwrap(),
        load("tiny_io.safetensors"),
    )
}

#[test]
fn tiny_model_matches_the_reference_stage_by_stage() {
    let (model, io) = tiny_model();
    let (avatar, trace) = model
        .reconstruct_traced(&io["source_image"], &io["source_transform"])
        .unwrap();
    compare("input_518", &trace.input_518, &io["input_518"], FEATURE_TOL);
    for k in 0..4 {
        compare(
            &format!("dino_{k}"),
            &trace.dino[k],
            &io[&format!("dino_{k}")],
            FEATURE_TOL,
        );
    }
    compare("f_id", &trace.f_id, &io["f_id"], FEATURE_TOL);
    compare("f_local", &trace.f_local, &io["f_local"], FEATURE_TOL);
    compare(
        "plane_points",
        &trace.plane_points,
        &io["plane_points"],
        FEATURE_TOL,
    );
    compare("plane_dir", &trace.plane_dir, &io["plane_dir"], FEATURE_TOL);
    compare(
        "dir_encoding",
        &trace.dir_encoding,
        &io["dir_encoding"],
        FEATURE_TOL,
    );
    let verts = &io["target_points"];
    compare(
        "gs_xyz",
        &avatar.positions(verts).unwrap(),
        &io["gs_xyz"],
        FEATURE_TOL,
    );
    compare("gs_colors", &avatar.colors, &io["gs_colors"], FEATURE_TOL);
    compare(
        "gs_opacities",
        &avatar.opacities,
        &io["gs_opacities"],
        FEATURE_TOL,
    );
    compare("gs_scales", &avatar.scales, &io["gs_scales"], FEATURE_TOL);
    compare(
        "gs_rotations",
        &avatar.rotations,
        &io["gs_rotations"],
        FEATURE_TOL,
    );
    let frame = model
        .drive(&avatar, verts, &io["target_transform"], Noise::Fixed)
        .unwrap();
    compare("coarse", &frame.coarse, &io["coarse"], IMAGE_TOL);
    compare("fine", &frame.fine, &io["fine"], IMAGE_TOL);
    // The renderer alone on the reference's coarse image isolates it from splatting.
    let fine = model.render(&io["coarse"], Noise::Fixed).unwrap();
    compare("fine (reference coarse)", &fine, &io["fine"], IMAGE_TOL);
}

#[test]
fn release_keys_are_the_checkpoint_keys() {
    let tsv = include_str!("data/official_state_dict.tsv");
    let mut official: Vec<(String, Vec<usize>)> = Vec::new();
    for line in tsv.lines().filter(|l| !l.trim().is_empty()) {
        let mut cols = line.split('\t');
        let (Some(name), Some(shape)) = (cols.next(), cols.next()) else {
            panic!("bad tsv line {line:?}");
        };
        if name.starts_with("percep_loss.") {
            continue;
        }
        let dims = shape
            .trim_matches(|c| c == '(' || c == ')')
            .split(',')
            .filter(|s| !s.trim().is_empty())
            .map(|s| s.trim().parse::<usize>().unwrap())
            .collect();
        official.push((name.to_string(), dims));
    }
    let ours = expected_keys(&ModelConfig::release()).unwrap();
    for (k, s) in &official {
        assert_eq!(
            ours.get(k),
            Some(s),
            "release key {k}: ours {:?}, checkpoint {s:?}",
            ours.get(k)
        );
    }
    assert_eq!(
        ours.len(),
        official.len(),
        "we ask for keys the checkpoint lacks"
    );
}

#[test]
fn missing_extra_and_misshapen_keys_are_listed_in_one_error() {
    let cfg = ModelConfig::tiny();
    let w = init_weights(&cfg, 3).unwrap();
    let mut map: HashMap<String, Tensor> = w
        .into_iter()
        .map(|(k, (s, v))| (k, Tensor::from_vec(v, s, &Device::Cpu).unwrap()))
        .collect();
    check_keys(&cfg, &map).unwrap();
    map.remove("head_base");
    map.insert(
        "bogus.weight".into(),
        Tensor::zeros(2, DType::F32, &Device::Cpu).unwrap(),
    );
    map.insert(
        "upsampler.final_linear.bias".into(),
        Tensor::zeros(7, DType::F32, &Device::Cpu).unwrap(),
    );
    map.insert(
        "percep_loss.vggface.x".into(),
        Tensor::zeros(1, DType::F32, &Device::Cpu).unwrap(),
    );
    let err = check_keys(&cfg, &map).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, NetError::Keys { .. }), "{msg}");
    for part in [
        "1 missing: head_base",
        "1 unexpected: bogus.weight",
        "upsampler.final_linear.bias (expected [32], found [7])",
    ] {
        assert!(msg.contains(part), "`{part}` not in: {msg}");
    }
    assert!(!msg.contains("percep_loss"), "{msg}");
}

#[test]
fn bad_inputs_are_errors() {
    let cfg = ModelConfig::tiny();
    let vb = VarBuilder::zeros(DType::F32, &Device::Cpu);
    let model = GagAvatar::new(&cfg, vb).unwrap();
    let dev = Device::Cpu;
    let img = Tensor::zeros((1, 3, 64, 64), DType::F32, &dev).unwrap();
    let tm = Tensor::new(
        &[[[1f32, 0., 0., 0.], [0., 1., 0., 0.], [0., 0., 1., 9.]]],
        &dev,
    )
    .unwrap();
    // wrong image size, wrong transform shape, NaN
    assert!(model
        .reconstruct(
            &Tensor::zeros((1, 3, 60, 64), DType::F32, &dev).unwrap(),
            &tm
        )
        .is_err());
    assert!(model
        .reconstruct(&img, &Tensor::zeros((1, 4, 4), DType::F32, &dev).unwrap())
        .is_err());
    let nan = (img.clone() * f64::NAN).unwrap();
    let e = model.reconstruct(&nan, &tm).unwrap_err();
    assert!(e.to_string().contains("NaN"), "{e}");
    let avatar = model.reconstruct(&img, &tm).unwrap();
    let verts = Tensor::zeros((1, 5023, 3), DType::F32, &dev).unwrap();
    assert!(model
        .drive(
            &avatar,
            &Tensor::zeros((1, 100, 3), DType::F32, &dev).unwrap(),
            &tm,
            Noise::Fixed
        )
        .is_err());
    let tm2 = Tensor::cat(&[&tm, &tm], 0).unwrap();
    assert!(
        model.drive(&avatar, &verts, &tm2, Noise::Fixed).is_err(),
        "batch mismatch"
    );
    let f = model.drive(&avatar, &verts, &tm, Noise::Fixed).unwrap();
    assert_eq!(f.fine.dims(), &[1, 3, 64, 64]);
}

#[test]
fn one_avatar_drives_a_batch_like_single_calls() {
    let (model, io) = tiny_model();
    let avatar = model
        .reconstruct(&io["source_image"], &io["source_transform"])
        .unwrap();
    let v = &io["target_points"];
    let t = &io["target_transform"];
    let v2 = Tensor::cat(&[v, &(v * 0.9).unwrap()], 0).unwrap();
    let t2 = Tensor::cat(&[t, &io["source_transform"]], 0).unwrap();
    let both = model.drive(&avatar, &v2, &t2, Noise::Fixed).unwrap();
    let a = model
        .drive(
            &avatar,
            &v2.narrow(0, 1, 1).unwrap(),
            &t2.narrow(0, 1, 1).unwrap(),
            Noise::Fixed,
        )
        .unwrap();
    compare(
        "batched fine[1]",
        &both.fine.narrow(0, 1, 1).unwrap(),
        &a.fine,
        1e-5,
    );
    compare(
        "batched coarse[1]",
        &both.coarse.narrow(0, 1, 1).unwrap(),
        &a.coarse,
        1e-6,
    );
}
