//! `train --device gpu`'s split step against the CPU step: the same state, batch and noise,
//! every loss term and every trained parameter's gradient.

use std::collections::HashMap;
use std::sync::Arc;

use candle_core::{DType, Device};
use gagavatar_train::bench::synthetic_batch;
use gagavatar_train::perceptual::{seeded_weights, PerceptualLoss, PERCEP_PREFIX};
use gagavatar_train::{RenderHalf, TrainConfig, TrainState};

use super::render_half::GpuRenderHalf;
use crate::device::{AdapterPolicy, Gpu};
use crate::testutil::{assert_close_rel, gpu};
use crate::Tuning;

/// Every gradient relative to its array's largest: the render step's bound
/// (`render_step`'s `STEP_RTOL`, the pieces chained), carried through the reconstruction's
/// backward, which is the same candle graph on both sides.
const SPLIT_RTOL: f64 = 1e-4;

/// The backbone's outputs on the GPU against the CPU's, relative to each output's largest.
const BACKBONE_RTOL: f64 = 1e-5;

/// Gradients with the backbone on the GPU: its outputs differ from the CPU's in the last bits,
/// so the Gaussians do too, and splatting is discontinuous (a Gaussian whose alpha at a pixel
/// lies within rounding of 1/255 is drawn on one side only); gradients that are sums over
/// every pixel (a noise weight's, a style convolution's) move most: measured worst 2.3e-3 on
/// lavapipe, against 5.6e-6 with the backbone's outputs bit-identical.
const BACKBONE_STEP_RTOL: f64 = 5e-3;

/// Gradients with the lifting generators on the GPU: the lifted Gaussians differ from the
/// CPU's in the last bits (the same convolutions summed in another order), with the same
/// effect on splatting as [`BACKBONE_STEP_RTOL`]'s.
const LIFT_STEP_RTOL: f64 = 5e-3;

/// Gradients with the backbone, the DPT head and the lifting generators on the GPU: as
/// [`BACKBONE_STEP_RTOL`] and [`LIFT_STEP_RTOL`], the last bits of `F_local` moving the lifted
/// Gaussians too.
const DPT_STEP_RTOL: f64 = 5e-3;

/// The loss terms: sums of the same f32 values in another order.
const TERM_RTOL: f64 = 1e-5;

/// A CPU state and a state whose rendering half is on the GPU, with the perceptual term (on
/// the GPU with `gpu_percep`, else on the CPU from the GPU's crops) or without.
fn states(percep: bool, gpu_percep: bool) -> Option<(TrainState, TrainState)> {
    states_with(percep, gpu_percep, false, false, false)
}

/// [`states`]; `backbone`: the tiny model's backbone frozen (as the release's is) and run on
/// the GPU; `lifting`: the lifting generators on the GPU; `dpt`: the DPT head too (with both).
fn states_with(
    percep: bool,
    gpu_percep: bool,
    backbone: bool,
    lifting: bool,
    dpt: bool,
) -> Option<(TrainState, TrainState)> {
    gpu()?;
    let mut cfg = TrainConfig::preset("tiny").unwrap();
    if backbone {
        cfg.model.freeze_backbone = Some(true);
    }
    let p = || {
        percep.then(|| {
            let w: HashMap<String, _> = seeded_weights(5)
                .unwrap()
                .into_iter()
                .map(|(k, v)| (format!("{PERCEP_PREFIX}{k}"), v))
                .collect();
            PerceptualLoss::from_tensors(&w, DType::F32, &Device::Cpu)
                .unwrap()
                .unwrap()
        })
    };
    let cpu = TrainState::new(cfg.clone(), None, p(), &Device::Cpu).unwrap();
    let mut split = TrainState::new(cfg.clone(), None, p(), &Device::Cpu).unwrap();
    // Its own device: the render half holds it for the run.
    let g = Arc::new(Gpu::new(AdapterPolicy::AllowCpu).unwrap());
    let pw = split.percep_weights().unwrap().filter(|_| gpu_percep);
    let rh = GpuRenderHalf::new(
        g,
        &Tuning::default(),
        &cfg.model,
        &split.renderer_weights().unwrap(),
        cfg.losses().box_size,
        pw.as_ref().map(|(w, f)| (w, *f)),
    )
    .unwrap();
    let rh = if backbone {
        rh.with_backbone(&split.model).unwrap()
    } else {
        rh
    };
    let rh = if lifting {
        rh.with_lifting(&cfg.model, &split.lifting_weights().unwrap())
            .unwrap()
    } else {
        rh
    };
    let rh = if dpt {
        rh.with_dpt(&cfg.model, &split.dpt_weights().unwrap())
            .unwrap()
    } else {
        rh
    };
    split.set_render_half(Box::new(rh)).unwrap();
    Some((cpu, split))
}

fn check_terms(step: usize, want: f64, got: f64, what: &str) {
    let d = (want - got).abs();
    assert!(
        d <= TERM_RTOL * want.abs(),
        "step {step}: {what}: expected {want}, got {got} (difference {d:e})"
    );
}

/// Batch 2 with every term on (the perceptual term on the GPU, the lifting term on the CPU):
/// the terms and every trained parameter's gradient.
#[test]
fn split_step_gradients_match_the_cpu_step() {
    compare_gradients(true);
}

/// As [`split_step_gradients_match_the_cpu_step`] with the perceptual term computed on the
/// CPU from the crops the GPU returns, its gradients sent back.
#[test]
fn split_step_with_a_cpu_perceptual_term_matches_the_cpu_step() {
    compare_gradients(false);
}

/// A frozen backbone run on the GPU, its outputs constants of the CPU graph: the terms and
/// every trained parameter's gradient (the backbone has none).
#[test]
fn split_step_with_the_backbone_on_the_gpu_matches_the_cpu_step() {
    let Some((cpu, split)) = states_with(false, false, true, false, false) else {
        return;
    };
    // The backbone's outputs themselves: the same f32 operations in other orders.
    let cfg = &cpu.cfg.model;
    let s = cfg.image_size;
    let batch = synthetic_batch(&cpu.cfg, 1, &Device::Cpu).unwrap();
    let (_, trace) = cpu
        .model
        .reconstruct_traced(&batch.source_image, &batch.source_transform)
        .unwrap();
    let g = Arc::new(Gpu::new(AdapterPolicy::AllowCpu).unwrap());
    let rh = GpuRenderHalf::new(
        g,
        &Tuning::default(),
        cfg,
        &cpu.renderer_weights().unwrap(),
        s,
        None,
    )
    .unwrap();
    let mut rh = rh.with_backbone(&cpu.model).unwrap();
    let flat =
        |t: &candle_core::Tensor| -> Vec<f32> { t.flatten_all().unwrap().to_vec1().unwrap() };
    let got = rh
        .backbone(&flat(&batch.source_image), &flat(&batch.source_transform))
        .unwrap();
    for (k, (want, got)) in trace.dino.iter().zip(&got).enumerate() {
        assert_close_rel(
            &format!("backbone output {k}"),
            &flat(want),
            got,
            BACKBONE_RTOL,
        );
    }
    compare_states_within(cpu, split, BACKBONE_STEP_RTOL);
}

/// The lifting generators on the GPU too (forward and backward, their lifted Gaussians and the
/// gradient of `F_local` crossing to the CPU), with every term on.
#[test]
fn split_step_with_the_lifting_generators_on_the_gpu_matches_the_cpu_step() {
    let Some((cpu, split)) = states_with(true, true, false, true, false) else {
        return;
    };
    compare_states_within(cpu, split, LIFT_STEP_RTOL);
}

/// The frozen backbone, the DPT head and the lifting generators on the GPU (`F_local` and its
/// gradient never cross to the CPU; the DPT head's weight gradients do), every term on.
#[test]
fn split_step_with_the_dpt_head_on_the_gpu_matches_the_cpu_step() {
    let Some((cpu, split)) = states_with(true, true, true, true, true) else {
        return;
    };
    compare_states_within(cpu, split, DPT_STEP_RTOL);
}

fn compare_gradients(gpu_percep: bool) {
    let Some((cpu, split)) = states(true, gpu_percep) else {
        return;
    };
    compare_states_within(cpu, split, SPLIT_RTOL);
}

fn compare_states_within(mut cpu: TrainState, mut split: TrainState, rtol: f64) {
    let batch = synthetic_batch(&cpu.cfg, 2, &Device::Cpu).unwrap();
    let (want, wg) = cpu.forward_backward(&batch).unwrap();
    let (got, gg) = split.forward_backward(&batch).unwrap();
    eprintln!("CPU {want:?}\nGPU {got:?}");
    check_terms(0, want.img, got.img, "img");
    check_terms(0, want.box_l1, got.box_l1, "box");
    if let (Some(w), Some(g)) = (want.percep, got.percep) {
        check_terms(0, w, g, "percep");
    }
    assert_eq!(want.percep.is_some(), got.percep.is_some());
    check_terms(0, want.point.unwrap(), got.point.unwrap(), "point");
    check_terms(0, want.loss, got.loss, "loss");
    let (wg, gg) = (wg.unwrap(), gg.unwrap());
    let cpu_vars: HashMap<String, _> = cpu.vars().unwrap().into_iter().collect();
    let mut compared = 0;
    for (name, v) in split.vars().unwrap() {
        let flat =
            |t: &candle_core::Tensor| -> Vec<f32> { t.flatten_all().unwrap().to_vec1().unwrap() };
        match (wg.get(cpu_vars[&name].as_tensor()), gg.get(v.as_tensor())) {
            (Some(w), Some(g)) => {
                assert_close_rel(&format!("d {name}"), &flat(w), &flat(g), rtol);
                compared += 1;
            }
            (None, None) => {}
            (w, g) => panic!(
                "{name}: a gradient on one side only (CPU {}, GPU {})",
                w.is_some(),
                g.is_some()
            ),
        }
    }
    assert!(compared > 200, "only {compared} parameters compared");
}

/// A few optimisation steps (batch 2, the release's Adam): the losses follow the CPU run's.
/// Adam normalises each gradient, so values whose gradient is rounding noise can move by up to
/// a learning rate either way; the losses stay close.
#[test]
fn split_steps_follow_the_cpu_run() {
    let Some((mut cpu, mut split)) = states(false, false) else {
        return;
    };
    let batch = synthetic_batch(&cpu.cfg, 2, &Device::Cpu).unwrap();
    for step in 0..4 {
        let want = cpu.train_step(&batch).unwrap();
        let got = split.train_step(&batch).unwrap();
        eprintln!("step {step}: CPU {}, GPU {}", want.loss, got.loss);
        assert!(want.skipped.is_none() && got.skipped.is_none());
        let d = (want.loss - got.loss).abs();
        assert!(
            d <= 1e-3 * want.loss,
            "step {step}: loss expected {}, got {} (difference {d:e})",
            want.loss,
            got.loss
        );
    }
}
