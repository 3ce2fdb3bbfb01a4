//! The combined training loss against the reference (every term and the gradients of the
//! total), and its switches and input checks.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use common::*;
use gagavatar_train::losses::{l1_loss, LossConfig, LossInputs, TrainLosses};
use gagavatar_train::perceptual::{seeded_weights, PerceptualLoss};

/// f32 terms against the f64 reference (relative above 1).
const TOL_TERM: f64 = 1e-5;
/// f32 gradients against the f64 reference, relative to the largest entry.
const TOL_GRAD: f64 = 1e-4;

struct Fixture {
    io: std::collections::HashMap<String, Tensor>,
}

impl Fixture {
    fn new() -> Self {
        Self {
            io: load("losses.safetensors"),
        }
    }
    fn t(&self, k: &str) -> &Tensor {
        get(&self.io, k)
    }
    fn box_size(&self) -> usize {
        self.t("box_size").to_vec1::<i64>().unwrap()[0] as usize
    }
}

fn percep() -> PerceptualLoss {
    PerceptualLoss::new(VarBuilder::from_tensors(
        seeded_weights(7).unwrap(),
        DType::F32,
        &Device::Cpu,
    ))
    .unwrap()
}

#[test]
fn golden_terms_and_gradients() {
    let f = Fixture::new();
    let coarse = Var::from_tensor(f.t("coarse")).unwrap();
    let fine = Var::from_tensor(f.t("fine")).unwrap();
    let lifted = Var::from_tensor(f.t("lifted")).unwrap();
    let cfg = LossConfig {
        box_size: f.box_size(),
        ..LossConfig::release()
    };
    let losses = TrainLosses::new(cfg, Some(percep()));
    assert!(losses.percep_enabled());
    let out = losses
        .compute(&LossInputs {
            coarse: coarse.as_tensor(),
            fine: fine.as_tensor(),
            gt: f.t("gt"),
            bbox: f.t("bbox"),
            lifted: lifted.as_tensor(),
            targets: f.t("targets"),
        })
        .unwrap();
    let percep = out.percep.as_ref().expect("perceptual term on");
    let point = out.point.as_ref().expect("lifting term on");
    for (name, term, key) in [
        ("img", &out.img, "img"),
        ("box", &out.box_l1, "box"),
        ("percep", percep, "percep"),
        ("point", point, "point"),
        ("total", &out.total, "total"),
    ] {
        assert_close_slices(name, &[term.value], &[scalar(f.t(key))], TOL_TERM);
        assert_eq!(
            term.value,
            scalar(&term.tensor),
            "{name}: logged value = tensor value"
        );
    }
    let g = out.total.tensor.backward().unwrap();
    assert_close_to_max(
        "d total / d coarse",
        g.get(coarse.as_tensor()).unwrap(),
        f.t("grad_coarse"),
        TOL_GRAD,
    );
    assert_close_to_max(
        "d total / d fine",
        g.get(fine.as_tensor()).unwrap(),
        f.t("grad_fine"),
        TOL_GRAD,
    );
    assert_close_to_max(
        "d total / d lifted",
        g.get(lifted.as_tensor()).unwrap(),
        f.t("grad_lifted"),
        TOL_GRAD,
    );
    // Where coarse equals gt exactly (outside the head box), the L1 subgradient is 0, and the
    // extra splatted channels get no gradient at all.
    let gc = g.get(coarse.as_tensor()).unwrap();
    let patch = gc
        .narrow(0, 0, 1)
        .unwrap()
        .narrow(1, 0, 3)
        .unwrap()
        .narrow(2, 0, 4)
        .unwrap()
        .narrow(3, 0, 4)
        .unwrap();
    assert!(
        to_f64(&patch).iter().all(|v| *v == 0.0),
        "matching pixels must get no gradient"
    );
    let extra = gc.narrow(1, 3, 1).unwrap();
    assert!(to_f64(&extra).iter().all(|v| *v == 0.0));
    assert_eq!(out.boxes.len(), 2);
}

#[test]
fn switches() {
    let f = Fixture::new();
    let inputs = LossInputs {
        coarse: f.t("coarse"),
        fine: f.t("fine"),
        gt: f.t("gt"),
        bbox: f.t("bbox"),
        lifted: f.t("lifted"),
        targets: f.t("targets"),
    };
    let cfg = LossConfig {
        box_size: f.box_size(),
        lifting: false,
        ..LossConfig::release()
    };
    let out = TrainLosses::new(cfg, None).compute(&inputs).unwrap();
    assert!(out.percep.is_none() && out.point.is_none());
    let want = scalar(f.t("img")) + scalar(f.t("box"));
    assert_close_slices("img + box", &[out.total.value], &[want], TOL_TERM);
    // The lifting term alone can be switched back on; the box size is a parameter.
    let cfg = LossConfig {
        box_size: 20,
        ..LossConfig::release()
    };
    let out = TrainLosses::new(cfg, None).compute(&inputs).unwrap();
    assert_close_slices(
        "point",
        &[out.point.unwrap().value],
        &[scalar(f.t("point"))],
        TOL_TERM,
    );
    assert!(
        (out.box_l1.value - scalar(f.t("box"))).abs() > 1e-6,
        "a different crop size changes the box term"
    );
}

#[test]
fn bad_inputs_are_errors() {
    let f = Fixture::new();
    let dev = Device::Cpu;
    let good = LossInputs {
        coarse: f.t("coarse"),
        fine: f.t("fine"),
        gt: f.t("gt"),
        bbox: f.t("bbox"),
        lifted: f.t("lifted"),
        targets: f.t("targets"),
    };
    let cfg = LossConfig {
        box_size: 36,
        ..LossConfig::release()
    };
    let losses = TrainLosses::new(cfg, None);
    assert!(losses.compute(&good).is_ok());
    let two = f.t("coarse").narrow(1, 0, 2).unwrap();
    let nan_box = Tensor::new(
        &[[0.3f32, 0.2, 0.75, 0.8], [f32::NAN, 0.1, 0.5, 0.45]],
        &dev,
    )
    .unwrap();
    let small_gt = f.t("gt").narrow(3, 0, 39).unwrap();
    let no_points = Tensor::zeros((2, 0, 3), DType::F32, &dev).unwrap();
    let one_box = f.t("bbox").narrow(0, 0, 1).unwrap();
    for (inputs, what) in [
        (
            LossInputs {
                coarse: &two,
                ..good
            },
            "coarse",
        ),
        (
            LossInputs {
                bbox: &nan_box,
                ..good
            },
            "bbox[1]",
        ),
        (
            LossInputs {
                gt: &small_gt,
                ..good
            },
            "gt",
        ),
        (
            LossInputs {
                lifted: &no_points,
                ..good
            },
            "empty",
        ),
        (
            LossInputs {
                bbox: &one_box,
                ..good
            },
            "bbox",
        ),
    ] {
        let e = losses.compute(&inputs).unwrap_err().to_string();
        assert!(e.contains(what), "expected `{what}` in `{e}`");
    }
}

#[test]
fn l1_has_zero_subgradient_at_equality() {
    let dev = Device::Cpu;
    let a = Var::from_tensor(&Tensor::new(&[1.0f32, 2.0, 3.0, 4.0], &dev).unwrap()).unwrap();
    let b = Tensor::new(&[1.0f32, 1.0, 3.0, 5.0], &dev).unwrap();
    let l = l1_loss(a.as_tensor(), &b).unwrap();
    assert_eq!(scalar(&l), 0.5);
    let g: Vec<f32> = l
        .backward()
        .unwrap()
        .get(a.as_tensor())
        .unwrap()
        .to_vec1()
        .unwrap();
    assert_eq!(g, vec![0.0, 0.25, 0.0, -0.25]);
    assert!(l1_loss(a.as_tensor(), &b.narrow(0, 0, 3).unwrap()).is_err());
}
