//! `gagavatar_ops::conv2d`: forward against candle's `conv2d` (evaluated in f64) on many shapes
//! and every kernel path, backward against f64 central finite differences, bad input errors.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::*;
use gagavatar_ops::conv::{conv2d_with_algo, ConvAlgo};
use gagavatar_ops::{conv2d, Conv2dSpec};

#[test]
fn forward_matches_candle_on_all_shapes_and_paths() {
    for (ci, c) in CASES.iter().enumerate() {
        check_forward(ci, c);
    }
}

/// Sum of `y * r` for a fixed random `r`: its gradient wrt y is `r`, every entry of which
/// reaches the arguments through the convolution.
fn loss(x: &Tensor, w: &Tensor, b: &Tensor, r: &Tensor, c: &Case, algo: ConvAlgo) -> Tensor {
    let y = conv2d_with_algo(x, w, Some(b), spec(c), algo).unwrap();
    (y * r).unwrap().sum_all().unwrap()
}

/// Indices to probe: all of a small tensor, else a spread of ~`max` including both ends.
fn probe_indices(n: usize, max: usize) -> Vec<usize> {
    if n <= max {
        return (0..n).collect();
    }
    let mut v: Vec<usize> = (0..max).map(|i| i * (n - 1) / (max - 1)).collect();
    v.dedup();
    v
}

fn fd_grad(vals: &[f64], shape: &[usize], idx: usize, f: &dyn Fn(&Tensor) -> f64) -> f64 {
    let mut p = vals.to_vec();
    p[idx] += FD_STEP;
    let lp = f(&Tensor::from_vec(p.clone(), shape, &Device::Cpu).unwrap());
    p[idx] -= 2.0 * FD_STEP;
    let lm = f(&Tensor::from_vec(p, shape, &Device::Cpu).unwrap());
    (lp - lm) / (2.0 * FD_STEP)
}

#[test]
fn backward_matches_finite_differences() {
    for (ci, c) in CASES.iter().enumerate() {
        let seed = 1000 + 10 * ci as u64;
        let x = tensor(&[c.b, c.cin, c.h, c.w], seed);
        let w = tensor(&[c.cout, c.cin, c.kh, c.kw], seed + 1);
        let b = tensor(&[c.cout], seed + 2);
        let y = reference(&x, &w, &b, c);
        let r = tensor(y.dims(), seed + 3);
        for algo in algos(c) {
            let (xv, wv, bv) = (
                Var::from_tensor(&x).unwrap(),
                Var::from_tensor(&w).unwrap(),
                Var::from_tensor(&b).unwrap(),
            );
            let l = loss(xv.as_tensor(), wv.as_tensor(), bv.as_tensor(), &r, c, algo);
            let grads = l.backward().unwrap();
            let lf = |xt: &Tensor, wt: &Tensor, bt: &Tensor| {
                loss(xt, wt, bt, &r, c, algo).to_scalar::<f64>().unwrap()
            };
            let args: [(&str, &Tensor, &Var); 3] =
                [("x", &x, &xv), ("w", &w, &wv), ("bias", &b, &bv)];
            for (k, (name, t, var)) in args.into_iter().enumerate() {
                let g = flat(grads.get(var.as_tensor()).unwrap());
                let vals = flat(t);
                let mut worst = 0.0f64;
                for i in probe_indices(vals.len(), 150) {
                    let f = |p: &Tensor| match k {
                        0 => lf(p, &w, &b),
                        1 => lf(&x, p, &b),
                        _ => lf(&x, &w, p),
                    };
                    let e = fd_grad(&vals, t.dims(), i, &f);
                    let err = (g[i] - e).abs() / e.abs().max(1.0);
                    assert!(
                        err <= FD_TOL,
                        "{c:?} {algo:?} d/d{name}: index {i}: finite difference {e}, backward {}, error {err:e} > {FD_TOL:e}",
                        g[i]
                    );
                    worst = worst.max(err);
                }
                println!("{c:?} {algo:?} d/d{name}: max error {worst:.2e}");
            }
        }
    }
}

/// The f32 backward (Winograd input gradient included) against the f64 one proven above.
#[test]
fn f32_backward_matches_f64_backward() {
    for (ci, c) in CASES.iter().enumerate() {
        let seed = 2000 + 10 * ci as u64;
        let x = tensor(&[c.b, c.cin, c.h, c.w], seed);
        let w = tensor(&[c.cout, c.cin, c.kh, c.kw], seed + 1);
        let b = tensor(&[c.cout], seed + 2);
        let r = tensor(reference(&x, &w, &b, c).dims(), seed + 3);
        for algo in algos(c) {
            let grads_in = |dtype: DType| {
                let vars =
                    [&x, &w, &b].map(|t| Var::from_tensor(&t.to_dtype(dtype).unwrap()).unwrap());
                let l = loss(
                    vars[0].as_tensor(),
                    vars[1].as_tensor(),
                    vars[2].as_tensor(),
                    &r.to_dtype(dtype).unwrap(),
                    c,
                    algo,
                );
                let g = l.backward().unwrap();
                vars.map(|v| flat(g.get(v.as_tensor()).unwrap()))
            };
            let (g64, g32) = (grads_in(DType::F64), grads_in(DType::F32));
            // Scale: the same gradients computed from absolute values bound each partial sum.
            let (xa, wa, ra) = (x.abs().unwrap(), w.abs().unwrap(), r.abs().unwrap());
            let gabs = {
                let vars = [&xa, &wa, &b].map(|t| Var::from_tensor(t).unwrap());
                let l = loss(
                    vars[0].as_tensor(),
                    vars[1].as_tensor(),
                    vars[2].as_tensor(),
                    &ra,
                    c,
                    ConvAlgo::Gemm,
                );
                let g = l.backward().unwrap();
                vars.map(|v| flat(g.get(v.as_tensor()).unwrap()))
            };
            for (k, name) in ["x", "w", "bias"].iter().enumerate() {
                let tol = match (algo, k) {
                    (ConvAlgo::Gemm, _) => GEMM_F32_TOL,
                    (_, 1) => WINOGRAD_GRAD_W_F32_TOL,
                    _ => WINOGRAD_F32_TOL,
                };
                let worst = check_close(
                    &format!("{c:?} {algo:?} f32 d/d{name}"),
                    &g32[k],
                    &g64[k],
                    &gabs[k],
                    tol,
                );
                println!("{c:?} {algo:?} f32 d/d{name}: max error {worst:.2e}");
            }
        }
    }
}

#[test]
fn no_gradient_for_untracked_input() {
    let c = case(1, 3, 8, 8, 4, 3, 3, 1, 1);
    let x = tensor(&[1, 3, 8, 8], 7);
    let w = Var::from_tensor(&tensor(&[4, 3, 3, 3], 8)).unwrap();
    let y = conv2d(&x, w.as_tensor(), None, spec(&c)).unwrap();
    let g = y.sum_all().unwrap().backward().unwrap();
    assert!(g.get(&x).is_none(), "plain input got a gradient");
    assert!(g.get(w.as_tensor()).is_some(), "weight lost its gradient");
}

#[test]
fn non_contiguous_input_gives_the_same_result() {
    let c = case(1, 5, 9, 12, 4, 3, 3, 1, 1);
    let xt = tensor(&[1, 5, 12, 9], 21);
    let x = xt.transpose(2, 3).unwrap();
    assert!(!x.is_contiguous());
    let w = tensor(&[4, 5, 3, 3], 22);
    let b = tensor(&[4], 23);
    let expected = flat(&reference(&x.contiguous().unwrap(), &w, &b, &c));
    let scale = flat(&reference(
        &x.abs().unwrap().contiguous().unwrap(),
        &w.abs().unwrap(),
        &b.abs().unwrap(),
        &c,
    ));
    let y = conv2d(&x, &w, Some(&b), spec(&c)).unwrap();
    check_close("non-contiguous", &flat(&y), &expected, &scale, F64_TOL);
}

#[test]
fn bad_input_is_an_error() {
    let x = tensor(&[1, 3, 8, 8], 1);
    let w = tensor(&[4, 3, 3, 3], 2);
    let s = Conv2dSpec {
        stride: 1,
        padding: 1,
    };
    let bad: Vec<(&str, candle_core::Result<Tensor>)> = vec![
        ("3-D input", conv2d(&x.squeeze(0).unwrap(), &w, None, s)),
        ("3-D weight", conv2d(&x, &w.flatten(2, 3).unwrap(), None, s)),
        (
            "channel mismatch",
            conv2d(&x, &tensor(&[4, 2, 3, 3], 3), None, s),
        ),
        ("bias length", conv2d(&x, &w, Some(&tensor(&[5], 4)), s)),
        ("bias rank", conv2d(&x, &w, Some(&tensor(&[1, 4], 4)), s)),
        (
            "stride 0",
            conv2d(
                &x,
                &w,
                None,
                Conv2dSpec {
                    stride: 0,
                    padding: 1,
                },
            ),
        ),
        (
            "kernel larger than input",
            conv2d(
                &x,
                &tensor(&[4, 3, 11, 11], 5),
                None,
                Conv2dSpec {
                    stride: 1,
                    padding: 1,
                },
            ),
        ),
        (
            "dtype mismatch",
            conv2d(&x.to_dtype(DType::F32).unwrap(), &w, None, s),
        ),
        (
            "empty input",
            conv2d(
                &Tensor::zeros((0, 3, 8, 8), DType::F64, &Device::Cpu).unwrap(),
                &w,
                None,
                s,
            ),
        ),
        (
            "Winograd on 1x1",
            conv2d_with_algo(&x, &tensor(&[4, 3, 1, 1], 6), None, s, ConvAlgo::Winograd),
        ),
        (
            "Winograd with stride 2",
            conv2d_with_algo(
                &x,
                &w,
                None,
                Conv2dSpec {
                    stride: 2,
                    padding: 1,
                },
                ConvAlgo::Winograd,
            ),
        ),
    ];
    for (what, r) in bad {
        match r {
            Err(e) => println!("{what}: {e}"),
            Ok(t) => panic!(
                "{what}: expected an error, got a tensor of shape {:?}",
                t.dims()
            ),
        }
    }
}

/// An image gets the same kernel and summation order alone as in a batch (the automatic choice
/// and the GEMM blocking depend on the image size only), so results agree bit for bit.
#[test]
fn a_batch_equals_single_images_exactly() {
    let shapes = [
        case(3, 16, 64, 60, 24, 3, 3, 1, 1),
        case(3, 7, 21, 18, 9, 3, 3, 2, 1),
        case(2, 32, 20, 20, 8, 1, 1, 1, 0),
        case(2, 240, 9, 9, 8, 3, 3, 1, 1),
    ];
    for (ci, c) in shapes.iter().enumerate() {
        let x = tensor(&[c.b, c.cin, c.h, c.w], 500 + ci as u64)
            .to_dtype(DType::F32)
            .unwrap();
        let w = tensor(&[c.cout, c.cin, c.kh, c.kw], 600 + ci as u64)
            .to_dtype(DType::F32)
            .unwrap();
        let b = tensor(&[c.cout], 700 + ci as u64)
            .to_dtype(DType::F32)
            .unwrap();
        for algo in algos(c) {
            let all = flat(&conv2d_with_algo(&x, &w, Some(&b), spec(c), algo).unwrap());
            let per = all.len() / c.b;
            for i in 0..c.b {
                let xi = x.narrow(0, i, 1).unwrap();
                let one = flat(&conv2d_with_algo(&xi, &w, Some(&b), spec(c), algo).unwrap());
                for (j, (a, e)) in all[i * per..(i + 1) * per].iter().zip(&one).enumerate() {
                    assert!(
                        a.to_bits() == e.to_bits(),
                        "{c:?} {algo:?}: image {i} index {j}: alone {e}, in the batch {a}"
                    );
                }
            }
        }
    }
}
