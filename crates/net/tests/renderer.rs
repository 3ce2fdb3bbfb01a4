//! The neural renderer (StyleUNet, `upsampler.*`) against the PyTorch reference goldens of the
//! `tiny` preset (`tools/reference/net_reference.py`), plus its own invariants: the key set,
//! batching, the two exact ways of running a modulated convolution, the factor-two resizes and
//! their gradients.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device, Shape, Tensor, Var};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder};
use gagavatar_net::style_unet::{
    downsample2x, upsample2x, ModulatedConv, ModulationPath, Noise, StyleUNet,
};
use gagavatar_net::ModelConfig;
use gagavatar_ops::{resize, ResizeMode};

mod common;
use common::{assert_close, get, load, to_vec_f64};

/// The fine image after ~40 f32 convolutions whose sums PyTorch orders differently (GEMM
/// blocking, the fused grouped conv of the modulated layers), then a sigmoid (slope <= 1/4):
/// about 1e-6 relative drift per layer on values in [0, 1].
const FINE_TOL: f32 = 1e-4;
/// The f64 forward against the golden, which the reference computed in f64 and stored as f32:
/// the stored value's rounding dominates, at most half an f32 ulp below 1 (2^-25 = 2.98e-8, the
/// fine image is a sigmoid); the f64 arithmetic adds ~1e-15 (measured 2.980e-8).
const F64_FINE_TOL: f64 = 3.0e-8;
/// Same computation, same kernels, batch 2 vs batch 1: only the convolution's batching can
/// change the summation order.
const BATCH_TOL: f32 = 1e-6;
/// Inference (fixed weights) against the tracked graph: the inference path scales a kept
/// Winograd transform of the weight (`G (s g) G^T` as `s (G g G^T)`) where the graph transforms
/// the scaled weight, a different rounding inside Winograd's ~10x error amplification
/// (measured 1.7e-6 on the fine image).
const INFERENCE_TOL: f32 = 1e-5;
/// The two modulation paths in f32 (weight scaled vs input and output scaled): rounding of a
/// few hundred products per output, relative to outputs of order 1.
const PATH_TOL_F32: f32 = 2e-5;
/// The same in f64, and against a literal f64 transcription of the per-sample formula.
const PATH_TOL_F64: f64 = 1e-12;
/// Sparse-tap resize vs the interpolation-matrix resize in f64: a few roundings per output.
const RESIZE_TOL: f64 = 1e-13;
/// Central finite differences in f64 along unit directions. The loss (~3e3) carries ~1e-11 of
/// rounding noise and is piecewise smooth (leaky-ReLU kinks): a step crossing kinks errs by
/// O(step), a small step amplifies the noise by 1/step. The input direction is smooth enough for
/// a 1e-3 step (measured 1e-8 relative error); a weight direction moves the latent or whole
/// feature maps and crosses kinks up to ~1e-4, so it takes 1e-5 (measured <= 1e-6).
const INPUT_STEP: f64 = 1e-3;
const WEIGHT_STEP: f64 = 1e-5;
const GRAD_REL_TOL: f64 = 1e-5;

/// Seeded weights of realistic magnitude for whatever the modules ask for, recording every
/// request (name, shape). With `vars`, the tensors are trainable variables.
#[derive(Default)]
struct RandomWeights {
    seed: u64,
    vars: bool,
    seen: Mutex<Vec<(String, Vec<usize>, Tensor)>>,
}

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Mean and standard deviation of the random weight `name` with `shape`.
fn init_rule(name: &str, shape: &[usize]) -> (f64, f64) {
    if name.contains("noises.noise") || name.ends_with("constant_input.weight") {
        (0.0, 1.0)
    } else if name.ends_with("modulation.bias") {
        (1.0, 0.1)
    } else if shape == [1] {
        // noise injection strength
        (0.3, 0.1)
    } else if name.ends_with("bias") {
        (0.0, 0.05)
    } else {
        let fan_in: usize = if shape.len() == 5 {
            shape[2..].iter().product()
        } else {
            shape[1..].iter().product()
        };
        (0.0, (1.0 / fan_in.max(1) as f64).sqrt())
    }
}

fn random_tensor(
    seed: u64,
    name: &str,
    shape: &[usize],
    dtype: DType,
) -> candle_core::Result<Tensor> {
    let key = name
        .bytes()
        .fold(splitmix(seed), |h, b| splitmix(h ^ b as u64));
    let (mean, std) = init_rule(name, shape);
    let n: usize = shape.iter().product();
    // Uniform with the wanted standard deviation.
    let v: Vec<f64> = (0..n as u64)
        .map(|i| {
            let u = (splitmix(key ^ i.wrapping_mul(0x2545_F491_4F6C_DD1D)) >> 11) as f64
                / (1u64 << 53) as f64;
            mean + std * 3f64.sqrt() * (2.0 * u - 1.0)
        })
        .collect();
    Tensor::from_vec(v, shape, &Device::Cpu)?.to_dtype(dtype)
}

/// The VarBuilder owns its backend; the test keeps a second handle to read the requests.
struct Shared(Arc<RandomWeights>);

impl SimpleBackend for Shared {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _h: Init,
        dtype: DType,
        _dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let mut t = random_tensor(self.0.seed, name, s.dims(), dtype)?;
        if self.0.vars {
            t = Var::from_tensor(&t)?.as_tensor().clone();
        }
        self.0
            .seen
            .lock()
            .map_err(|_| candle_core::Error::msg("poisoned"))?
            .push((name.to_string(), s.dims().to_vec(), t.clone()));
        Ok(t)
    }
    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("no shape for {name}")
    }
    fn contains_tensor(&self, _: &str) -> bool {
        true
    }
}

fn random_renderer(
    cfg: &ModelConfig,
    dtype: DType,
    seed: u64,
    vars: bool,
) -> (StyleUNet, Arc<RandomWeights>) {
    let w = Arc::new(RandomWeights {
        seed,
        vars,
        ..Default::default()
    });
    let vb = VarBuilder::from_backend(Box::new(Shared(w.clone())), dtype, Device::Cpu);
    let net = StyleUNet::new(cfg, vb.pp("upsampler")).expect("renderer");
    (net, w)
}

fn requested_keys(w: &RandomWeights) -> BTreeMap<String, Vec<usize>> {
    let seen = w.seen.lock().expect("lock");
    let mut out = BTreeMap::new();
    for (k, s, _) in seen.iter() {
        if let Some(prev) = out.insert(k.clone(), s.clone()) {
            assert_eq!(&prev, s, "{k} requested with two shapes");
        }
    }
    out
}

fn random_input(shape: &[usize], seed: u64, dtype: DType) -> Tensor {
    // Values in [0, 1] like a splatted image.
    let t = random_tensor(seed, "input", shape, DType::F64).expect("input");
    ((t / 2.0).expect("scale") + 0.5)
        .expect("shift")
        .to_dtype(dtype)
        .expect("dtype")
}

fn golden_renderer(dtype: DType) -> StyleUNet {
    let vb = VarBuilder::from_tensors(load("tiny_weights.safetensors"), dtype, &Device::Cpu);
    StyleUNet::new(&ModelConfig::tiny(), vb.pp("upsampler")).expect("tiny renderer")
}

#[test]
fn fine_image_matches_the_reference_with_fixed_noise() {
    let io = load("tiny_io.safetensors");
    let net = golden_renderer(DType::F32);
    let fine = net
        .forward(get(&io, "coarse"), Noise::Fixed)
        .expect("forward");
    assert_close("fine (f32)", &fine, get(&io, "fine"), FINE_TOL as f64);
}

#[test]
fn f64_forward_matches_the_reference() {
    let io = load("tiny_io.safetensors");
    let net = golden_renderer(DType::F64);
    let coarse = get(&io, "coarse").to_dtype(DType::F64).expect("f64");
    let fine = net.forward(&coarse, Noise::Fixed).expect("forward");
    assert_eq!(fine.dtype(), DType::F64);
    assert_close("fine (f64)", &fine, get(&io, "fine"), F64_FINE_TOL);
}

#[test]
fn golden_weights_have_exactly_the_requested_keys() {
    let (_, w) = random_renderer(&ModelConfig::tiny(), DType::F32, 1, false);
    let ours = requested_keys(&w);
    let golden = load("tiny_weights.safetensors");
    let theirs: BTreeMap<String, Vec<usize>> = golden
        .iter()
        .filter(|(k, _)| k.starts_with("upsampler."))
        .map(|(k, t)| (k.clone(), t.dims().to_vec()))
        .collect();
    for (k, s) in &theirs {
        assert_eq!(
            ours.get(k),
            Some(s),
            "golden key {k}: ours {:?}",
            ours.get(k)
        );
    }
    for k in ours.keys() {
        assert!(
            theirs.contains_key(k),
            "we ask for {k}, the golden lacks it"
        );
    }
}

#[test]
fn release_keys_are_the_checkpoint_upsampler_keys() {
    let tsv = include_str!("data/official_state_dict.tsv");
    let mut official = BTreeMap::new();
    for line in tsv.lines().filter(|l| l.starts_with("upsampler.")) {
        let mut cols = line.split('\t');
        let (Some(name), Some(shape)) = (cols.next(), cols.next()) else {
            panic!("bad tsv line {line:?}");
        };
        let dims: Vec<usize> = shape
            .trim_matches(|c| c == '(' || c == ')')
            .split(',')
            .filter(|s| !s.trim().is_empty())
            .map(|s| s.trim().parse::<usize>().expect("dim"))
            .collect();
        official.insert(name.to_string(), dims);
    }
    assert!(
        official.len() > 200,
        "tsv has {} upsampler keys",
        official.len()
    );
    let (_, w) = random_renderer(&ModelConfig::release(), DType::F32, 1, false);
    let ours = requested_keys(&w);
    for (k, s) in &official {
        assert_eq!(
            ours.get(k),
            Some(s),
            "checkpoint key {k}: ours {:?}",
            ours.get(k)
        );
    }
    for k in ours.keys() {
        assert!(
            official.contains_key(k),
            "we ask for {k}, the checkpoint lacks it"
        );
    }
}

#[test]
fn fresh_noise_gives_a_different_finite_image() {
    let cfg = ModelConfig::tiny();
    let (net, _) = random_renderer(&cfg, DType::F32, 7, false);
    let x = random_input(&[1, 32, 64, 64], 3, DType::F32);
    let fixed = net.forward(&x, Noise::Fixed).expect("fixed");
    let again = net.forward(&x, Noise::Fixed).expect("fixed again");
    assert_close("fixed noise is deterministic", &again, &fixed, 0.0);
    let a = net.forward(&x, Noise::Fresh).expect("fresh");
    let b = net.forward(&x, Noise::Fresh).expect("fresh again");
    for (what, img) in [("fresh", &a), ("fresh again", &b)] {
        assert_eq!(img.dims(), &[1, 3, 64, 64]);
        let v = to_vec_f64(img);
        assert!(
            v.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x)),
            "{what}: values outside [0, 1]"
        );
        let d = to_vec_f64(&(img - &fixed).expect("diff").abs().expect("abs"))
            .into_iter()
            .fold(0.0, gagavatar_testkit::max_or_nan);
        assert!(d > 1e-3, "{what} noise changes the image by only {d:.2e}");
    }
    let d = to_vec_f64(&(&a - &b).expect("diff").abs().expect("abs"))
        .into_iter()
        .fold(0.0, gagavatar_testkit::max_or_nan);
    assert!(d > 1e-3, "two fresh draws differ by only {d:.2e}");
    // Like the release, fresh noise is drawn per sample: two copies of one input differ.
    let pair = net
        .forward(&Tensor::cat(&[&x, &x], 0).expect("cat"), Noise::Fresh)
        .expect("fresh pair");
    let d = to_vec_f64(
        &(pair.narrow(0, 0, 1).expect("0") - pair.narrow(0, 1, 1).expect("1"))
            .expect("diff")
            .abs()
            .expect("abs"),
    )
    .into_iter()
    .fold(0.0, gagavatar_testkit::max_or_nan);
    assert!(
        d > 1e-3,
        "the samples of a batch share their noise (differ by {d:.2e})"
    );
}

#[test]
fn wrong_inputs_are_errors() {
    let cfg = ModelConfig::tiny();
    let (net, _) = random_renderer(&cfg, DType::F32, 7, false);
    let dev = Device::Cpu;
    let bad = [
        Tensor::zeros((1, 31, 64, 64), DType::F32, &dev),
        Tensor::zeros((1, 32, 32, 32), DType::F32, &dev),
        Tensor::zeros((1, 32, 64, 32), DType::F32, &dev),
        Tensor::zeros((32, 64, 64), DType::F32, &dev),
        Tensor::zeros((1, 32, 64, 64), DType::U8, &dev),
    ];
    for x in bad {
        let x = x.expect("zeros");
        let r = net.forward(&x, Noise::Fixed);
        assert!(r.is_err(), "{:?} {:?} accepted", x.dims(), x.dtype());
    }
    let ok = net
        .forward(
            &Tensor::zeros((1, 32, 64, 64), DType::F32, &dev).expect("zeros"),
            Noise::Fixed,
        )
        .expect("right shape");
    assert_eq!(ok.dims(), &[1, 3, 64, 64]);
}

#[test]
fn a_batch_of_two_equals_two_single_calls() {
    let cfg = ModelConfig::tiny();
    let (net, _) = random_renderer(&cfg, DType::F32, 11, false);
    let x0 = random_input(&[1, 32, 64, 64], 1, DType::F32);
    let x1 = random_input(&[1, 32, 64, 64], 2, DType::F32);
    let both = net
        .forward(&Tensor::cat(&[&x0, &x1], 0).expect("cat"), Noise::Fixed)
        .expect("batch");
    assert_eq!(both.dims(), &[2, 3, 64, 64]);
    for (i, x) in [x0, x1].iter().enumerate() {
        let single = net.forward(x, Noise::Fixed).expect("single");
        let part = both.narrow(0, i, 1).expect("narrow");
        assert_close(&format!("batch item {i}"), &part, &single, BATCH_TOL as f64);
    }
    // The two images differ, so the comparison above could fail.
    let d = to_vec_f64(
        &(both.narrow(0, 0, 1).unwrap() - both.narrow(0, 1, 1).unwrap())
            .unwrap()
            .abs()
            .unwrap(),
    )
    .into_iter()
    .fold(0.0, gagavatar_testkit::max_or_nan);
    assert!(d > 1e-3, "batch items differ by only {d:.2e}");
}

/// Without gradient tracking the element-wise epilogues run in place; with trainable weights
/// they are ordinary candle expressions. Both must compute the same image.
#[test]
fn in_place_inference_equals_the_tracked_graph() {
    let cfg = ModelConfig::tiny();
    let (plain, _) = random_renderer(&cfg, DType::F32, 19, false);
    let (tracked, _) = random_renderer(&cfg, DType::F32, 19, true);
    let x = random_input(&[2, 32, 64, 64], 4, DType::F32);
    let a = plain.forward(&x, Noise::Fixed).expect("in place");
    let b = tracked.forward(&x, Noise::Fixed).expect("tracked");
    assert_close("in-place vs tracked", &a, &b, INFERENCE_TOL as f64);
    // The input survives the in-place epilogues.
    assert_close(
        "input untouched",
        &x,
        &random_input(&[2, 32, 64, 64], 4, DType::F32),
        0.0,
    );
}

/// A modulated convolution written literally from the formula, per sample, in f64.
fn modconv_reference(
    x: &Tensor,
    weight: &Tensor, // [cout, cin, k, k]
    style: &Tensor,  // [B, cin]
    demodulate: bool,
    gain: f64,
) -> Tensor {
    let (b, _, _, _) = x.dims4().unwrap();
    let (cout, cin, k, _) = weight.dims4().unwrap();
    let mut outs = Vec::new();
    for i in 0..b {
        let s = style
            .narrow(0, i, 1)
            .unwrap()
            .reshape((1, cin, 1, 1))
            .unwrap();
        let mut w = weight.broadcast_mul(&s).unwrap();
        if demodulate {
            let d = ((w.sqr().unwrap().sum_keepdim((1, 2, 3)).unwrap() + 1e-8).unwrap())
                .sqrt()
                .unwrap()
                .recip()
                .unwrap();
            w = w.broadcast_mul(&d).unwrap();
        }
        let y = x
            .narrow(0, i, 1)
            .unwrap()
            .conv2d(&w, k / 2, 1, 1, 1)
            .unwrap();
        outs.push((y * gain).unwrap());
    }
    assert_eq!(outs[0].dim(1).unwrap(), cout);
    Tensor::cat(&outs, 0).unwrap()
}

#[test]
fn both_modulation_paths_equal_the_per_sample_formula() {
    let (cin, cout, sd) = (6, 5, 4);
    for (k, demodulate, gain) in [(3, true, std::f64::consts::SQRT_2), (1, false, 1.0)] {
        for dtype in [DType::F64, DType::F32] {
            let w = Arc::new(RandomWeights {
                seed: 5,
                ..Default::default()
            });
            let vb = VarBuilder::from_backend(Box::new(Shared(w.clone())), dtype, Device::Cpu);
            let conv = ModulatedConv::new(vb.pp("m"), cin, cout, k, sd, demodulate).unwrap();
            let tensors: HashMap<String, Tensor> = w
                .seen
                .lock()
                .unwrap()
                .iter()
                .map(|(n, _, t)| (n.clone(), t.to_dtype(DType::F64).unwrap()))
                .collect();
            let x = random_input(&[2, cin, 7, 9], 9, dtype);
            let latent = random_tensor(4, "latent", &[2, sd], dtype).unwrap();
            // Reference in f64 from the same numbers.
            let style = latent
                .to_dtype(DType::F64)
                .unwrap()
                .matmul(&tensors["m.modulation.weight"].t().unwrap())
                .unwrap()
                .broadcast_add(&tensors["m.modulation.bias"])
                .unwrap();
            let weight = tensors["m.weight"].reshape((cout, cin, k, k)).unwrap();
            let want = modconv_reference(
                &x.to_dtype(DType::F64).unwrap(),
                &weight,
                &style,
                demodulate,
                gain,
            );
            let tol = if dtype == DType::F64 {
                PATH_TOL_F64
            } else {
                PATH_TOL_F32 as f64
            };
            for path in [
                ModulationPath::ModulateWeight,
                ModulationPath::ScaleInput,
                ModulationPath::Auto,
            ] {
                let got = conv.forward_with(&x, &latent, gain, None, path).unwrap();
                assert_close(
                    &format!("k={k} demod={demodulate} {dtype:?} {path:?}"),
                    &got,
                    &want,
                    tol,
                );
            }
        }
    }
}

#[test]
fn factor_two_resizes_match_the_matrix_resize_and_its_gradient() {
    for (h, w) in [(5, 7), (1, 4), (6, 8)] {
        let x = Var::from_tensor(&random_input(&[2, 3, h, w], 21, DType::F64)).unwrap();
        let up = upsample2x(x.as_tensor()).unwrap();
        let up_ref = resize(x.as_tensor(), 2 * h, 2 * w, ResizeMode::HalfPixel).unwrap();
        assert_close(&format!("upsample2x {h}x{w}"), &up, &up_ref, RESIZE_TOL);
        // Gradient of a random linear functional: the backward is the transpose.
        let r = random_input(&[2, 3, 2 * h, 2 * w], 22, DType::F64);
        let g = (up * &r).unwrap().sum_all().unwrap().backward().unwrap();
        let g_ref = (up_ref * &r)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert_close(
            &format!("upsample2x gradient {h}x{w}"),
            g.get(x.as_tensor()).unwrap(),
            g_ref.get(x.as_tensor()).unwrap(),
            RESIZE_TOL,
        );
        if h % 2 == 0 && w % 2 == 0 {
            let down = downsample2x(x.as_tensor()).unwrap();
            let down_ref = resize(x.as_tensor(), h / 2, w / 2, ResizeMode::HalfPixel).unwrap();
            assert_close(
                &format!("downsample2x {h}x{w}"),
                &down,
                &down_ref,
                RESIZE_TOL,
            );
            let r = random_input(&[2, 3, h / 2, w / 2], 23, DType::F64);
            let g = (down * &r).unwrap().sum_all().unwrap().backward().unwrap();
            let g_ref = (down_ref * &r)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            assert_close(
                &format!("downsample2x gradient {h}x{w}"),
                g.get(x.as_tensor()).unwrap(),
                g_ref.get(x.as_tensor()).unwrap(),
                RESIZE_TOL,
            );
        } else {
            assert!(downsample2x(x.as_tensor()).is_err(), "odd {h}x{w} halved");
        }
    }
}

/// Autograd through the whole renderer (custom resize ops, the demodulation through a trainable
/// weight, SFT) against a central finite difference along a random direction, in f64.
#[test]
fn gradients_match_finite_differences() {
    let cfg = ModelConfig::tiny();
    let (net, w) = random_renderer(&cfg, DType::F64, 13, true);
    let x = Var::from_tensor(&random_input(&[1, 32, 64, 64], 5, DType::F64)).unwrap();
    let r = random_input(&[1, 3, 64, 64], 6, DType::F64);
    let loss = |net: &StyleUNet, x: &Tensor| -> Tensor {
        (net.forward(x, Noise::Fixed).unwrap() * &r)
            .unwrap()
            .sum_all()
            .unwrap()
    };
    let grads = loss(&net, x.as_tensor()).backward().unwrap();
    // Along a unit direction in input space (unit steps cross few leaky-ReLU kinks).
    let dir = random_tensor(8, "direction", &[1, 32, 64, 64], DType::F64).unwrap();
    let dir = (&dir / to_vec_f64(&dir.sqr().unwrap().sum_all().unwrap())[0].sqrt()).unwrap();
    let gx = grads.get(x.as_tensor()).expect("input gradient");
    let analytic = (gx * &dir)
        .unwrap()
        .sum_all()
        .unwrap()
        .to_scalar::<f64>()
        .unwrap();
    let plus = loss(
        &net,
        &(x.as_tensor() + (&dir * INPUT_STEP).unwrap()).unwrap(),
    );
    let minus = loss(
        &net,
        &(x.as_tensor() - (&dir * INPUT_STEP).unwrap()).unwrap(),
    );
    let numeric = ((plus - minus).unwrap().to_scalar::<f64>().unwrap()) / (2.0 * INPUT_STEP);
    let rel = (analytic - numeric).abs() / numeric.abs().max(1e-12);
    eprintln!("input: analytic {analytic:.10e}, numeric {numeric:.10e}, rel {rel:.2e}");
    assert!(
        rel < GRAD_REL_TOL,
        "input: analytic {analytic}, numeric {numeric}"
    );
    // Along directions in a few weights whose gradients take different routes.
    let seen: Vec<(String, Tensor)> = w
        .seen
        .lock()
        .unwrap()
        .iter()
        .map(|(n, _, t)| (n.clone(), t.clone()))
        .collect();
    for name in [
        "upsampler.stylegan_decoder.style_convs.2.modulated_conv.weight",
        "upsampler.stylegan_decoder.style_mlp.1.weight",
        "upsampler.conv_body_down.1.conv1.weight",
        "upsampler.conv_body_up.2.skip.weight",
        "upsampler.condition_shift.3.2.weight",
    ] {
        let t = &seen.iter().find(|(n, _)| n == name).expect(name).1;
        let g = grads
            .get(t)
            .unwrap_or_else(|| panic!("no gradient for {name}"));
        let dir = random_tensor(17, name, t.dims(), DType::F64).unwrap();
        let dir = (&dir / to_vec_f64(&dir.sqr().unwrap().sum_all().unwrap())[0].sqrt()).unwrap();
        let analytic = (g * &dir)
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        // `t` is a variable, so `var` shares its storage with the weight the network holds and
        // `set` perturbs that weight in place.
        let var = Var::from_tensor(t).unwrap();
        let orig = t.copy().unwrap();
        let eval = |sign: f64| -> f64 {
            var.set(&(&orig + (&dir * (sign * WEIGHT_STEP)).unwrap()).unwrap())
                .unwrap();
            loss(&net, x.as_tensor()).to_scalar::<f64>().unwrap()
        };
        let numeric = (eval(1.0) - eval(-1.0)) / (2.0 * WEIGHT_STEP);
        var.set(&orig).unwrap();
        let rel = (analytic - numeric).abs() / numeric.abs().max(1e-12);
        eprintln!("{name}: analytic {analytic:.10e}, numeric {numeric:.10e}, rel {rel:.2e}");
        assert!(
            rel < GRAD_REL_TOL,
            "{name}: analytic {analytic}, numeric {numeric}"
        );
    }
}
