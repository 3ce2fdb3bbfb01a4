//! Shared helpers of the convolution tests: deterministic data, shapes, the candle reference
//! and the error check.
#![allow(dead_code)]

use candle_core::{DType, Device, Tensor};
use gagavatar_ops::conv::{conv2d_with_algo, ConvAlgo};
use gagavatar_ops::Conv2dSpec;

/// f32 GEMM path vs an f64 reference, relative to `conv(|x|, |w|)` at the same output (the
/// scale of the partial sums): a few f32 roundings per accumulation step, far below this.
pub const GEMM_F32_TOL: f64 = 2e-6;
/// f32 Winograd F(4x4,3x3): the transforms scale values by up to ~10^2 before they cancel,
/// so the error is ~10x that of a direct sum (measured up to 3.5e-6 on these cases).
pub const WINOGRAD_F32_TOL: f64 = 2e-5;
/// f32 Winograd weight gradient, whose transforms (factors up to 8 and 1/24) cancel most in
/// tiny images that are mostly padding: 5.3e-5 for a 2x2 input, ~5e-7 at realistic sizes.
pub const WINOGRAD_GRAD_W_F32_TOL: f64 = 1e-4;
/// f64 paths: pure rounding of sums of at most a few thousand terms.
pub const F64_TOL: f64 = 1e-12;
/// Backward vs central differences in f64. The loss is linear in each argument, so the
/// difference quotient is exact up to rounding of the loss (~1e-16 |L| / step).
pub const FD_TOL: f64 = 1e-7;
pub const FD_STEP: f64 = 1e-3;

/// Deterministic uniform values in [-1, 1).
pub fn rand_vec(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(0x2545_F491_4F6C_DD1D);
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        })
        .collect()
}

pub fn tensor(shape: &[usize], seed: u64) -> Tensor {
    let n = shape.iter().product();
    Tensor::from_vec(rand_vec(n, seed), shape, &Device::Cpu).unwrap()
}

#[derive(Debug, Clone, Copy)]
pub struct Case {
    pub b: usize,
    pub cin: usize,
    pub h: usize,
    pub w: usize,
    pub cout: usize,
    pub kh: usize,
    pub kw: usize,
    pub stride: usize,
    pub pad: usize,
}

#[allow(clippy::too_many_arguments)]
pub const fn case(
    b: usize,
    cin: usize,
    h: usize,
    w: usize,
    cout: usize,
    kh: usize,
    kw: usize,
    stride: usize,
    pad: usize,
) -> Case {
    Case {
        b,
        cin,
        h,
        w,
        cout,
        kh,
        kw,
        stride,
        pad,
    }
}

/// Shapes that reach every edge of the kernels: odd sizes, images smaller than one Winograd
/// tile or GEMM band, several bands and tasks, batch > 1, strides 1-3, paddings 0-2, 1x1,
/// 4x4, 5x5 and rectangular kernels, 3 input channels, split reductions.
pub const CASES: &[Case] = &[
    case(1, 3, 17, 13, 5, 3, 3, 1, 1),
    case(2, 4, 9, 11, 6, 3, 3, 1, 0),
    case(2, 5, 15, 16, 7, 3, 3, 2, 1),
    case(1, 6, 10, 10, 4, 1, 1, 1, 0),
    case(2, 6, 10, 9, 4, 1, 1, 2, 0),
    case(1, 3, 12, 12, 4, 4, 4, 2, 1),
    case(1, 2, 7, 9, 3, 2, 3, 1, 1),
    case(1, 8, 3, 3, 8, 3, 3, 1, 1),
    case(1, 4, 2, 2, 3, 3, 3, 1, 1),
    case(1, 4, 1, 5, 3, 3, 3, 1, 1),
    case(1, 16, 37, 37, 24, 3, 3, 2, 1),
    case(1, 20, 40, 33, 12, 3, 3, 1, 1),
    case(3, 7, 21, 18, 9, 3, 3, 1, 2),
    case(1, 32, 64, 70, 16, 3, 3, 1, 1),
    case(1, 3, 11, 11, 2, 5, 5, 1, 2),
    case(1, 3, 8, 8, 4, 3, 3, 3, 1),
    case(1, 5, 6, 7, 3, 1, 1, 1, 1),
    case(2, 9, 19, 19, 11, 3, 3, 1, 1),
    // Few pixels, many patch rows: the reduction is split over input-channel ranges.
    case(2, 240, 9, 9, 8, 3, 3, 1, 1),
    case(1, 230, 12, 11, 6, 3, 3, 2, 1),
];

pub fn spec(c: &Case) -> Conv2dSpec {
    Conv2dSpec {
        stride: c.stride,
        padding: c.pad,
    }
}

pub fn algos(c: &Case) -> Vec<ConvAlgo> {
    let mut a = vec![ConvAlgo::Auto, ConvAlgo::Gemm];
    if c.kh == 3 && c.kw == 3 && c.stride == 1 {
        a.push(ConvAlgo::Winograd);
    }
    a
}

/// candle's conv2d plus bias, in f64.
pub fn reference(x: &Tensor, w: &Tensor, b: &Tensor, c: &Case) -> Tensor {
    let y = x.conv2d(w, c.pad, c.stride, 1, 1).unwrap();
    y.broadcast_add(&b.reshape((1, c.cout, 1, 1)).unwrap())
        .unwrap()
}

pub fn flat(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

/// Largest `|actual - expected| / scale` and where; panics with the element if over `tol`.
pub fn check_close(what: &str, actual: &[f64], expected: &[f64], scale: &[f64], tol: f64) -> f64 {
    assert_eq!(actual.len(), expected.len(), "{what}: length");
    let mut worst = 0.0f64;
    for (i, ((a, e), s)) in actual.iter().zip(expected).zip(scale).enumerate() {
        let err = (a - e).abs() / s.max(1e-30);
        assert!(
            err <= tol,
            "{what}: index {i}: expected {e}, actual {a}, error {err:e} of scale {s} > tolerance {tol:e}"
        );
        worst = worst.max(err);
    }
    worst
}

/// Tolerance of one path in one dtype.
pub fn tolerance(dtype: DType, algo: ConvAlgo) -> f64 {
    match (dtype, algo) {
        (DType::F64, _) => F64_TOL,
        (_, ConvAlgo::Winograd | ConvAlgo::Auto) => WINOGRAD_F32_TOL,
        _ => GEMM_F32_TOL,
    }
}

/// Checks case `ci` through every path in f32 and f64, with and without bias; returns the
/// largest error seen.
pub fn check_forward(ci: usize, c: &Case) -> f64 {
    let seed = 10 * ci as u64;
    let x = tensor(&[c.b, c.cin, c.h, c.w], seed);
    let w = tensor(&[c.cout, c.cin, c.kh, c.kw], seed + 1);
    let b = tensor(&[c.cout], seed + 2);
    let expected = flat(&reference(&x, &w, &b, c));
    // conv(|x|, |w|) + |b| bounds the partial sums of every output.
    let scale = flat(&reference(
        &x.abs().unwrap(),
        &w.abs().unwrap(),
        &b.abs().unwrap(),
        c,
    ));
    let mut worst_all = 0.0f64;
    for algo in algos(c) {
        for dtype in [DType::F32, DType::F64] {
            let (xd, wd, bd) = (
                x.to_dtype(dtype).unwrap(),
                w.to_dtype(dtype).unwrap(),
                b.to_dtype(dtype).unwrap(),
            );
            let y = conv2d_with_algo(&xd, &wd, Some(&bd), spec(c), algo).unwrap();
            assert_eq!(y.dtype(), dtype);
            let tol = tolerance(dtype, algo);
            let worst = check_close(
                &format!("{c:?} {algo:?} {dtype:?}"),
                &flat(&y),
                &expected,
                &scale,
                tol,
            );
            println!("{c:?} {algo:?} {dtype:?}: max error {worst:.2e}");
            worst_all = worst_all.max(worst);
            // Without bias: the CustomOp2 path.
            let y0 = conv2d_with_algo(&xd, &wd, None, spec(c), algo).unwrap();
            let y0b = y0
                .broadcast_add(&bd.reshape((1, c.cout, 1, 1)).unwrap())
                .unwrap();
            check_close(
                &format!("{c:?} {algo:?} {dtype:?} no bias"),
                &flat(&y0b),
                &expected,
                &scale,
                tol,
            );
        }
    }
    worst_all
}
