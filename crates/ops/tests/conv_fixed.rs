//! `conv2d_fixed`: the inference convolution that keeps a fixed weight's Winograd transform and
//! scales it per call (StyleGAN2's modulated weights), against candle's f64 convolution of the
//! scaled weight.

mod common;

use candle_core::{DType, Tensor, Var};
use common::*;
use gagavatar_ops::conv::{conv2d_fixed, WinogradCache};
use gagavatar_ops::{conv2d, Conv2dSpec};

/// Shapes: two that run Winograd (>= 64 output tiles, >= 8 channels; the second with a filter
/// count, 11 x 13 = 143, that is not a multiple of the transform's block) and one that runs
/// the GEMM (too few tiles), where the scaled weight is formed instead.
const SHAPES: [Case; 3] = [
    case(1, 16, 48, 48, 24, 3, 3, 1, 1),
    case(2, 13, 50, 47, 11, 3, 3, 1, 1),
    case(1, 16, 12, 12, 24, 3, 3, 1, 1),
];

fn f32(t: &Tensor) -> Tensor {
    t.to_dtype(DType::F32).unwrap()
}

/// Filter scales in [0.5, 1.5), like a style times a demodulation factor.
fn filter_scale(c: &Case, seed: u64) -> Tensor {
    ((tensor(&[c.cout, c.cin], seed) * 0.5).unwrap() + 1.0).unwrap()
}

fn scaled_weight(w: &Tensor, s: &Tensor, c: &Case) -> Tensor {
    w.broadcast_mul(&s.reshape((c.cout, c.cin, 1, 1)).unwrap())
        .unwrap()
}

#[test]
fn matches_the_convolution_of_the_scaled_weight() {
    for (ci, c) in SHAPES.iter().enumerate() {
        let seed = 40 + 10 * ci as u64;
        let x = tensor(&[c.b, c.cin, c.h, c.w], seed);
        let w = tensor(&[c.cout, c.cin, 3, 3], seed + 1);
        let b = tensor(&[c.cout], seed + 2);
        let s = filter_scale(c, seed + 3);
        let (xf, wf, bf, sf) = (f32(&x), f32(&w), f32(&b), f32(&s));
        let cache = WinogradCache::default();
        for with_scale in [false, true] {
            for with_bias in [false, true] {
                let ws = if with_scale {
                    scaled_weight(&w, &s, c)
                } else {
                    w.clone()
                };
                let mut expected = x.conv2d(&ws, c.pad, 1, 1, 1).unwrap();
                if with_bias {
                    expected = expected
                        .broadcast_add(&b.reshape((1, c.cout, 1, 1)).unwrap())
                        .unwrap();
                }
                let magnitude = flat(
                    &x.abs()
                        .unwrap()
                        .conv2d(&ws.abs().unwrap(), c.pad, 1, 1, 1)
                        .unwrap(),
                );
                let actual = conv2d_fixed(
                    &xf,
                    &wf,
                    with_scale.then_some(&sf),
                    with_bias.then_some(&bf),
                    spec(c),
                    &cache,
                )
                .unwrap();
                let scale: Vec<f64> = magnitude.iter().map(|m| m + 1.0).collect();
                check_close(
                    &format!("{c:?} scale {with_scale} bias {with_bias}"),
                    &flat(&actual),
                    &flat(&expected),
                    &scale,
                    WINOGRAD_F32_TOL,
                );
            }
        }
        // Only the layers that run Winograd keep a transform.
        assert_eq!(cache.is_filled(), ci < 2, "{c:?}: cache filled");
    }
}

#[test]
fn reuses_its_transform_and_renews_it_for_a_new_weight() {
    let c = SHAPES[0];
    let x = f32(&tensor(&[c.b, c.cin, c.h, c.w], 1));
    let w1 = f32(&tensor(&[c.cout, c.cin, 3, 3], 2));
    let w2 = f32(&tensor(&[c.cout, c.cin, 3, 3], 3));
    let s = f32(&filter_scale(&c, 4));
    let cache = WinogradCache::default();
    let first = flat(&conv2d_fixed(&x, &w1, Some(&s), None, spec(&c), &cache).unwrap());
    assert!(cache.is_filled());
    let again = flat(&conv2d_fixed(&x, &w1, Some(&s), None, spec(&c), &cache).unwrap());
    for (i, (a, e)) in again.iter().zip(&first).enumerate() {
        assert!(
            a.to_bits() == e.to_bits(),
            "index {i}: first call {e}, second call {a}"
        );
    }
    // The same cache given another weight of the same shape must not reuse the old transform.
    let other = flat(&conv2d_fixed(&x, &w2, Some(&s), None, spec(&c), &cache).unwrap());
    let expected = flat(&conv2d(&x, &scaled_weight(&w2, &s, &c), None, spec(&c)).unwrap());
    let ones = vec![1.0; expected.len()];
    check_close("new weight", &other, &expected, &ones, 1e-4);
    let moved = other.iter().zip(&first).filter(|(a, b)| a != b).count();
    assert!(moved > other.len() / 2, "only {moved} outputs changed");
}

/// A trainable weight or a tracked input takes the differentiable path: the same gradients as
/// `conv2d` of the scaled weight, and nothing cached.
#[test]
fn tracked_operands_keep_their_gradients() {
    let c = SHAPES[0];
    let x = f32(&tensor(&[c.b, c.cin, c.h, c.w], 5));
    let w = Var::from_tensor(&f32(&tensor(&[c.cout, c.cin, 3, 3], 6))).unwrap();
    let s = Var::from_tensor(&f32(&filter_scale(&c, 7))).unwrap();
    let r = f32(&tensor(&[c.b, c.cout, c.h, c.w], 8));
    let cache = WinogradCache::default();
    let y = conv2d_fixed(
        &x,
        w.as_tensor(),
        Some(s.as_tensor()),
        None,
        spec(&c),
        &cache,
    )
    .unwrap();
    let grads = (y * &r).unwrap().sum_all().unwrap().backward().unwrap();
    let y_ref = conv2d(
        &x,
        &scaled_weight(w.as_tensor(), s.as_tensor(), &c),
        None,
        spec(&c),
    )
    .unwrap();
    let grads_ref = (y_ref * &r).unwrap().sum_all().unwrap().backward().unwrap();
    assert!(!cache.is_filled());
    for (name, v) in [("weight", &w), ("scale", &s)] {
        let (g, e) = (flat(grads.get(v).unwrap()), flat(grads_ref.get(v).unwrap()));
        let ones = vec![1.0; e.len()];
        check_close(&format!("gradient of the {name}"), &g, &e, &ones, 0.0);
    }
}

#[test]
fn a_scale_of_the_wrong_shape_is_an_error() {
    let c = SHAPES[0];
    let x = f32(&tensor(&[c.b, c.cin, c.h, c.w], 9));
    let w = f32(&tensor(&[c.cout, c.cin, 3, 3], 10));
    let bad = f32(&tensor(&[c.cin, c.cout], 11));
    let spec = Conv2dSpec {
        stride: 1,
        padding: 1,
    };
    let err = conv2d_fixed(&x, &w, Some(&bad), None, spec, &WinogradCache::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("filter scale must be [24, 16]"), "{err}");
}

/// Many first calls of one layer at once, from rayon tasks (as LPIPS runs inside a parallel
/// evaluation): they finish, agree bit for bit, and leave one transform.
#[test]
fn concurrent_first_calls_finish_and_agree() {
    use rayon::prelude::*;
    let c = case(1, 64, 48, 48, 64, 3, 3, 1, 1);
    let x = f32(&tensor(&[c.b, c.cin, c.h, c.w], 12));
    let w = f32(&tensor(&[c.cout, c.cin, 3, 3], 13));
    let cache = WinogradCache::default();
    // More workers than this machine's cores, so that first calls overlap.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(6)
        .build()
        .unwrap();
    let outs: Vec<Vec<f64>> = pool.install(|| {
        (0..24)
            .into_par_iter()
            .map(|_| flat(&conv2d_fixed(&x, &w, None, None, spec(&c), &cache).unwrap()))
            .collect()
    });
    for (k, o) in outs.iter().enumerate().skip(1) {
        for (i, (a, e)) in o.iter().zip(&outs[0]).enumerate() {
            assert!(
                a.to_bits() == e.to_bits(),
                "call {k} index {i}: first call {e}, this call {a}"
            );
        }
    }
    assert!(cache.is_filled());
}
