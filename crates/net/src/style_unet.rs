//! The neural renderer (spec section 8, keys `upsampler.*`): a StyleUNet that maps the splatted
//! `color_dim`-channel image to RGB. A U-Net encodes the input into a StyleGAN2 latent and into
//! per-resolution SFT scale/shift maps; a StyleGAN2 decoder with spatial feature transforms
//! generates the image; a final sigmoid maps it to [0, 1].
//!
//! Efficiency choices (all exact in real arithmetic, so they change results only by rounding):
//! - An up ResBlock applies its 1x1 skip before the x2 resize instead of after: both are linear,
//!   one mixes channels and the other pixels, so they commute, and at the low resolution the
//!   1x1 does a quarter of the work.
//! - A modulated convolution scales either the weight (per sample) or the input and output
//!   (one batched convolution with the shared weight), whichever touches fewer numbers; see
//!   [`ModulatedConv`].
//! - Without gradient tracking the element-wise epilogues (leaky ReLU, noise injection, SFT,
//!   residual sums) overwrite freshly computed tensors in place (module `fused`): at 512x512
//!   each avoided allocation is tens of MB of page faults and a memory pass.

use std::f64::consts::SQRT_2;

use candle_core::{bail, DType, Module, Result, Tensor, D};
use candle_nn::{Linear, VarBuilder};
use gagavatar_ops::conv::{conv2d_fixed, Bf16Conv, WinogradCache};
use gagavatar_ops::epilogue;
use gagavatar_ops::{resize, Conv2dSpec, Precision, ResizeMode};

use crate::config::ModelConfig;
use crate::layers::{fixed, Conv2d};

/// Added to the squared norms in the style-code normalisation and the demodulation.
const EPS: f64 = 1e-8;

/// Named weights as [`StyleUNet::named_weights`] lists them: `prefix.weight`, `prefix.bias`.
fn push_conv(out: &mut Vec<(String, Tensor)>, prefix: &str, c: &Conv2d) {
    out.push((format!("{prefix}.weight"), c.weight.clone()));
    if let Some(b) = &c.bias {
        out.push((format!("{prefix}.bias"), b.clone()));
    }
}

fn push_linear(out: &mut Vec<(String, Tensor)>, prefix: &str, l: &Linear) {
    out.push((format!("{prefix}.weight"), l.weight().clone()));
    if let Some(b) = l.bias() {
        out.push((format!("{prefix}.bias"), b.clone()));
    }
}

/// Which noise the decoder's StyleConvs inject.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Noise {
    /// The checkpoint's buffers `stylegan_decoder.noises.noise{i}`: deterministic, so video
    /// frames do not flicker.
    #[default]
    Fixed,
    /// Fresh N(0, 1) noise per call and per sample, as the release does at inference (and in
    /// training), from candle's own unseeded generator.
    Fresh,
    /// N(0, 1) noise like `Fresh`, but a function of the seed: the same seed gives the same
    /// buffers, so a training run that derives the seed from its step reproduces itself when
    /// resumed. Buffer `i` comes from its own stream of the seed, drawn sample after sample, so
    /// sample 0 gets the same noise whatever the batch size.
    Seeded(u64),
    /// `Seeded(seed)`'s noise of samples `first..` of the step's batch: a data-parallel rank
    /// holding that part of the batch gets the noise one process holding all of it would.
    SeededFrom { seed: u64, first: usize },
}

/// N(0, 1) noise `[batch, 1, r, r]` for buffer `index` from `seed` (see [`Noise::Seeded`]).
pub fn seeded_noise(
    seed: u64,
    index: usize,
    batch: usize,
    r: usize,
    like: &Tensor,
) -> Result<Tensor> {
    seeded_noise_from(seed, index, 0, batch, r, like)
}

/// Samples `first..first + batch` of [`seeded_noise`]'s stream (see [`Noise::SeededFrom`]).
pub fn seeded_noise_from(
    seed: u64,
    index: usize,
    first: usize,
    batch: usize,
    r: usize,
    like: &Tensor,
) -> Result<Tensor> {
    // SplitMix64 finaliser of (seed, index): independent streams per buffer.
    let mut z = seed ^ (index as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    let mut rng = gagavatar_splat::testscene::Rng::new(z ^ (z >> 31));
    for _ in 0..first * r * r {
        rng.normal();
    }
    let v: Vec<f64> = (0..batch * r * r).map(|_| rng.normal()).collect();
    Tensor::from_vec(v, (batch, 1, r, r), like.device())?.to_dtype(like.dtype())
}

/// A ResBlock of the U-Net: `conv1` 3x3 (in -> in), leaky ReLU, bilinear resize (x0.5 down,
/// x2 up), `conv2` 3x3 (in -> out), leaky ReLU, plus `skip` 1x1 (no bias) of the resized input.
#[derive(Debug, Clone)]
pub struct ResBlock {
    conv1: Conv2d,
    conv2: Conv2d,
    skip: Conv2d,
    up: bool,
}

impl ResBlock {
    pub fn new(vb: VarBuilder, cin: usize, cout: usize, up: bool) -> Result<Self> {
        Ok(Self {
            conv1: Conv2d::k3(vb.pp("conv1"), cin, cin)?,
            conv2: Conv2d::k3(vb.pp("conv2"), cin, cout)?,
            skip: Conv2d::new(vb.pp("skip"), cin, cout, 1, 1, 0, false)?,
            up,
        })
    }

    fn named_weights(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        push_conv(out, &format!("{prefix}.conv1"), &self.conv1);
        push_conv(out, &format!("{prefix}.conv2"), &self.conv2);
        push_conv(out, &format!("{prefix}.skip"), &self.skip);
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.conv1.set_precision(precision)?;
        self.conv2.set_precision(precision)?;
        self.skip.set_precision(precision)
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = epilogue::lrelu(self.conv1.forward(x)?)?;
        if self.up {
            let h = epilogue::lrelu(self.conv2.forward(&upsample2x(&h)?)?)?;
            // skip(resize(x)) == resize(skip(x)); the 1x1 is 4x cheaper before the upsampling.
            let s = upsample2x(&self.skip.forward(x)?)?;
            epilogue::add(h, &s)
        } else {
            let h = epilogue::lrelu(self.conv2.forward(&downsample2x(&h)?)?)?;
            let s = self.skip.forward(&downsample2x(x)?)?;
            epilogue::add(h, &s)
        }
    }
}

/// `condition_scale.k` / `condition_shift.k`: 3x3 conv (ch -> ch), leaky ReLU, 3x3 conv
/// (ch -> decoder channels); keys `0.*` and `2.*` (index 1 is the activation).
#[derive(Debug, Clone)]
pub struct ConditionBranch {
    conv0: Conv2d,
    conv2: Conv2d,
}

impl ConditionBranch {
    pub fn new(vb: VarBuilder, ch: usize, out: usize) -> Result<Self> {
        Ok(Self {
            conv0: Conv2d::k3(vb.pp("0"), ch, ch)?,
            conv2: Conv2d::k3(vb.pp("2"), ch, out)?,
        })
    }

    fn named_weights(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        push_conv(out, &format!("{prefix}.0"), &self.conv0);
        push_conv(out, &format!("{prefix}.2"), &self.conv2);
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.conv0.set_precision(precision)?;
        self.conv2.set_precision(precision)
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.conv2
            .forward(&epilogue::lrelu(self.conv0.forward(x)?)?)
    }
}

/// StyleGAN2's modulated convolution (no bias of its own): `style = modulation(latent)`,
/// `w = weight * style` per sample over the input channels, optionally demodulated by
/// `rsqrt(sum over in, kh, kw of w^2 + 1e-8)` per output channel, padding `k / 2`.
///
/// Two exact ways to run it, picked per call by which touches fewer numbers:
/// - weight modulation: build each sample's weight `weight * (d[o] s[i])` and run an ordinary
///   convolution per sample (cheap when the weight is small and the image large, e.g. 512x512);
/// - input scaling: `conv(x * s[i], weight) * d[o]`, one batched convolution with the shared
///   weight (cheap at low resolutions, where the 512x512x3x3 weights dominate). The per-sample
///   weight is a rank-one rescaling of the shared one, so the two agree up to rounding.
///
/// The demodulation norms use `sum_i s[i]^2 E[o, i]` with `E = sum over kh, kw of weight^2`,
/// which equals the sum over the modulated weight without building it; `E` is computed once at
/// load time unless the weight is a trainable variable (then it is recomputed each call so the
/// gradient flows through it).
#[derive(Debug, Clone)]
pub struct ModulatedConv {
    weight: Tensor,
    modulation: Linear,
    demodulate: bool,
    kernel_energy: Option<Tensor>,
    cin: usize,
    cout: usize,
    k: usize,
    /// Under `Precision::Bf16`: the shared weight packed for the input-scaling path (the
    /// weight-modulation path packs each sample's weight per call).
    bf16: Option<Bf16Conv>,
    /// The shared weight's Winograd transform (both paths scale it per image, see
    /// `conv2d_fixed`).
    wino: WinogradCache,
}

/// How [`ModulatedConv`] applies the style (see there); `Auto` picks the cheaper.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModulationPath {
    Auto,
    ModulateWeight,
    ScaleInput,
}

impl ModulatedConv {
    /// Loads `weight` [1, cout, cin, k, k] and `modulation.{weight, bias}` [cin, style_dim], [cin].
    pub fn new(
        vb: VarBuilder,
        cin: usize,
        cout: usize,
        k: usize,
        style_dim: usize,
        demodulate: bool,
    ) -> Result<Self> {
        let raw = vb.get((1, cout, cin, k, k), "weight")?;
        let trainable = raw.is_variable();
        let weight = raw.reshape((cout, cin, k, k))?;
        let modulation = candle_nn::linear(style_dim, cin, vb.pp("modulation"))?;
        let kernel_energy = if demodulate && !trainable {
            Some(Self::energy(&weight)?)
        } else {
            None
        };
        Ok(Self {
            weight,
            modulation,
            demodulate,
            kernel_energy,
            cin,
            cout,
            k,
            bf16: None,
            wino: WinogradCache::default(),
        })
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.bf16 = match precision {
            Precision::F32 => None,
            Precision::Bf16 => {
                fixed(&self.weight)?;
                Some(Bf16Conv::new(&self.weight, None, self.spec())?)
            }
        };
        Ok(())
    }

    fn spec(&self) -> Conv2dSpec {
        Conv2dSpec {
            stride: 1,
            padding: self.k / 2,
        }
    }

    fn named_weights(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        out.push((format!("{prefix}.weight"), self.weight.clone()));
        push_linear(out, &format!("{prefix}.modulation"), &self.modulation);
    }

    fn energy(weight: &Tensor) -> Result<Tensor> {
        weight.sqr()?.sum((2, 3))
    }

    /// `x` [B, cin, H, W], `latent` [B, style_dim] -> `gain * modconv(x) + bias` [B, cout, H, W];
    /// `bias` [cout]. Folding the gain and bias in here saves passes over the output.
    pub fn forward(
        &self,
        x: &Tensor,
        latent: &Tensor,
        gain: f64,
        bias: Option<&Tensor>,
    ) -> Result<Tensor> {
        self.forward_with(x, latent, gain, bias, ModulationPath::Auto)
    }

    /// [`Self::forward`] with an explicit choice of path (both are exact; for tests and timing).
    pub fn forward_with(
        &self,
        x: &Tensor,
        latent: &Tensor,
        gain: f64,
        bias: Option<&Tensor>,
        path: ModulationPath,
    ) -> Result<Tensor> {
        let (b, cin, h, w) = x.dims4()?;
        if cin != self.cin {
            bail!(
                "modulated conv expects {} input channels, got {cin}",
                self.cin
            );
        }
        let (lb, _) = latent.dims2()?;
        if lb != b {
            bail!("modulated conv: {b} images but {lb} latents");
        }
        // [B, cin]
        let style = self.modulation.forward(latent)?;
        // Per-sample output-channel factor [B, cout]: demodulation times the gain.
        let factor = if self.demodulate {
            let energy = match &self.kernel_energy {
                Some(e) => e.clone(),
                None => Self::energy(&self.weight)?,
            };
            let norm2 = (style.sqr()?.matmul(&energy.t()?)? + EPS)?;
            Some((norm2.sqrt()?.recip()? * gain)?)
        } else if gain != 1.0 {
            Some(Tensor::full(gain, (b, self.cout), x.device())?.to_dtype(x.dtype())?)
        } else {
            None
        };
        let path = match path {
            ModulationPath::Auto => {
                let weight_numbers = self.cout * self.cin * self.k * self.k;
                let image_numbers = (self.cin + self.cout) * h * w;
                if image_numbers < weight_numbers {
                    ModulationPath::ScaleInput
                } else {
                    ModulationPath::ModulateWeight
                }
            }
            p => p,
        };
        let spec = self.spec();
        let bf16 = self
            .bf16
            .as_ref()
            .filter(|_| !x.track_op() && !latent.track_op());
        match path {
            ModulationPath::ScaleInput => {
                let xs = x.broadcast_mul(&style.reshape((b, cin, 1, 1))?)?;
                let mut y = match bf16 {
                    Some(packed) => packed.forward(&xs)?,
                    None => conv2d_fixed(&xs, &self.weight, None, None, spec, &self.wino)?,
                };
                if let Some(f) = &factor {
                    y = y.broadcast_mul(&f.reshape((b, self.cout, 1, 1))?)?;
                }
                match bias {
                    Some(bias) => y.broadcast_add(&bias.reshape((1, self.cout, 1, 1))?),
                    None => Ok(y),
                }
            }
            _ => {
                let mut outs = Vec::with_capacity(b);
                for i in 0..b {
                    let s = style.narrow(0, i, 1)?;
                    let scale = match &factor {
                        // Outer product d[o] s[i]: [cout, cin].
                        Some(f) => f.narrow(0, i, 1)?.t()?.broadcast_mul(&s)?,
                        None => s,
                    };
                    let xi = if b == 1 {
                        x.clone()
                    } else {
                        x.narrow(0, i, 1)?
                    };
                    let scale = scale.broadcast_as((self.cout, cin))?;
                    outs.push(match bf16 {
                        Some(packed) => packed.forward_scaled(&xi, &scale, bias)?,
                        None => {
                            conv2d_fixed(&xi, &self.weight, Some(&scale), bias, spec, &self.wino)?
                        }
                    });
                }
                if b == 1 {
                    Ok(outs.remove(0))
                } else {
                    Tensor::cat(&outs, 0)
                }
            }
        }
    }
}

/// StyleGAN2 StyleConv: `lrelu(modconv(x) * sqrt(2) + weight * noise + bias, 0.2)`, with a x2
/// bilinear upsampling of the input first when `upsample`.
#[derive(Debug, Clone)]
pub struct StyleConv {
    modulated_conv: ModulatedConv,
    noise_weight: Tensor,
    bias: Tensor,
    upsample: bool,
}

impl StyleConv {
    pub fn new(
        vb: VarBuilder,
        cin: usize,
        cout: usize,
        style_dim: usize,
        upsample: bool,
    ) -> Result<Self> {
        Ok(Self {
            modulated_conv: ModulatedConv::new(
                vb.pp("modulated_conv"),
                cin,
                cout,
                3,
                style_dim,
                true,
            )?,
            noise_weight: vb.get(1, "weight")?,
            bias: vb.get((1, cout, 1, 1), "bias")?.reshape(cout)?,
            upsample,
        })
    }

    fn named_weights(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        self.modulated_conv
            .named_weights(&format!("{prefix}.modulated_conv"), out);
        out.push((format!("{prefix}.weight"), self.noise_weight.clone()));
        out.push((format!("{prefix}.bias"), self.bias.clone()));
    }

    /// `noise` [1 or B, 1, H', W'] at the output resolution.
    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.modulated_conv.set_precision(precision)
    }

    pub fn forward(&self, x: &Tensor, latent: &Tensor, noise: &Tensor) -> Result<Tensor> {
        let up;
        let x = if self.upsample {
            up = upsample2x(x)?;
            &up
        } else {
            x
        };
        let y = self
            .modulated_conv
            .forward(x, latent, SQRT_2, Some(&self.bias))?;
        epilogue::noise_lrelu(y, noise, &self.noise_weight)
    }
}

/// StyleGAN2 ToRGB: modulated 1x1 without demodulation, `+ bias`, plus the previous RGB skip
/// upsampled x2 when given.
#[derive(Debug, Clone)]
pub struct ToRgb {
    modulated_conv: ModulatedConv,
    bias: Tensor,
}

impl ToRgb {
    pub fn new(vb: VarBuilder, cin: usize, style_dim: usize) -> Result<Self> {
        Ok(Self {
            modulated_conv: ModulatedConv::new(
                vb.pp("modulated_conv"),
                cin,
                3,
                1,
                style_dim,
                false,
            )?,
            bias: vb.get((1, 3, 1, 1), "bias")?.reshape(3)?,
        })
    }

    fn named_weights(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        self.modulated_conv
            .named_weights(&format!("{prefix}.modulated_conv"), out);
        out.push((format!("{prefix}.bias"), self.bias.clone()));
    }

    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.modulated_conv.set_precision(precision)
    }

    pub fn forward(&self, x: &Tensor, latent: &Tensor, skip: Option<&Tensor>) -> Result<Tensor> {
        let y = self
            .modulated_conv
            .forward(x, latent, 1.0, Some(&self.bias))?;
        match skip {
            Some(s) => epilogue::add(y, &upsample2x(s)?),
            None => Ok(y),
        }
    }
}

/// `upsampler.stylegan_decoder`: StyleGAN2 generator with SFT conditions (one scale/shift pair
/// per resolution 8 .. image_size, applied after the first StyleConv of that resolution).
#[derive(Debug, Clone)]
pub struct StyleGan2Decoder {
    style_mlp: Vec<Linear>,
    constant_input: Tensor,
    style_conv1: StyleConv,
    to_rgb1: ToRgb,
    style_convs: Vec<StyleConv>,
    to_rgbs: Vec<ToRgb>,
    noises: Vec<Tensor>,
}

impl StyleGan2Decoder {
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        let sd = cfg.style_dim;
        let levels = cfg.renderer_levels();
        let ch = |r: usize| cfg.decoder_channels(r);
        let style_mlp = (0..cfg.style_mlp_layers)
            .map(|i| candle_nn::linear(sd, sd, vb.pp(format!("style_mlp.{}", 2 * i + 1))))
            .collect::<Result<Vec<_>>>()?;
        let constant_input = vb.get((1, ch(4), 4, 4), "constant_input.weight")?;
        let style_conv1 = StyleConv::new(vb.pp("style_conv1"), ch(4), ch(4), sd, false)?;
        let to_rgb1 = ToRgb::new(vb.pp("to_rgb1"), ch(4), sd)?;
        let mut style_convs = Vec::with_capacity(2 * levels);
        let mut to_rgbs = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = 8 << k;
            let (cin, cout) = (ch(r / 2), ch(r));
            let i = 2 * k;
            style_convs.push(StyleConv::new(
                vb.pp(format!("style_convs.{i}")),
                cin,
                cout,
                sd,
                true,
            )?);
            style_convs.push(StyleConv::new(
                vb.pp(format!("style_convs.{}", i + 1)),
                cout,
                cout,
                sd,
                false,
            )?);
            to_rgbs.push(ToRgb::new(vb.pp(format!("to_rgbs.{k}")), cout, sd)?);
        }
        let noises = (0..2 * levels + 1)
            .map(|i| {
                let r = noise_resolution(i);
                vb.get((1, 1, r, r), &format!("noises.noise{i}"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            style_mlp,
            constant_input,
            style_conv1,
            to_rgb1,
            style_convs,
            to_rgbs,
            noises,
        })
    }

    /// The mapping network: RMS-normalise the code, then Linear + leaky ReLU layers.
    fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.style_conv1.set_precision(precision)?;
        self.to_rgb1.set_precision(precision)?;
        for c in &mut self.style_convs {
            c.set_precision(precision)?;
        }
        for c in &mut self.to_rgbs {
            c.set_precision(precision)?;
        }
        Ok(())
    }

    pub fn latent(&self, code: &Tensor) -> Result<Tensor> {
        let ms = code.sqr()?.mean_keepdim(D::Minus1)?;
        let mut x = code.broadcast_div(&(ms + EPS)?.sqrt()?)?;
        for layer in &self.style_mlp {
            x = epilogue::lrelu(layer.forward(&x)?)?;
        }
        Ok(x)
    }

    fn noise(&self, i: usize, batch: usize, mode: Noise, like: &Tensor) -> Result<Tensor> {
        match mode {
            Noise::Fixed => Ok(self.noises[i].clone()),
            Noise::Fresh => {
                let r = noise_resolution(i);
                Tensor::randn(0f32, 1f32, (batch, 1, r, r), like.device())?.to_dtype(like.dtype())
            }
            Noise::Seeded(seed) => seeded_noise(seed, i, batch, noise_resolution(i), like),
            Noise::SeededFrom { seed, first } => {
                seeded_noise_from(seed, i, first, batch, noise_resolution(i), like)
            }
        }
    }

    fn named_weights(&self, out: &mut Vec<(String, Tensor)>) {
        for (i, l) in self.style_mlp.iter().enumerate() {
            push_linear(out, &format!("style_mlp.{}", 2 * i + 1), l);
        }
        out.push(("constant_input.weight".into(), self.constant_input.clone()));
        self.style_conv1.named_weights("style_conv1", out);
        self.to_rgb1.named_weights("to_rgb1", out);
        for (i, c) in self.style_convs.iter().enumerate() {
            c.named_weights(&format!("style_convs.{i}"), out);
        }
        for (k, c) in self.to_rgbs.iter().enumerate() {
            c.named_weights(&format!("to_rgbs.{k}"), out);
        }
        for (i, t) in self.noises.iter().enumerate() {
            out.push((format!("noises.noise{i}"), t.clone()));
        }
    }

    /// The fixed noise buffers `noises.noise{i}`, in order (buffers, not trained parameters).
    pub fn noise_buffers(&self) -> &[Tensor] {
        &self.noises
    }

    /// `code` [B, style_dim] and the SFT (scale, shift) pairs for resolutions 8 .. image_size
    /// -> the RGB image before the sigmoid [B, 3, image_size, image_size].
    pub fn forward(
        &self,
        code: &Tensor,
        conditions: &[(Tensor, Tensor)],
        noise: Noise,
    ) -> Result<Tensor> {
        if conditions.len() != self.to_rgbs.len() {
            bail!(
                "the decoder needs {} SFT conditions, got {}",
                self.to_rgbs.len(),
                conditions.len()
            );
        }
        let b = code.dim(0)?;
        let latent = self.latent(code)?;
        let c4 = self.constant_input.dim(1)?;
        let mut out = self
            .constant_input
            .broadcast_as((b, c4, 4, 4))?
            .contiguous()?;
        out = self
            .style_conv1
            .forward(&out, &latent, &self.noise(0, b, noise, code)?)?;
        let mut skip = self.to_rgb1.forward(&out, &latent, None)?;
        for (k, (scale, shift)) in conditions.iter().enumerate() {
            let conv_up = &self.style_convs[2 * k];
            let conv = &self.style_convs[2 * k + 1];
            out = conv_up.forward(&out, &latent, &self.noise(2 * k + 1, b, noise, code)?)?;
            if scale.dims() != out.dims() || shift.dims() != out.dims() {
                bail!(
                    "SFT condition {k}: scale {:?} / shift {:?} do not match the features {:?}",
                    scale.dims(),
                    shift.dims(),
                    out.dims()
                );
            }
            out = epilogue::sft(out, scale, shift)?;
            out = conv.forward(&out, &latent, &self.noise(2 * k + 2, b, noise, code)?)?;
            skip = self.to_rgbs[k].forward(&out, &latent, Some(&skip))?;
        }
        Ok(skip)
    }
}

/// Side of noise buffer `i`: 4, 8, 8, 16, 16, ...
pub fn noise_resolution(i: usize) -> usize {
    1 << ((i + 5) / 2)
}

/// `upsampler`: the StyleUNet renderer, `[B, color_dim, S, S]` -> `[B, 3, S, S]` in [0, 1]
/// (S = image_size).
#[derive(Debug, Clone)]
pub struct StyleUNet {
    conv_body_first: Conv2d,
    conv_body_down: Vec<ResBlock>,
    final_conv: Conv2d,
    final_linear: Linear,
    conv_body_up: Vec<ResBlock>,
    condition_scale: Vec<ConditionBranch>,
    condition_shift: Vec<ConditionBranch>,
    /// `toRGB.k` are in the checkpoint (the release computes them only for an optional extra
    /// output that is commented out), so they are loaded for the key set but never feed the
    /// image.
    _to_rgb: Vec<Conv2d>,
    decoder: StyleGan2Decoder,
    color_dim: usize,
    image_size: usize,
}

impl StyleUNet {
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        cfg.validate().map_err(candle_core::Error::msg)?;
        let levels = cfg.renderer_levels();
        let s = cfg.image_size;
        let u = |r: usize| cfg.unet_channels(r);
        let conv_body_first = Conv2d::k1(vb.pp("conv_body_first"), cfg.color_dim, u(s))?;
        let conv_body_down = (0..levels)
            .map(|k| {
                let r = s >> k;
                ResBlock::new(vb.pp(format!("conv_body_down.{k}")), u(r), u(r / 2), false)
            })
            .collect::<Result<Vec<_>>>()?;
        let final_conv = Conv2d::k3(vb.pp("final_conv"), u(4), u(4))?;
        let final_linear = candle_nn::linear(u(4) * 16, cfg.style_dim, vb.pp("final_linear"))?;
        let mut conv_body_up = Vec::with_capacity(levels);
        let mut condition_scale = Vec::with_capacity(levels);
        let mut condition_shift = Vec::with_capacity(levels);
        let mut to_rgb = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = 8 << k;
            conv_body_up.push(ResBlock::new(
                vb.pp(format!("conv_body_up.{k}")),
                u(r / 2),
                u(r),
                true,
            )?);
            let dc = cfg.decoder_channels(r);
            condition_scale.push(ConditionBranch::new(
                vb.pp(format!("condition_scale.{k}")),
                u(r),
                dc,
            )?);
            condition_shift.push(ConditionBranch::new(
                vb.pp(format!("condition_shift.{k}")),
                u(r),
                dc,
            )?);
            to_rgb.push(Conv2d::k1(vb.pp(format!("toRGB.{k}")), u(r), 3)?);
        }
        let decoder = StyleGan2Decoder::new(cfg, vb.pp("stylegan_decoder"))?;
        Ok(Self {
            conv_body_first,
            conv_body_down,
            final_conv,
            final_linear,
            conv_body_up,
            condition_scale,
            condition_shift,
            _to_rgb: to_rgb,
            decoder,
            color_dim: cfg.color_dim,
            image_size: s,
        })
    }

    /// The coarse image [B, color_dim, S, S] -> the fine RGB image [B, 3, S, S] in [0, 1].
    /// Switches the convolutions between f32 and bf16 products (bf16: fixed weights only,
    /// inference; the small linear layers of the style code stay f32).
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.conv_body_first.set_precision(precision)?;
        for b in self.conv_body_down.iter_mut().chain(&mut self.conv_body_up) {
            b.set_precision(precision)?;
        }
        self.final_conv.set_precision(precision)?;
        for c in self
            .condition_scale
            .iter_mut()
            .chain(&mut self.condition_shift)
        {
            c.set_precision(precision)?;
        }
        self.decoder.set_precision(precision)
    }

    pub fn forward(&self, x: &Tensor, noise: Noise) -> Result<Tensor> {
        let (feat, skips) = self.down(x)?;
        let code = self.style_code(&feat)?;
        let conditions = self.conditions(&feat, &skips)?;
        let image = self.decoder.forward(&code, &conditions, noise)?;
        candle_nn::ops::sigmoid(&image)
    }

    /// U-Net encoder: the 4x4 features after `final_conv` and the ResBlock outputs, deepest
    /// first (the order the up path consumes them).
    pub fn down(&self, x: &Tensor) -> Result<(Tensor, Vec<Tensor>)> {
        let dims = x.dims();
        let (c, s) = (self.color_dim, self.image_size);
        if dims.len() != 4 || dims[1] != c || dims[2] != s || dims[3] != s {
            bail!("the renderer expects [B, {c}, {s}, {s}], got {dims:?}");
        }
        if !matches!(x.dtype(), DType::F32 | DType::F64) {
            bail!("the renderer supports f32 and f64, got {:?}", x.dtype());
        }
        let mut feat = epilogue::lrelu(self.conv_body_first.forward(x)?)?;
        let mut skips = Vec::with_capacity(self.conv_body_down.len());
        for block in &self.conv_body_down {
            feat = block.forward(&feat)?;
            skips.push(feat.clone());
        }
        skips.reverse();
        let feat = epilogue::lrelu(self.final_conv.forward(&feat)?)?;
        Ok((feat, skips))
    }

    /// `final_linear` on the flattened (C, H, W) 4x4 features: the style code [B, style_dim].
    pub fn style_code(&self, feat: &Tensor) -> Result<Tensor> {
        self.final_linear.forward(&feat.flatten_from(1)?)
    }

    /// U-Net decoder: the SFT (scale, shift) pairs for resolutions 8 .. image_size.
    pub fn conditions(&self, feat: &Tensor, skips: &[Tensor]) -> Result<Vec<(Tensor, Tensor)>> {
        if skips.len() != self.conv_body_up.len() {
            bail!(
                "the U-Net needs {} skips, got {}",
                self.conv_body_up.len(),
                skips.len()
            );
        }
        let mut out = Vec::with_capacity(skips.len());
        let mut prev: Option<Tensor> = None;
        for (k, skip) in skips.iter().enumerate() {
            // The caller's `feat` is only read; later levels add into their own fresh output.
            let input = match prev.take() {
                None => (feat + skip)?,
                Some(f) => epilogue::add(f, skip)?,
            };
            let feat = self.conv_body_up[k].forward(&input)?;
            out.push((
                self.condition_scale[k].forward(&feat)?,
                self.condition_shift[k].forward(&feat)?,
            ));
            prev = Some(feat);
        }
        Ok(out)
    }

    pub fn decoder(&self) -> &StyleGan2Decoder {
        &self.decoder
    }

    /// Every weight the forward pass uses, under its key relative to `upsampler.` (the
    /// checkpoint's key without that prefix), for other backends (the GPU drive path). Values
    /// are the checkpoint's; shapes are the module's (the modulated convolutions' weights are
    /// `[cout, cin, k, k]` and the StyleConv biases `[cout]`). The unused `toRGB.k` are left out.
    pub fn named_weights(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        push_conv(&mut out, "conv_body_first", &self.conv_body_first);
        for (k, b) in self.conv_body_down.iter().enumerate() {
            b.named_weights(&format!("conv_body_down.{k}"), &mut out);
        }
        push_conv(&mut out, "final_conv", &self.final_conv);
        push_linear(&mut out, "final_linear", &self.final_linear);
        for (k, b) in self.conv_body_up.iter().enumerate() {
            b.named_weights(&format!("conv_body_up.{k}"), &mut out);
        }
        for (k, b) in self.condition_scale.iter().enumerate() {
            b.named_weights(&format!("condition_scale.{k}"), &mut out);
        }
        for (k, b) in self.condition_shift.iter().enumerate() {
            b.named_weights(&format!("condition_shift.{k}"), &mut out);
        }
        let mut dec = Vec::new();
        self.decoder.named_weights(&mut dec);
        out.extend(
            dec.into_iter()
                .map(|(k, t)| (format!("stylegan_decoder.{k}"), t)),
        );
        out
    }
}

/// Bilinear x2 upsampling, `align_corners=False` (PyTorch `interpolate(scale_factor=2)`), of
/// the last two dims of a 4-D f32/f64 tensor; differentiable.
pub fn upsample2x(x: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    resize(x, 2 * h, 2 * w, ResizeMode::HalfPixel)
}

/// Bilinear x0.5 downsampling, `align_corners=False`, of even-sized planes (each output is the
/// mean of a 2x2 block: the source position `2o + 0.5` lies halfway between two samples).
pub fn downsample2x(x: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    if h % 2 != 0 || w % 2 != 0 {
        bail!("downsample2x needs even sizes, got {h}x{w}");
    }
    resize(x, h / 2, w / 2, ResizeMode::HalfPixel)
}

#[cfg(test)]
mod tests {
    use crate::checkpoint::{build_model, init_weights};
    use crate::ModelConfig;
    use candle_core::{Device, Tensor};
    use std::collections::HashMap;

    /// A data-parallel rank's noise (`SeededFrom`) is its samples' part of the whole batch's.
    #[test]
    fn seeded_noise_from_is_a_slice_of_the_whole_batch() {
        let like = Tensor::zeros(1, candle_core::DType::F32, &Device::Cpu).unwrap();
        let whole = super::seeded_noise(9, 2, 4, 8, &like).unwrap();
        for (first, n) in [(0, 1), (1, 2), (3, 1)] {
            let part = super::seeded_noise_from(9, 2, first, n, 8, &like).unwrap();
            let want = whole.narrow(0, first, n).unwrap();
            let d = (part - want)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap();
            assert_eq!(d, 0.0, "samples {first}..{}", first + n);
        }
    }

    /// `named_weights` lists every renderer key of the checkpoint but the unused `toRGB.k`,
    /// each with the checkpoint's values.
    #[test]
    fn named_weights_are_the_checkpoint_values() {
        let cfg = ModelConfig::tiny();
        let data = init_weights(&cfg, 3).unwrap();
        let mut map = HashMap::new();
        for (k, (shape, v)) in &data {
            map.insert(
                k.clone(),
                Tensor::from_vec(v.clone(), shape.clone(), &Device::Cpu).unwrap(),
            );
        }
        let model = build_model(&cfg, map, &Device::Cpu).unwrap();
        let named = model.renderer.named_weights();
        let mut seen = std::collections::BTreeSet::new();
        for (k, t) in &named {
            let full = format!("upsampler.{k}");
            let (_, want) = data
                .get(&full)
                .unwrap_or_else(|| panic!("{full} is not a key"));
            let got: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            assert_eq!(&got, want, "{full}");
            assert!(seen.insert(full.clone()), "{full} listed twice");
        }
        for k in data.keys() {
            if let Some(rest) = k.strip_prefix("upsampler.") {
                assert!(
                    seen.contains(k) || rest.starts_with("toRGB."),
                    "{k} is missing from named_weights"
                );
            }
        }
    }
}
