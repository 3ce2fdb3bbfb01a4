//! `resample::resize` by sparse taps: the taps are exactly the dense interpolation matrices,
//! the forward matches the dense matrix products, the backward matches f64 central finite
//! differences and the dense version's (matmul) backward.

use candle_core::{DType, Device, Tensor, Var};
use gagavatar_ops::resample::{interp_matrix, resize, resize_dense, ResizeMode, Taps};

/// f64: the dense product adds the same few non-zero terms (plus exact zeros), possibly in
/// another order when antialias gives more than two taps.
const F64_TOL: f64 = 1e-14;
/// f32: a few roundings of terms whose weights sum to 1, relative to the largest |input|.
const F32_TOL: f64 = 1e-6;
/// Backward vs central differences in f64; resize is linear, so only rounding of the loss.
const FD_TOL: f64 = 1e-9;
const FD_STEP: f64 = 1e-3;

const MODES: [ResizeMode; 3] = [
    ResizeMode::HalfPixel,
    ResizeMode::AlignCorners,
    ResizeMode::Antialias,
];

fn tensor(shape: &[usize], seed: u64) -> Tensor {
    let n: usize = shape.iter().product();
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let v: Vec<f64> = (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        })
        .collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

fn flat(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn check(what: &str, actual: &[f64], expected: &[f64], scale: f64, tol: f64) {
    assert_eq!(actual.len(), expected.len(), "{what}: length");
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        let err = (a - e).abs() / scale;
        assert!(
            err <= tol,
            "{what}: index {i}: expected {e}, actual {a}, error {err:e} > {tol:e}"
        );
    }
}

#[test]
fn taps_are_the_dense_matrix_exactly() {
    for mode in MODES {
        for input in [1, 2, 3, 5, 7, 16, 37, 64, 518] {
            for output in [1, 2, 3, 5, 8, 19, 40, 128, 296] {
                let dense = interp_matrix(input, output, mode);
                let t = Taps::new(input, output, mode);
                let mut m = vec![0.0f64; output * input];
                for o in 0..output {
                    assert!(
                        t.start[o] + t.n <= input,
                        "{mode:?} {input}->{output}: window of {o} leaves the input"
                    );
                    for k in 0..t.n {
                        m[o * input + t.start[o] + k] = t.w[o * t.n + k];
                    }
                }
                for (i, (a, e)) in m.iter().zip(&dense).enumerate() {
                    assert!(
                        a.to_bits() == e.to_bits(),
                        "{mode:?} {input}->{output}: index {i} (row {}, col {}): expected {e}, taps give {a}",
                        i / input,
                        i % input
                    );
                }
            }
        }
    }
}

/// (input shape, output h, output w)
const CASES: &[(&[usize], usize, usize)] = &[
    (&[2, 3, 17, 13], 34, 26),
    (&[2, 3, 17, 13], 8, 6),
    (&[1, 4, 17, 13], 17, 40),
    (&[1, 4, 17, 13], 5, 13),
    (&[1, 1, 1, 1], 3, 3),
    (&[3, 9, 7], 4, 14),
    (&[12, 10], 37, 3),
    (&[1, 2, 64, 64], 19, 19),
    (&[1, 2, 70, 70], 518, 518),
];

#[test]
fn forward_matches_dense_products() {
    for (ci, &(shape, oh, ow)) in CASES.iter().enumerate() {
        let x = tensor(shape, ci as u64 + 1);
        for mode in MODES {
            let expected = flat(&resize_dense(&x, oh, ow, mode).unwrap());
            for (dtype, tol) in [(DType::F64, F64_TOL), (DType::F32, F32_TOL)] {
                let y = resize(&x.to_dtype(dtype).unwrap(), oh, ow, mode).unwrap();
                let mut want = shape.to_vec();
                let n = want.len();
                want[n - 2] = oh;
                want[n - 1] = ow;
                assert_eq!(
                    y.dims(),
                    &want[..],
                    "{shape:?} -> {oh}x{ow} {mode:?}: shape"
                );
                check(
                    &format!("{shape:?} -> {oh}x{ow} {mode:?} {dtype:?}"),
                    &flat(&y),
                    &expected,
                    1.0,
                    tol,
                );
            }
        }
    }
}

#[test]
fn non_contiguous_input() {
    let x = tensor(&[1, 3, 13, 17], 5).transpose(2, 3).unwrap();
    for mode in MODES {
        let expected = flat(&resize_dense(&x.contiguous().unwrap(), 30, 7, mode).unwrap());
        let y = resize(&x, 30, 7, mode).unwrap();
        check(
            &format!("transposed {mode:?}"),
            &flat(&y),
            &expected,
            1.0,
            F64_TOL,
        );
    }
}

#[test]
fn backward_matches_finite_differences_and_dense_backward() {
    for (ci, &(shape, oh, ow)) in CASES.iter().enumerate().take(7) {
        let x = tensor(shape, 100 + ci as u64);
        for mode in MODES {
            let probe = resize(&x, oh, ow, mode).unwrap();
            let r = tensor(probe.dims(), 200 + ci as u64);
            let loss = |t: &Tensor| {
                (resize(t, oh, ow, mode).unwrap() * &r)
                    .unwrap()
                    .sum_all()
                    .unwrap()
            };
            let xv = Var::from_tensor(&x).unwrap();
            let g = flat(
                loss(xv.as_tensor())
                    .backward()
                    .unwrap()
                    .get(xv.as_tensor())
                    .unwrap(),
            );
            let vals = flat(&x);
            for i in 0..vals.len() {
                let mut p = vals.clone();
                p[i] += FD_STEP;
                let lp = loss(&Tensor::from_vec(p.clone(), shape, &Device::Cpu).unwrap())
                    .to_scalar::<f64>()
                    .unwrap();
                p[i] -= 2.0 * FD_STEP;
                let lm = loss(&Tensor::from_vec(p, shape, &Device::Cpu).unwrap())
                    .to_scalar::<f64>()
                    .unwrap();
                let e = (lp - lm) / (2.0 * FD_STEP);
                let err = (g[i] - e).abs() / e.abs().max(1.0);
                assert!(err <= FD_TOL, "{shape:?} -> {oh}x{ow} {mode:?}: index {i}: finite difference {e}, backward {}, error {err:e}", g[i]);
            }
            // f32 backward vs the dense version's matmul backward.
            let x32 = Var::from_tensor(&x.to_dtype(DType::F32).unwrap()).unwrap();
            let r32 = r.to_dtype(DType::F32).unwrap();
            let ours = (resize(x32.as_tensor(), oh, ow, mode).unwrap() * &r32)
                .unwrap()
                .sum_all()
                .unwrap();
            let dense = (resize_dense(x32.as_tensor(), oh, ow, mode).unwrap() * &r32)
                .unwrap()
                .sum_all()
                .unwrap();
            let go = flat(ours.backward().unwrap().get(x32.as_tensor()).unwrap());
            let gd = flat(dense.backward().unwrap().get(x32.as_tensor()).unwrap());
            // Each gradient entry sums at most ~out/in * taps terms of |r| <= 1.
            let scale = (oh as f64 / shape[shape.len() - 2] as f64).max(1.0)
                * (ow as f64 / shape[shape.len() - 1] as f64).max(1.0);
            check(
                &format!("{shape:?} -> {oh}x{ow} {mode:?} f32 backward"),
                &go,
                &gd,
                scale,
                F32_TOL,
            );
        }
    }
}

#[test]
fn bad_input_is_an_error() {
    let x = tensor(&[2, 3, 4, 4], 1);
    let bad = [
        ("1-D", resize(&tensor(&[5], 2), 3, 3, ResizeMode::HalfPixel)),
        ("zero height", resize(&x, 0, 3, ResizeMode::HalfPixel)),
        ("zero width", resize(&x, 3, 0, ResizeMode::AlignCorners)),
        (
            "integer dtype",
            resize(
                &x.to_dtype(DType::U32).unwrap(),
                3,
                3,
                ResizeMode::Antialias,
            ),
        ),
    ];
    for (what, r) in bad {
        match r {
            Err(e) => println!("{what}: {e}"),
            Ok(t) => panic!("{what}: expected an error, got shape {:?}", t.dims()),
        }
    }
}
