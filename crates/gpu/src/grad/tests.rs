//! The backward kernels against candle's CPU autograd and against f64 central differences.

use candle_core::{Device, Tensor, Var};
use gagavatar_splat::testscene::Rng;

use super::conv::{conv_backward, wgrad_plan, ConvGrad};
use super::layers::{act_backward, resize_backward, rms_norm_backward, Kept};
use super::modconv::{modconv_backward, ModConvGrad, ModConvScratch};
use super::optim::{adam, AdamBuffers, AdamStep, GpuAdam};
use super::params::Param;
use crate::conv::{Act, At, Conv, ConvWeights, Ops};
use crate::device::Gpu;
use crate::error::GpuError;
use crate::kernel::Step;
use crate::testutil::{assert_close, gpu, max_diff};
use crate::tuning::{ConvTile, Tuning};

/// A gradient of sums of up to ~10^4 f32 products, in another order than candle's: the
/// largest difference relative to the largest gradient value.
const GRAD_REL_TOL: f64 = 1e-5;
/// The GPU's f32 gradients against f64 central differences of the f64 loss, relative to
/// `max(1, |gradient|)`: f32 rounding of sums of a few hundred products.
const FD_TOL: f64 = 1e-4;
/// Step of the central differences (the loss is smooth away from the activations' kinks).
const FD_STEP: f64 = 1e-4;
/// The activation gradients against f64 derivatives (GELU's through A&S erf, |error| < 1.5e-7).
const ACT_TOL: f64 = 1e-6;
/// Adam's parameters after a few steps against the f64 update, relative to `max(1, |p|)`.
const ADAM_TOL: f64 = 1e-6;

fn values(rng: &mut Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect()
}

#[derive(Debug, Clone, Copy)]
struct Layer {
    cin: usize,
    cout: usize,
    h: usize,
    w: usize,
    k: usize,
}

impl Layer {
    fn x_len(&self) -> usize {
        self.cin * self.h * self.w
    }
    fn z_len(&self) -> usize {
        self.cout * self.h * self.w
    }
    fn w_len(&self) -> usize {
        self.cout * self.cin * self.k * self.k
    }
}

/// The scratch every test of a layer needs, with an [`Ops`] over it.
struct Bench {
    tuning: Tuning,
    small: wgpu::Buffer,
    split: wgpu::Buffer,
}

impl Bench {
    fn new(g: &Gpu, tuning: Tuning, l: Layer) -> Self {
        let need = Ops::split_need(&tuning, l.cout, l.cin, l.h, l.w, l.k)
            .max(Ops::split_need(&tuning, l.cin, l.cout, l.h, l.w, l.k));
        Bench {
            tuning,
            small: g.buffer("vecs", 64),
            split: g.buffer("split", 4 * need as u64),
        }
    }
    fn ops<'a>(&'a self, g: &'a Gpu) -> Ops<'a> {
        Ops {
            gpu: g,
            tuning: &self.tuning,
            vecs: &self.small,
            dummy: &self.small,
            split_scratch: &self.split,
        }
    }
}

/// The GPU's (dX, dW, dB) of one layer for the output gradient `dz`; with `prior`, the weight
/// and bias gradients are accumulated onto those values.
fn gpu_grads(
    g: &Gpu,
    tuning: Tuning,
    l: Layer,
    x: &[f32],
    wt: &[f32],
    dz: &[f32],
    prior: Option<(&[f32], &[f32])>,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let bench = Bench::new(g, tuning, l);
    let ops = bench.ops(g);
    // Offsets into the buffers, so the kernels' offset arithmetic is covered too.
    let (xo, zo, go) = (3usize, 5usize, 7usize);
    let mut xs = vec![0f32; xo];
    xs.extend_from_slice(x);
    let mut zs = vec![0f32; zo];
    zs.extend_from_slice(dz);
    let xb = g.buffer_with("x", &xs);
    let zb = g.buffer_with("dz", &zs);
    let wb = g.buffer_with("w", wt);
    let dxb = g.buffer("dx", 4 * (go + l.x_len()) as u64);
    let (pw, pb) = prior.unwrap_or((&[], &[]));
    let mut init_w = vec![0f32; go];
    init_w.extend(if pw.is_empty() {
        vec![0.0; l.w_len()]
    } else {
        pw.to_vec()
    });
    let mut init_b = vec![0f32; go];
    init_b.extend(if pb.is_empty() {
        vec![0.0; l.cout]
    } else {
        pb.to_vec()
    });
    let dwb = g.buffer_with("dw", &init_w);
    let dbb = g.buffer_with("db", &init_b);
    let c = ConvGrad {
        cin: l.cin,
        cout: l.cout,
        h: l.h,
        w: l.w,
        k: l.k,
        input: At::off(&xb, xo),
        weight: &wb,
        grad_out: At::off(&zb, zo),
        grad_input: Some(At::off(&dxb, go)),
        grad_weight: At::off(&dwb, go),
        grad_bias: Some(At::off(&dbb, go)),
        accumulate: prior.is_some(),
    };
    let steps = backward_alone(g, &ops, &c);
    g.submit(&steps);
    let read =
        |b: &wgpu::Buffer, n: usize| g.read_f32(b, go + n).expect("read back")[go..].to_vec();
    (
        read(&dxb, l.x_len()),
        read(&dwb, l.w_len()),
        read(&dbb, l.cout),
    )
}

/// `c`'s backward recorded with scratch of its own (the recorded steps keep it alive).
fn backward_alone(g: &Gpu, ops: &Ops, c: &ConvGrad) -> Vec<Step> {
    let flipped = g.buffer("flipped", 4 * c.flipped_floats() as u64);
    let part = g.buffer("part", 4 * c.part_floats(ops) as u64);
    conv_backward(ops, c, &flipped, &part).expect("record the backward")
}

/// candle's gradients of `sum(G * (conv(X, W) + B))` (so dZ = G), f32 on the CPU.
fn cpu_grads(l: Layer, x: &[f32], wt: &[f32], dz: &[f32]) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let dev = Device::Cpu;
    let xv = Var::from_vec(x.to_vec(), (1, l.cin, l.h, l.w), &dev).unwrap();
    let wv = Var::from_vec(wt.to_vec(), (l.cout, l.cin, l.k, l.k), &dev).unwrap();
    let bv = Var::from_vec(vec![0.1f32; l.cout], l.cout, &dev).unwrap();
    let gz = Tensor::from_vec(dz.to_vec(), (1, l.cout, l.h, l.w), &dev).unwrap();
    let z = xv
        .conv2d(&wv, l.k / 2, 1, 1, 1)
        .unwrap()
        .broadcast_add(&bv.reshape((1, l.cout, 1, 1)).unwrap())
        .unwrap();
    let loss = (z * gz).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let flat = |v: &Var| {
        grads
            .get(v.as_tensor())
            .expect("a gradient")
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    };
    (flat(&xv), flat(&wv), flat(&bv))
}

fn assert_rel(what: &str, want: &[f32], got: &[f32], rel: f64) {
    let scale = want
        .iter()
        .fold(0f64, |m, v| m.max(v.abs() as f64))
        .max(1e-30);
    assert_close(what, want, got, rel * scale);
}

const LAYERS: [Layer; 5] = [
    Layer {
        cin: 5,
        cout: 7,
        h: 9,
        w: 11,
        k: 3,
    },
    Layer {
        cin: 3,
        cout: 4,
        h: 6,
        w: 5,
        k: 1,
    },
    Layer {
        cin: 16,
        cout: 24,
        h: 20,
        w: 20,
        k: 3,
    },
    // Wider than a 64-wide tile in both dimensions, many pixel slices.
    Layer {
        cin: 40,
        cout: 70,
        h: 33,
        w: 35,
        k: 3,
    },
    Layer {
        cin: 1,
        cout: 1,
        h: 1,
        w: 1,
        k: 3,
    },
];

/// Input, weight and bias gradients of each layer against candle's autograd, with the default
/// tile and a smaller one (another generated micro-tile), and with split-K in the input
/// gradient's convolution.
#[test]
fn conv_gradients_match_candle_autograd() {
    let Some(g) = gpu() else { return };
    let small_tile = ConvTile {
        bm: 32,
        bn: 32,
        bk: 8,
        tm: 2,
        tn: 4,
    };
    let tunings = [
        Tuning::default(),
        Tuning {
            conv: small_tile,
            conv_small: small_tile,
            conv_split_k: 16,
            ..Tuning::default()
        },
    ];
    let mut rng = Rng::new(11);
    for (ti, tuning) in tunings.iter().enumerate() {
        for l in LAYERS {
            let x = values(&mut rng, l.x_len());
            let wt = values(&mut rng, l.w_len());
            let dz = values(&mut rng, l.z_len());
            let (dx, dw, db) = gpu_grads(g, tuning.clone(), l, &x, &wt, &dz, None);
            let (cx, cw, cb) = cpu_grads(l, &x, &wt, &dz);
            let what = format!("tuning {ti} {l:?}");
            assert_rel(&format!("{what} dX"), &cx, &dx, GRAD_REL_TOL);
            assert_rel(&format!("{what} dW"), &cw, &dw, GRAD_REL_TOL);
            assert_rel(&format!("{what} dB"), &cb, &db, GRAD_REL_TOL);
        }
    }
}

/// `accumulate` adds the weight and bias gradients to what the buffers held; the input
/// gradient is overwritten either way.
#[test]
fn accumulated_gradients_add_to_the_buffers() {
    let Some(g) = gpu() else { return };
    let l = LAYERS[2];
    let mut rng = Rng::new(12);
    let x = values(&mut rng, l.x_len());
    let wt = values(&mut rng, l.w_len());
    let dz = values(&mut rng, l.z_len());
    let pw = values(&mut rng, l.w_len());
    let pb = values(&mut rng, l.cout);
    let (dx0, dw0, db0) = gpu_grads(g, Tuning::default(), l, &x, &wt, &dz, None);
    let (dx1, dw1, db1) = gpu_grads(g, Tuning::default(), l, &x, &wt, &dz, Some((&pw, &pb)));
    assert_eq!(dx0, dx1, "the input gradient must not accumulate");
    let sum = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(a, b)| a + b).collect::<Vec<_>>();
    assert_close("accumulated dW", &sum(&pw, &dw0), &dw1, 1e-6);
    assert_close("accumulated dB", &sum(&pb, &db0), &db1, 1e-6);
}

/// The weight gradient's pixel slices cover every pixel once, for sizes around the slice
/// boundaries.
#[test]
fn wgrad_slices_cover_the_pixels() {
    let tile = Tuning::default().conv;
    for hw in [1usize, 15, 16, 17, 400, 1155, 65_536, 262_144] {
        for (cin, cout, k) in [(1, 1, 3), (64, 64, 3), (512, 256, 3), (3, 32, 1)] {
            let p = wgrad_plan(tile, cin, cout, hw, k);
            assert_eq!(p.slice % tile.bk as usize, 0, "slice of {p:?}");
            assert!(p.slices * p.slice >= hw, "{p:?} misses pixels of {hw}");
            assert!(
                (p.slices - 1) * p.slice < hw,
                "{p:?} has an empty slice for {hw}"
            );
        }
    }
}

/// f64 loops: `y = act(conv(x, w) + b)` of a layer.
fn forward_f64(l: Layer, act: Act, x: &[f64], wt: &[f64], b: &[f64]) -> Vec<f64> {
    let (hw, taps, pad) = (l.h * l.w, l.k * l.k, (l.k / 2) as isize);
    let mut y = vec![0f64; l.z_len()];
    for co in 0..l.cout {
        for py in 0..l.h {
            for px in 0..l.w {
                let mut s = b[co];
                for ci in 0..l.cin {
                    for t in 0..taps {
                        let yy = py as isize + (t / l.k) as isize - pad;
                        let xx = px as isize + (t % l.k) as isize - pad;
                        if yy < 0 || xx < 0 || yy >= l.h as isize || xx >= l.w as isize {
                            continue;
                        }
                        s += wt[(co * l.cin + ci) * taps + t]
                            * x[ci * hw + yy as usize * l.w + xx as usize];
                    }
                }
                y[co * hw + py * l.w + px] = match act {
                    Act::Lrelu => s.max(0.2 * s),
                    Act::Relu => s.max(0.0),
                    Act::Gelu => {
                        0.5 * s
                            * (1.0 + candle_core::cpu::erf::erf_f64(s / std::f64::consts::SQRT_2))
                    }
                    Act::None => s,
                };
            }
        }
    }
    y
}

/// A convolution with leaky ReLU, then one with GELU, forward on the GPU, backward through
/// `act_backward` and `conv_backward`, against f64 central differences of
/// `L = sum(G * act(conv(X, W) + B))` at sampled entries of X, W and B.
#[test]
fn conv_and_activation_gradients_match_f64_finite_differences() {
    let Some(g) = gpu() else { return };
    let l = Layer {
        cin: 3,
        cout: 4,
        h: 6,
        w: 7,
        k: 3,
    };
    let tuning = Tuning::default();
    let bench = Bench::new(g, tuning, l);
    let ops = bench.ops(g);
    for (seed, act) in [(21u64, Act::Lrelu), (22, Act::Gelu)] {
        let mut rng = Rng::new(seed);
        let x = values(&mut rng, l.x_len());
        let wt = values(&mut rng, l.w_len());
        let b = values(&mut rng, l.cout);
        let gy = values(&mut rng, l.z_len());
        // The forward: the pre-activation (kept for GELU) and the output (kept for leaky ReLU).
        let xb = g.buffer_with("x", &x);
        let weights = ConvWeights {
            weight: g.buffer_with("w", &wt),
            bias: Some(0),
            cin: l.cin,
            cout: l.cout,
            k: l.k,
        };
        let vecs = g.buffer_with("bias", &b);
        let zb = g.buffer("z", 4 * l.z_len() as u64);
        let yb = g.buffer("y", 4 * l.z_len() as u64);
        let fwd = Ops {
            vecs: &vecs,
            ..bench.ops(g)
        };
        let mut steps = fwd
            .conv(&Conv::plain(
                &weights,
                (l.h, l.w),
                At::new(&xb),
                At::new(&zb),
            ))
            .unwrap();
        steps.extend(
            fwd.conv(&Conv {
                act,
                ..Conv::plain(&weights, (l.h, l.w), At::new(&xb), At::new(&yb))
            })
            .unwrap(),
        );
        // The backward.
        let gyb = g.buffer_with("dy", &gy);
        let dzb = g.buffer("dz", 4 * l.z_len() as u64);
        let (kept, kind) = if act == Act::Gelu {
            (&zb, Kept::GeluInput)
        } else {
            (&yb, Kept::LreluOutput)
        };
        steps.push(
            act_backward(
                g,
                kind,
                l.z_len(),
                At::new(kept),
                At::new(&gyb),
                At::new(&dzb),
            )
            .unwrap(),
        );
        let (dxb, dwb, dbb) = (
            g.buffer("dx", 4 * l.x_len() as u64),
            g.buffer("dw", 4 * l.w_len() as u64),
            g.buffer("db", 4 * l.cout as u64),
        );
        let c = ConvGrad {
            cin: l.cin,
            cout: l.cout,
            h: l.h,
            w: l.w,
            k: l.k,
            input: At::new(&xb),
            weight: &weights.weight,
            grad_out: At::new(&dzb),
            grad_input: Some(At::new(&dxb)),
            grad_weight: At::new(&dwb),
            grad_bias: Some(At::new(&dbb)),
            accumulate: false,
        };
        steps.extend(backward_alone(g, &ops, &c));
        g.submit(&steps);
        let dx = g.read_f32(&dxb, l.x_len()).unwrap();
        let dw = g.read_f32(&dwb, l.w_len()).unwrap();
        let db = g.read_f32(&dbb, l.cout).unwrap();

        let f64s = |v: &[f32]| v.iter().map(|&a| a as f64).collect::<Vec<f64>>();
        let (x64, w64, b64, g64) = (f64s(&x), f64s(&wt), f64s(&b), f64s(&gy));
        let loss = |x: &[f64], w: &[f64], b: &[f64]| -> f64 {
            forward_f64(l, act, x, w, b)
                .iter()
                .zip(&g64)
                .map(|(y, g)| y * g)
                .sum()
        };
        let mut sample = Rng::new(seed + 100);
        for (name, grad, which) in [("dX", &dx, 0), ("dW", &dw, 1), ("dB", &db, 2)] {
            for _ in 0..24 {
                let i = sample.below(grad.len());
                let (mut xp, mut wp, mut bp) = (x64.clone(), w64.clone(), b64.clone());
                let (mut xm, mut wm, mut bm) = (x64.clone(), w64.clone(), b64.clone());
                match which {
                    0 => (xp[i] += FD_STEP, xm[i] -= FD_STEP),
                    1 => (wp[i] += FD_STEP, wm[i] -= FD_STEP),
                    _ => (bp[i] += FD_STEP, bm[i] -= FD_STEP),
                };
                let fd = (loss(&xp, &wp, &bp) - loss(&xm, &wm, &bm)) / (2.0 * FD_STEP);
                let got = grad[i] as f64;
                assert!(
                    (got - fd).abs() <= FD_TOL * fd.abs().max(1.0),
                    "{act:?} {name} index {i}: expected (f64 central difference) {fd}, actual {got}"
                );
            }
        }
        eprintln!("{act:?}: 72 sampled gradients within {FD_TOL:e} of f64 central differences");
    }
}

/// Leaky ReLU, ReLU, GELU and sigmoid gradients over values around 0 and far out, against f64.
#[test]
fn activation_gradients_match_f64() {
    let Some(g) = gpu() else { return };
    let mut v: Vec<f32> = (0..=4000).map(|i| -10.0 + i as f32 / 200.0).collect();
    v.extend([0.0, -0.0, 1e-30, -1e-30, 1e-7, -1e-7, 30.0, -30.0]);
    let mut rng = Rng::new(5);
    let dy = values(&mut rng, v.len());
    let vb = g.buffer_with("v", &v);
    let dyb = g.buffer_with("dy", &dy);
    let out = g.buffer("dz", 4 * v.len() as u64);
    for kind in [
        Kept::LreluOutput,
        Kept::ReluOutput,
        Kept::GeluInput,
        Kept::SigmoidOutput,
    ] {
        let step =
            act_backward(g, kind, v.len(), At::new(&vb), At::new(&dyb), At::new(&out)).unwrap();
        g.submit(&[step]);
        let got = g.read_f32(&out, v.len()).unwrap();
        let want: Vec<f32> = v
            .iter()
            .zip(&dy)
            .map(|(&s, &d)| {
                let s = s as f64;
                let slope = match kind {
                    Kept::LreluOutput => {
                        if s > 0.0 {
                            1.0
                        } else {
                            0.2
                        }
                    }
                    Kept::ReluOutput => {
                        if s > 0.0 {
                            1.0
                        } else {
                            0.0
                        }
                    }
                    // `s` is the sigmoid's output here.
                    Kept::SigmoidOutput => s * (1.0 - s),
                    Kept::GeluInput => {
                        let cdf = 0.5
                            * (1.0 + candle_core::cpu::erf::erf_f64(s / std::f64::consts::SQRT_2));
                        cdf + s * (-0.5 * s * s).exp() / (2.0 * std::f64::consts::PI).sqrt()
                    }
                };
                (d as f64 * slope) as f32
            })
            .collect();
        // The sigmoid's slope of values far outside (0, 1) is large: compare relatively.
        let scale = want.iter().fold(1f64, |m, v| m.max(v.abs() as f64));
        assert_close(&format!("{kind:?} gradient"), &want, &got, ACT_TOL * scale);
    }
}

/// The x2 resizes' input gradients against candle's autograd through the CPU path's
/// differentiable resizes (odd sizes upsampled too), at buffer offsets.
#[test]
fn resize_gradients_match_candle_autograd() {
    let Some(g) = gpu() else { return };
    let dev = Device::Cpu;
    let mut rng = Rng::new(41);
    for (up, c, h, w) in [
        (true, 3, 5, 7),
        (true, 2, 1, 1),
        (true, 4, 16, 16),
        (false, 3, 6, 8),
        (false, 2, 2, 2),
        (false, 4, 32, 32),
    ] {
        let (ho, wo) = if up { (2 * h, 2 * w) } else { (h / 2, w / 2) };
        let x = values(&mut rng, c * h * w);
        let dy = values(&mut rng, c * ho * wo);
        let xv = Var::from_vec(x.clone(), (1, c, h, w), &dev).unwrap();
        let y = if up {
            gagavatar_ops::resize(&xv, ho, wo, gagavatar_ops::ResizeMode::HalfPixel).unwrap()
        } else {
            gagavatar_net::style_unet::downsample2x(&xv).unwrap()
        };
        let gy = Tensor::from_vec(dy.clone(), (1, c, ho, wo), &dev).unwrap();
        let grads = (y * gy).unwrap().sum_all().unwrap().backward().unwrap();
        let want: Vec<f32> = grads
            .get(xv.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let mut dys = vec![0f32; 9];
        dys.extend_from_slice(&dy);
        let dyb = g.buffer_with("dy", &dys);
        let dxb = g.buffer("dx", 4 * (4 + c * h * w) as u64);
        let step = resize_backward(g, up, (c, h, w), At::off(&dyb, 9), At::off(&dxb, 4)).unwrap();
        g.submit(&[step]);
        let got = g.read_f32(&dxb, 4 + c * h * w).unwrap()[4..].to_vec();
        assert_close(
            &format!(
                "resize {} {c}x{h}x{w} gradient",
                if up { "up" } else { "down" }
            ),
            &want,
            &got,
            GRAD_REL_TOL,
        );
    }
    let dummy = g.buffer("d", 4);
    assert!(resize_backward(g, false, (1, 1, 4), At::new(&dummy), At::new(&dummy)).is_err());
}

/// The mapping network's normalisation: input gradient against f64 central differences.
#[test]
fn rms_norm_gradient_matches_f64_finite_differences() {
    let Some(g) = gpu() else { return };
    for n in [1usize, 7, 512, 1000] {
        let mut rng = Rng::new(n as u64);
        let x = values(&mut rng, n);
        let dy = values(&mut rng, n);
        let (xb, dyb, dxb) = (
            g.buffer_with("x", &x),
            g.buffer_with("dy", &dy),
            g.buffer("dx", 4 * n as u64),
        );
        g.submit(&[rms_norm_backward(g, n, &xb, &dyb, &dxb).unwrap()]);
        let got = g.read_f32(&dxb, n).unwrap();
        let loss = |x: &[f64]| -> f64 {
            let d = (x.iter().map(|v| v * v).sum::<f64>() / n as f64 + 1e-8).sqrt();
            x.iter().zip(&dy).map(|(v, g)| v / d * *g as f64).sum()
        };
        let x64: Vec<f64> = x.iter().map(|&v| v as f64).collect();
        for i in (0..n).step_by((n / 16).max(1)) {
            let (mut xp, mut xm) = (x64.clone(), x64.clone());
            xp[i] += FD_STEP;
            xm[i] -= FD_STEP;
            let fd = (loss(&xp) - loss(&xm)) / (2.0 * FD_STEP);
            assert!(
                (got[i] as f64 - fd).abs() <= FD_TOL * fd.abs().max(1.0),
                "rms norm n={n} index {i}: expected (f64 central difference) {fd}, actual {}",
                got[i]
            );
        }
    }
}

/// One modulated convolution with its style linear layer, forward and backward on the GPU,
/// against candle's autograd through the CPU path's `ModulatedConv` (the renderer's layer): the
/// gradients of the input, the latent, the weight, the modulation's weight and bias and the
/// bias. Demodulated with gain sqrt 2 (3x3) and plain with gain 1 (1x1, the RGB layers).
#[test]
fn modulated_conv_gradients_match_the_cpu_layer() {
    use candle_nn::{VarBuilder, VarMap};
    use gagavatar_net::style_unet::ModulatedConv;
    let Some(g) = gpu() else { return };
    let dev = Device::Cpu;
    for (seed, demodulate, k, gain) in [
        (51u64, true, 3usize, std::f64::consts::SQRT_2),
        (52, false, 1, 1.0),
    ] {
        let (cin, cout, h, w, sd) = (6usize, 5usize, 9usize, 7usize, 8usize);
        let mut rng = Rng::new(seed);
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, candle_core::DType::F32, &dev);
        let layer = ModulatedConv::new(vb.pp("m"), cin, cout, k, sd, demodulate).unwrap();
        let mut named: Vec<(String, Var)> = varmap
            .data()
            .lock()
            .unwrap()
            .iter()
            .map(|(n, v)| (n.clone(), v.clone()))
            .collect();
        named.sort_by(|a, b| a.0.cmp(&b.0));
        let mut host = std::collections::HashMap::new();
        for (name, var) in &named {
            let vals = values(&mut rng, var.elem_count());
            var.set(&Tensor::from_vec(vals.clone(), var.shape(), &dev).unwrap())
                .unwrap();
            host.insert(name.clone(), vals);
        }
        let x = values(&mut rng, cin * h * w);
        let latent = values(&mut rng, sd);
        let bias = values(&mut rng, cout);
        let dz = values(&mut rng, cout * h * w);
        let xv = Var::from_vec(x.clone(), (1, cin, h, w), &dev).unwrap();
        let lv = Var::from_vec(latent.clone(), (1, sd), &dev).unwrap();
        let bv = Var::from_vec(bias.clone(), cout, &dev).unwrap();
        let y = layer.forward(&xv, &lv, gain, Some(bv.as_tensor())).unwrap();
        let gz = Tensor::from_vec(dz.clone(), (1, cout, h, w), &dev).unwrap();
        let grads = (y * gz).unwrap().sum_all().unwrap().backward().unwrap();
        let grad_of = |t: &Tensor| -> Vec<f32> {
            grads
                .get(t)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        };
        let var = |n: &str| named.iter().find(|(k, _)| k == n).unwrap().1.clone();
        let (wv, mwv, mbv) = (
            var("m.weight"),
            var("m.modulation.weight"),
            var("m.modulation.bias"),
        );

        // GPU: style = modulation(latent) and demodulation into `vecs`, then the backward.
        let tuning = Tuning::default();
        let l = Layer { cin, cout, h, w, k };
        let bench = Bench::new(g, tuning, l);
        let style_off = 0u32;
        let demod_off = 16u32;
        let vecs = g.buffer("vecs", 4 * 32);
        let energy: Vec<f32> = host["m.weight"]
            .chunks(k * k)
            .map(|c| c.iter().map(|v| v * v).sum())
            .collect();
        let (latb, mwb, mbb, eb) = (
            g.buffer_with("latent", &latent),
            g.buffer_with("mod w", &host["m.modulation.weight"]),
            g.buffer_with("mod b", &host["m.modulation.bias"]),
            g.buffer_with("energy", &energy),
        );
        let wb = g.buffer_with("w", &host["m.weight"]);
        let ops = Ops {
            vecs: &vecs,
            ..bench.ops(g)
        };
        let mut steps = vec![ops
            .linear(
                sd,
                cin,
                At::new(&latb),
                &mwb,
                &mbb,
                false,
                At::off(&vecs, style_off as usize),
            )
            .unwrap()];
        if demodulate {
            steps.push(
                ops.demod(cin, cout, &eb, style_off, demod_off, gain as f32)
                    .unwrap(),
            );
        }
        let (xb, dzb) = (g.buffer_with("x", &x), g.buffer_with("dz", &dz));
        let (dxb, dwb, dbb, dsb) = (
            g.buffer("dx", 4 * l.x_len() as u64),
            g.buffer("dw", 4 * l.w_len() as u64),
            g.buffer("db", 4 * cout as u64),
            g.buffer("ds", 4 * cin as u64),
        );
        let m = ModConvGrad {
            conv: ConvGrad {
                cin,
                cout,
                h,
                w,
                k,
                input: At::new(&xb),
                weight: &wb,
                grad_out: At::new(&dzb),
                grad_input: Some(At::new(&dxb)),
                grad_weight: At::new(&dwb),
                grad_bias: Some(At::new(&dbb)),
                accumulate: false,
            },
            style: style_off,
            demod: demodulate.then_some(demod_off),
            gain: gain as f32,
            grad_style: At::new(&dsb),
        };
        let flipped = g.buffer("flipped", 4 * m.conv.flipped_floats() as u64);
        let part = g.buffer("part", 4 * m.conv.part_floats(&ops) as u64);
        let scratch = ModConvScratch::new(g, &m);
        steps.extend(modconv_backward(&ops, &m, &flipped, &part, &scratch).unwrap());
        // The modulation (a linear layer: a 1x1 convolution of one pixel) from ds.
        let (dlb, dmwb, dmbb) = (
            g.buffer("dlatent", 4 * sd as u64),
            g.buffer("dmod w", 4 * (cin * sd) as u64),
            g.buffer("dmod b", 4 * cin as u64),
        );
        let lin = ConvGrad {
            cin: sd,
            cout: cin,
            h: 1,
            w: 1,
            k: 1,
            input: At::new(&latb),
            weight: &mwb,
            grad_out: At::new(&dsb),
            grad_input: Some(At::new(&dlb)),
            grad_weight: At::new(&dmwb),
            grad_bias: Some(At::new(&dmbb)),
            accumulate: false,
        };
        steps.extend(backward_alone(g, &ops, &lin));
        g.submit(&steps);

        let what = format!("modulated conv k{k} demodulate={demodulate}");
        for (name, want, buf, n) in [
            ("dX", grad_of(xv.as_tensor()), &dxb, l.x_len()),
            ("dW", grad_of(wv.as_tensor()), &dwb, l.w_len()),
            ("dB", grad_of(bv.as_tensor()), &dbb, cout),
            ("dlatent", grad_of(lv.as_tensor()), &dlb, sd),
            ("dmod.weight", grad_of(mwv.as_tensor()), &dmwb, cin * sd),
            ("dmod.bias", grad_of(mbv.as_tensor()), &dmbb, cin),
        ] {
            assert_rel(
                &format!("{what} {name}"),
                &want,
                &g.read_f32(buf, n).unwrap(),
                GRAD_REL_TOL,
            );
        }
    }
}

/// Five Adam steps with the release's betas (0, 0.99) and with (0.9, 0.999), a decaying
/// rate, against the f64 update of torch.optim.Adam's formula.
#[test]
fn adam_matches_the_f64_update() {
    let Some(g) = gpu() else { return };
    let n = 1000;
    for (b1, b2) in [(0.0, 0.99), (0.9, 0.999)] {
        let mut rng = Rng::new(31);
        let p0 = values(&mut rng, n);
        let pb = g.buffer_with("p", &p0);
        let mb = g.buffer("m", 4 * n as u64);
        let vb = g.buffer("v", 4 * n as u64);
        let (mut p, mut m, mut v) = (
            p0.iter().map(|&a| a as f64).collect::<Vec<_>>(),
            vec![0f64; n],
            vec![0f64; n],
        );
        for t in 1..=5u64 {
            // Gradients spanning magnitudes, zeros included (v = 0: the eps branch).
            let grad: Vec<f32> = (0..n)
                .map(|i| {
                    if i % 97 == 0 {
                        0.0
                    } else {
                        rng.range(-1.0, 1.0) as f32 * 10f32.powi((i % 7) as i32 - 4)
                    }
                })
                .collect();
            let gb = g.buffer_with("g", &grad);
            let s = AdamStep {
                beta1: b1,
                beta2: b2,
                eps: 1e-8,
                lr: 1e-3 * (1.0 - 0.1 * t as f64),
                t,
            };
            let step = adam(
                g,
                s,
                n,
                &AdamBuffers {
                    grad: &gb,
                    param: &pb,
                    off: 0,
                    m: &mb,
                    v: &vb,
                },
            )
            .unwrap();
            g.submit(&[step]);
            for i in 0..n {
                let gi = grad[i] as f64;
                m[i] = b1 * m[i] + (1.0 - b1) * gi;
                v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                let denom = v[i].sqrt() / (1.0 - b2.powi(t as i32)).sqrt() + 1e-8;
                p[i] -= s.lr / (1.0 - b1.powi(t as i32)) * m[i] / denom;
            }
        }
        let got = g.read_f32(&pb, n).unwrap();
        let want: Vec<f32> = p.iter().map(|&a| a as f32).collect();
        let (d, i, w, gv) = max_diff(&want, &got);
        assert!(
            d <= ADAM_TOL * (w.abs() as f64).max(1.0),
            "betas ({b1}, {b2}): parameter {i} after 5 steps: expected {w}, actual {gv}"
        );
        eprintln!("Adam betas ({b1}, {b2}): max difference {d:e} after 5 steps");
    }
    let dummy = g.buffer("x", 4);
    let b = AdamBuffers {
        grad: &dummy,
        param: &dummy,
        off: 0,
        m: &dummy,
        v: &dummy,
    };
    let s = AdamStep {
        beta1: 0.0,
        beta2: 0.99,
        eps: 1e-8,
        lr: 1e-4,
        t: 0,
    };
    assert!(adam(g, s, 1, &b).is_err(), "step 0 is an error");
    assert!(
        adam(g, AdamStep { t: 1, ..s }, 2, &b).is_err(),
        "a short buffer is an error"
    );
}

/// Layers the kernels do not handle, and scratch too small, are errors before anything runs.
#[test]
fn bad_layers_and_short_scratch_are_errors() {
    let Some(g) = gpu() else { return };
    let l = LAYERS[0];
    let bench = Bench::new(g, Tuning::default(), l);
    let ops = bench.ops(g);
    let buf = g.buffer("b", 4 * 10_000);
    let tiny = g.buffer("tiny", 4);
    let base = ConvGrad {
        cin: l.cin,
        cout: l.cout,
        h: l.h,
        w: l.w,
        k: l.k,
        input: At::new(&buf),
        weight: &buf,
        grad_out: At::new(&buf),
        grad_input: None,
        grad_weight: At::new(&buf),
        grad_bias: None,
        accumulate: false,
    };
    let scratch = g.buffer("s", 4 * 100_000);
    let five = ConvGrad { k: 5, ..base };
    assert!(matches!(
        conv_backward(&ops, &five, &scratch, &scratch),
        Err(GpuError::Unsupported(_))
    ));
    let empty = ConvGrad { h: 0, ..base };
    assert!(conv_backward(&ops, &empty, &scratch, &scratch).is_err());
    let short = conv_backward(&ops, &base, &tiny, &scratch);
    assert!(matches!(short, Err(GpuError::Device(m)) if m.contains("rotated weight")));
    let short = conv_backward(&ops, &base, &scratch, &tiny);
    assert!(matches!(short, Err(GpuError::Device(m)) if m.contains("partial sum")));
}

/// [`GpuAdam`] over three parameters, two sharing a buffer at offsets, with their own rates
/// and a decaying schedule, against the f64 update over four steps; the values around the
/// parameters in the shared buffer stay untouched.
#[test]
fn gpu_adam_updates_each_parameter_at_its_offset_and_rate() {
    let Some(g) = gpu() else { return };
    let (b1, b2, eps) = (0.0, 0.99, 1e-8);
    let mut rng = Rng::new(33);
    // Buffer 0: [pad 3][p0: 10][pad 2][p1: 7][pad 1]; buffer 1: its gradients at the same
    // places; buffer 2: p2 (20) and buffer 3 its gradient.
    let shared = values(&mut rng, 23);
    let own = values(&mut rng, 20);
    let buffers = vec![
        g.buffer_with("shared", &shared),
        g.buffer("shared grads", 4 * 23),
        g.buffer_with("own", &own),
        g.buffer("own grad", 4 * 20),
    ];
    let params = vec![
        Param {
            key: "a.style_mlp.1.weight".into(),
            value: 0,
            grad: 1,
            offset: 3,
            len: 10,
        },
        Param {
            key: "b.bias".into(),
            value: 0,
            grad: 1,
            offset: 15,
            len: 7,
        },
        Param {
            key: "c.weight".into(),
            value: 2,
            grad: 3,
            offset: 0,
            len: 20,
        },
    ];
    let lr0 = |k: &str| if k.contains("style_mlp") { 1e-4 } else { 1e-3 };
    let mut opt = GpuAdam::new(g, (&buffers, &params), (b1, b2, eps), &lr0).unwrap();
    let mut want: Vec<Vec<f64>> = vec![
        shared.iter().map(|&v| v as f64).collect(),
        own.iter().map(|&v| v as f64).collect(),
    ];
    let mut moments: Vec<(Vec<f64>, Vec<f64>)> = params
        .iter()
        .map(|p| (vec![0.0; p.len], vec![0.0; p.len]))
        .collect();
    for t in 1..=4u64 {
        let factor = 1.0 - 0.2 * (t - 1) as f64;
        let gs = values(&mut rng, 23);
        let go = values(&mut rng, 20);
        g.queue
            .write_buffer(&buffers[1], 0, bytemuck::cast_slice(&gs));
        g.queue
            .write_buffer(&buffers[3], 0, bytemuck::cast_slice(&go));
        g.submit(opt.step(g, factor).unwrap());
        for (p, (m, v)) in params.iter().zip(&mut moments) {
            let (vals, grads) = if p.value == 0 {
                (&mut want[0], &gs)
            } else {
                (&mut want[1], &go)
            };
            let lr = lr0(&p.key) * factor;
            for i in 0..p.len {
                let gi = grads[p.offset + i] as f64;
                m[i] = b1 * m[i] + (1.0 - b1) * gi;
                v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                let denom = v[i].sqrt() / (1.0 - b2.powi(t as i32)).sqrt() + eps;
                vals[p.offset + i] -= lr / (1.0 - b1.powi(t as i32)) * m[i] / denom;
            }
        }
    }
    for (bi, w) in [(0usize, &want[0]), (2, &want[1])] {
        let got = g.read_f32(&buffers[bi], w.len()).unwrap();
        let w32: Vec<f32> = w.iter().map(|&v| v as f32).collect();
        assert_close(
            &format!("buffer {bi} after 4 Adam steps"),
            &w32,
            &got,
            ADAM_TOL,
        );
    }
    let bad = vec![Param {
        key: "x".into(),
        value: 9,
        grad: 1,
        offset: 0,
        len: 1,
    }];
    assert!(GpuAdam::new(g, (&buffers, &bad), (b1, b2, eps), &lr0).is_err());
}
