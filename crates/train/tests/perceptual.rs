//! The perceptual networks and distance against the reference (seeded weights shared with
//! tools/reference/train_reference.py), the input gradient against finite differences, the
//! max-pool op, and weight loading.

mod common;

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use common::*;
use gagavatar_train::perceptual::{
    layer_distance, layer_distance_portable, maxpool2d, maxpool2d_portable, relu, seeded_weights,
    PerceptualLoss, PERCEP_PREFIX,
};

/// The seed the reference uses.
const SEED: u64 = 7;
/// f32 network against the f64 reference: features (relative to the largest value).
const TOL_FEAT_F32: f64 = 1e-5;
/// f32 loss terms (relative).
const TOL_TERMS_F32: f64 = 1e-5;
/// f32 input gradient (relative to the largest entry).
const TOL_GRAD_F32: f64 = 1e-4;
/// Our f64 network against the f64 reference: only summation order differs.
const TOL_F64: f64 = 1e-10;
/// f64 backward against central differences of step 1e-6 (kinks of ReLU/max-pool are the only
/// error source besides rounding ~1e-10).
const TOL_FD: f64 = 1e-6;

fn net(dtype: DType) -> PerceptualLoss {
    let w = seeded_weights(SEED).unwrap();
    PerceptualLoss::new(VarBuilder::from_tensors(w, dtype, &Device::Cpu)).unwrap()
}

#[test]
fn seeded_weights_match_the_reference_stream() {
    let probe = load("seeded_weights_probe.safetensors");
    let w = seeded_weights(SEED).unwrap();
    assert_eq!(w.len(), 36, "10 AlexNet + 26 VGG tensors");
    for (k, want) in &probe {
        let got = w[k]
            .flatten_all()
            .unwrap()
            .narrow(0, 0, want.dims()[0])
            .unwrap();
        let (g, e): (Vec<f32>, Vec<f32>) = (got.to_vec1().unwrap(), want.to_vec1().unwrap());
        for (i, (a, b)) in g.iter().zip(&e).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "{k}[{i}]: expected {b}, got {a}");
        }
    }
}

#[test]
fn golden_features_terms_and_gradient_f32() {
    let io = load("perceptual.safetensors");
    let p = net(DType::F32);
    let (x, y) = (get(&io, "x"), get(&io, "y"));
    let f = p.features(x).unwrap();
    for l in 0..5 {
        let got = f.alex[l].narrow(0, 0, 1).unwrap().squeeze(0).unwrap();
        assert_close_to_max(
            &format!("alex {l}"),
            &got,
            get(&io, &format!("alex_{l}")),
            TOL_FEAT_F32,
        );
    }
    for l in [3, 4] {
        let got = f.vgg[l].narrow(0, 0, 1).unwrap().squeeze(0).unwrap();
        assert_close_to_max(
            &format!("vgg {l}"),
            &got,
            get(&io, &format!("vgg_{l}")),
            TOL_FEAT_F32,
        );
    }
    let xv = Var::from_tensor(x).unwrap();
    let terms = PerceptualLoss::layer_terms(
        &p.features(xv.as_tensor()).unwrap(),
        &p.features(y).unwrap(),
    )
    .unwrap();
    let got: Vec<f64> = terms.iter().map(scalar).collect();
    assert_close_slices(
        "layer terms",
        &got,
        &to_f64(get(&io, "terms")),
        TOL_TERMS_F32,
    );
    let loss = p.loss(xv.as_tensor(), y).unwrap();
    assert_close_slices(
        "loss",
        &[scalar(&loss)],
        &[scalar(get(&io, "loss"))],
        TOL_TERMS_F32,
    );
    let g = loss.backward().unwrap();
    assert_close_to_max(
        "input gradient",
        g.get(xv.as_tensor()).unwrap(),
        get(&io, "grad_x"),
        TOL_GRAD_F32,
    );
}

#[test]
fn golden_f64() {
    let io = load("perceptual.safetensors");
    let p = net(DType::F64);
    let x = Var::from_tensor(&get(&io, "x").to_dtype(DType::F64).unwrap()).unwrap();
    let y = get(&io, "y").to_dtype(DType::F64).unwrap();
    let terms = PerceptualLoss::layer_terms(
        &p.features(x.as_tensor()).unwrap(),
        &p.features(&y).unwrap(),
    )
    .unwrap();
    let got: Vec<f64> = terms.iter().map(scalar).collect();
    assert_close_slices("f64 layer terms", &got, &to_f64(get(&io, "terms")), TOL_F64);
    let loss = p.loss(x.as_tensor(), &y).unwrap();
    let g = loss.backward().unwrap();
    // The fixture stores the gradient in f32.
    assert_close_to_max(
        "f64 input gradient",
        g.get(x.as_tensor()).unwrap(),
        &get(&io, "grad_x").to_dtype(DType::F64).unwrap(),
        1e-6,
    );
}

#[test]
fn input_gradient_matches_finite_differences() {
    let p = net(DType::F64);
    let mut rng = Rng::from_state(11);
    let dims = (1usize, 3usize, 32usize, 32usize);
    let n = dims.0 * dims.1 * dims.2 * dims.3;
    let xv: Vec<f64> = (0..n).map(|_| rng.uniform()).collect();
    let yv: Vec<f64> = (0..n).map(|_| rng.uniform()).collect();
    let y = Tensor::from_vec(yv, dims, &Device::Cpu).unwrap();
    let eval = |v: &[f64]| -> f64 {
        let t = Tensor::from_vec(v.to_vec(), dims, &Device::Cpu).unwrap();
        scalar(&p.loss(&t, &y).unwrap())
    };
    let x = Var::from_tensor(&Tensor::from_vec(xv.clone(), dims, &Device::Cpu).unwrap()).unwrap();
    let grad = to_f64(
        p.loss(x.as_tensor(), &y)
            .unwrap()
            .backward()
            .unwrap()
            .get(x.as_tensor())
            .unwrap(),
    );
    let scale = grad.iter().fold(0f64, |a, v| a.max(v.abs()));
    assert!(scale > 0.0);
    let h = 1e-6;
    for k in 0..24 {
        let i = if k < 4 {
            [0, 31, 32 * 32 + 500, n - 1][k]
        } else {
            // Modulo, as these indices were always drawn (the same inputs as before).
            (rng.next_u64() % n as u64) as usize
        };
        let (mut a, mut b) = (xv.clone(), xv.clone());
        a[i] += h;
        b[i] -= h;
        let fd = (eval(&a) - eval(&b)) / (2.0 * h);
        assert!(
            (fd - grad[i]).abs() <= TOL_FD * scale,
            "input {i}: finite difference {fd}, backward {} (max |grad| {scale})",
            grad[i]
        );
    }
}

#[test]
fn maxpool_matches_the_composite_path_and_torch_ties() {
    let mut rng = Rng::from_state(5);
    let dev = Device::Cpu;
    for (k, s, h, w) in [
        (3usize, 2usize, 15usize, 13usize),
        (2, 2, 12, 9),
        (3, 2, 7, 7),
    ] {
        let v: Vec<f64> = (0..2 * 3 * h * w).map(|_| rng.normal()).collect();
        let x = Var::from_tensor(&Tensor::from_vec(v, (2, 3, h, w), &dev).unwrap()).unwrap();
        let ours = maxpool2d(x.as_tensor(), k, s).unwrap();
        // Reference: every window's maximum by brute force.
        let (oh, ow) = ((h - k) / s + 1, (w - k) / s + 1);
        assert_eq!(ours.dims(), &[2, 3, oh, ow]);
        let xs = to_f64(x.as_tensor());
        let got = to_f64(&ours);
        for p in 0..6 {
            for i in 0..oh {
                for j in 0..ow {
                    let mut m = f64::NEG_INFINITY;
                    for dy in 0..k {
                        for dx in 0..k {
                            m = m.max(xs[p * h * w + (i * s + dy) * w + j * s + dx]);
                        }
                    }
                    assert_eq!(
                        got[p * oh * ow + i * ow + j],
                        m,
                        "k{k} s{s} plane {p} ({i}, {j})"
                    );
                }
            }
        }
        // Gradient of a weighted sum: each output's weight lands on its window's maximum.
        let wts = Tensor::rand(0f64, 1.0, (2, 3, oh, ow), &dev).unwrap();
        let g = (ours * &wts)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let gx = to_f64(g.get(x.as_tensor()).unwrap());
        let wv = to_f64(&wts);
        let mut want = vec![0.0; xs.len()];
        for p in 0..6 {
            for i in 0..oh {
                for j in 0..ow {
                    let mut best = (f64::NEG_INFINITY, 0);
                    for dy in 0..k {
                        for dx in 0..k {
                            let idx = p * h * w + (i * s + dy) * w + j * s + dx;
                            if xs[idx] > best.0 {
                                best = (xs[idx], idx);
                            }
                        }
                    }
                    want[best.1] += wv[p * oh * ow + i * ow + j];
                }
            }
        }
        assert_close_slices(&format!("max-pool k{k} s{s} gradient"), &gx, &want, 1e-15);
        // The portable path (other devices) gives the same values and, without ties, gradients.
        let xp = Var::from_tensor(x.as_tensor()).unwrap();
        let port = maxpool2d_portable(xp.as_tensor(), k, s).unwrap();
        assert_eq!(to_f64(&port), got, "portable max-pool k{k} s{s}");
        let gp = (port * &wts)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert_close_slices(
            &format!("portable max-pool k{k} s{s} gradient"),
            &to_f64(gp.get(xp.as_tensor()).unwrap()),
            &want,
            1e-15,
        );
    }
    // Ties: all of a window's gradient goes to its first maximum in row-major order (PyTorch),
    // not split between the tied ones.
    let x = Var::from_tensor(&Tensor::ones((1, 1, 3, 3), DType::F32, &dev).unwrap()).unwrap();
    let g = maxpool2d(x.as_tensor(), 3, 2)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let gx: Vec<f32> = g
        .get(x.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert_eq!(gx, vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    // Too small.
    assert!(maxpool2d(
        &Tensor::zeros((1, 1, 2, 5), DType::F32, &dev).unwrap(),
        3,
        2
    )
    .is_err());
}

#[test]
fn weight_loading() {
    let dev = Device::Cpu;
    let w = seeded_weights(SEED).unwrap();
    let prefixed: HashMap<String, Tensor> = w
        .iter()
        .map(|(k, v)| (format!("{PERCEP_PREFIX}{k}"), v.clone()))
        .collect();
    // No perceptual key at all: the term is off, not an error.
    let other: HashMap<String, Tensor> = [(
        "head_base".to_string(),
        Tensor::zeros(3, DType::F32, &dev).unwrap(),
    )]
    .into();
    assert!(PerceptualLoss::from_tensors(&other, DType::F32, &dev)
        .unwrap()
        .is_none());
    // Complete, and without the two layers the loss never runs.
    assert!(PerceptualLoss::from_tensors(&prefixed, DType::F32, &dev)
        .unwrap()
        .is_some());
    let mut partial = prefixed.clone();
    for k in ["weight", "bias"] {
        partial.remove(&format!("{PERCEP_PREFIX}vggface.network.26.{k}"));
        partial.remove(&format!("{PERCEP_PREFIX}vggface.network.28.{k}"));
    }
    assert!(PerceptualLoss::from_tensors(&partial, DType::F32, &dev)
        .unwrap()
        .is_some());
    // A missing and a misshapen tensor are both named.
    let mut bad = prefixed.clone();
    bad.remove(&format!("{PERCEP_PREFIX}net.slice3.6.bias"));
    bad.insert(
        format!("{PERCEP_PREFIX}vggface.network.10.weight"),
        Tensor::zeros((256, 128, 3, 2), DType::F32, &dev).unwrap(),
    );
    let e = PerceptualLoss::from_tensors(&bad, DType::F32, &dev)
        .expect_err("must fail")
        .to_string();
    assert!(e.contains("net.slice3.6.bias` is missing"), "{e}");
    assert!(
        e.contains("vggface.network.10.weight` has shape [256, 128, 3, 2]"),
        "{e}"
    );
    // From a safetensors file, with or without the prefix; missing file is an error.
    let dir = std::env::temp_dir().join(format!("gagavatar-train-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let x = Tensor::rand(0f32, 1.0, (1, 3, 40, 40), &dev).unwrap();
    let y = Tensor::rand(0f32, 1.0, (1, 3, 40, 40), &dev).unwrap();
    let want = scalar(&net(DType::F32).loss(&x, &y).unwrap());
    for (name, map) in [
        ("prefixed.safetensors", &prefixed),
        ("bare.safetensors", &w),
    ] {
        let path = dir.join(name);
        candle_core::safetensors::save(map, &path).unwrap();
        let p = PerceptualLoss::load(&path, DType::F32, &dev).unwrap();
        assert_eq!(scalar(&p.loss(&x, &y).unwrap()), want, "{name}");
    }
    assert!(PerceptualLoss::load(&dir.join("missing.safetensors"), DType::F32, &dev).is_err());
    std::fs::remove_dir_all(&dir).ok();
    // Inputs too small for AlexNet, or mismatched pairs.
    let p = net(DType::F32);
    let small = Tensor::zeros((1, 3, 30, 30), DType::F32, &dev).unwrap();
    assert!(p.features(&small).is_err());
    assert!(p
        .loss(
            &x,
            &Tensor::zeros((1, 3, 40, 41), DType::F32, &dev).unwrap()
        )
        .is_err());
}

#[test]
fn identical_images_have_zero_distance() {
    let p = net(DType::F32);
    let x = Tensor::rand(0f32, 1.0, (2, 3, 40, 40), &Device::Cpu).unwrap();
    assert_eq!(scalar(&p.loss(&x, &x).unwrap()), 0.0);
}

/// The fused kernels against the same formulas in candle ops: f64, both inputs tracked, two
/// groups of predictions against one target batch.
#[test]
fn fused_kernels_match_candle_ops() {
    let dev = Device::Cpu;
    let mut rng = Rng::from_state(21);
    let mut rand = |d: (usize, usize, usize, usize)| -> Tensor {
        let n = d.0 * d.1 * d.2 * d.3;
        // ReLU-like features: about a third exactly zero, including a fully dead position.
        let v: Vec<f64> = (0..n)
            .map(|_| rng.normal().max(-0.4) + 0.4)
            .map(|x| if x < 0.3 { 0.0 } else { x })
            .collect();
        Tensor::from_vec(v, d, &dev).unwrap()
    };
    let a0 = rand((4, 7, 5, 19));
    let mut bv = to_f64(&rand((2, 7, 5, 19)));
    for c in 0..7 {
        bv[c * 95 + 3] = 0.0; // position 3 of target image 0: all channels zero
    }
    let b0 = Tensor::from_vec(bv, (2, 7, 5, 19), &dev).unwrap();
    let (a1, b1) = (
        Var::from_tensor(&a0).unwrap(),
        Var::from_tensor(&b0).unwrap(),
    );
    let (a2, b2) = (
        Var::from_tensor(&a0).unwrap(),
        Var::from_tensor(&b0).unwrap(),
    );
    let w = Tensor::new(0.37f64, &dev).unwrap();
    let fused = layer_distance(a1.as_tensor(), b1.as_tensor()).unwrap();
    let port = layer_distance_portable(a2.as_tensor(), b2.as_tensor()).unwrap();
    assert_close_slices("distance", &[scalar(&fused)], &[scalar(&port)], 1e-13);
    let gf = fused.mul(&w).unwrap().backward().unwrap();
    let gp = port.mul(&w).unwrap().backward().unwrap();
    assert_close_to_max(
        "distance d/da",
        gf.get(a1.as_tensor()).unwrap(),
        gp.get(a2.as_tensor()).unwrap(),
        1e-12,
    );
    assert_close_to_max(
        "distance d/db",
        gf.get(b1.as_tensor()).unwrap(),
        gp.get(b2.as_tensor()).unwrap(),
        1e-12,
    );
    // Mismatched groups are an error.
    assert!(layer_distance(&rand((3, 7, 5, 19)), &b0).is_err());
    // ReLU: same values; gradient zero where the input is <= 0 (PyTorch's rule at 0).
    let x = Var::from_tensor(&Tensor::new(&[-1.0f64, 0.0, 2.0, -0.0, 3.5], &dev).unwrap()).unwrap();
    let y = relu(x.as_tensor()).unwrap();
    assert_eq!(to_f64(&y), vec![0.0, 0.0, 2.0, 0.0, 3.5]);
    let g = y
        .mul(&Tensor::new(&[1.0f64, 2.0, 3.0, 4.0, 5.0], &dev).unwrap())
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    assert_eq!(
        to_f64(g.get(x.as_tensor()).unwrap()),
        vec![0.0, 0.0, 3.0, 0.0, 5.0]
    );
}
