//! The neural renderer (spec section 8, `upsampler.*`) on the GPU: the StyleUNet's U-Net
//! encoder and SFT branches, the mapping network and the StyleGAN2 decoder, as the CPU path
//! (`gagavatar_net::style_unet`) computes them, with the weights uploaded once and every
//! activation in its own buffer, allocated once.
//!
//! Exact rearrangements (they change results only by rounding): a modulated convolution
//! scales its input by the style and its output by the demodulation (the CPU path picks this
//! or weight modulation per layer); the SFT branches' first convolutions (scale and shift read
//! the same features) run as one convolution with both weight sets; the final sigmoid and the
//! SFT are fused into the convolutions before them.

use std::f32::consts::SQRT_2;

use gagavatar_net::style_unet::noise_resolution;
use gagavatar_net::ModelConfig;

use crate::conv::{Act, At, Conv, ConvWeights, Ops};
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::Step;
use crate::tuning::Tuning;

/// Where the renderer's weights come from: the value of a key relative to `upsampler.`
/// (row-major, any shape with the right element count).
pub type WeightFn<'a> = dyn Fn(&str) -> Result<Vec<f32>> + 'a;

/// The value of `upsampler.{key}`, checked to hold `len` values.
pub(crate) fn get(weights: &WeightFn, key: &str, len: usize) -> Result<Vec<f32>> {
    let v = weights(key)?;
    if v.len() != len {
        return Err(GpuError::Weights(format!(
            "upsampler.{key} has {} values, expected {len}",
            v.len()
        )));
    }
    Ok(v)
}

/// Host-side layout of the shared vector buffer: biases (constant) and the per-frame styles
/// and demodulation factors (written by kernels).
#[derive(Default)]
struct Vecs {
    host: Vec<f32>,
}

impl Vecs {
    fn push(&mut self, v: &[f32]) -> u32 {
        let at = self.host.len();
        self.host.extend_from_slice(v);
        at as u32
    }
    fn reserve(&mut self, n: usize) -> u32 {
        let at = self.host.len();
        self.host.resize(at + n, 0.0);
        at as u32
    }
}

struct ModW {
    weight: wgpu::Buffer,
    cin: usize,
    cout: usize,
    k: usize,
    style: u32,
    /// Demodulation: the factors' offset and the kernel energies `[cout, cin]`.
    demod: Option<(u32, wgpu::Buffer)>,
    bias: u32,
    /// The noise weight's offset in the vector buffer.
    noise_weight: u32,
}

struct Loader<'g, 'w> {
    gpu: &'g Gpu,
    weights: &'w WeightFn<'w>,
    vecs: Vecs,
    /// Stacked modulation weights `[rows, style_dim]` and biases.
    mod_w: Vec<f32>,
    mod_b: Vec<f32>,
    style_dim: usize,
}

impl Loader<'_, '_> {
    fn conv(
        &mut self,
        key: &str,
        cin: usize,
        cout: usize,
        k: usize,
        bias: bool,
    ) -> Result<ConvWeights> {
        let w = get(self.weights, &format!("{key}.weight"), cout * cin * k * k)?;
        let bias = if bias {
            let b = get(self.weights, &format!("{key}.bias"), cout)?;
            Some(self.vecs.push(&b))
        } else {
            None
        };
        Ok(ConvWeights {
            weight: self.gpu.buffer_with(key, &w),
            bias,
            cin,
            cout,
            k,
        })
    }

    /// Two 3x3 convolutions reading the same input, as one with both output sets.
    fn conv_pair(&mut self, a: &str, b: &str, cin: usize, cout: usize) -> Result<ConvWeights> {
        let n = cout * cin * 9;
        let mut w = get(self.weights, &format!("{a}.weight"), n)?;
        w.extend(get(self.weights, &format!("{b}.weight"), n)?);
        let mut bias = get(self.weights, &format!("{a}.bias"), cout)?;
        bias.extend(get(self.weights, &format!("{b}.bias"), cout)?);
        Ok(ConvWeights {
            weight: self.gpu.buffer_with(a, &w),
            bias: Some(self.vecs.push(&bias)),
            cin,
            cout: 2 * cout,
            k: 3,
        })
    }

    fn modconv(
        &mut self,
        key: &str,
        cin: usize,
        cout: usize,
        k: usize,
        demodulate: bool,
        bias_len: usize,
    ) -> Result<ModW> {
        let mc = format!("{key}.modulated_conv");
        let w = get(self.weights, &format!("{mc}.weight"), cout * cin * k * k)?;
        let mw = get(
            self.weights,
            &format!("{mc}.modulation.weight"),
            cin * self.style_dim,
        )?;
        let mb = get(self.weights, &format!("{mc}.modulation.bias"), cin)?;
        let style_row = self.mod_b.len();
        self.mod_w.extend(mw);
        self.mod_b.extend(mb);
        let demod = if demodulate {
            let taps = k * k;
            let energy: Vec<f32> = w
                .chunks(taps)
                .map(|c| c.iter().map(|v| v * v).sum())
                .collect();
            Some((
                self.vecs.reserve(cout),
                self.gpu.buffer_with("kernel energy", &energy),
            ))
        } else {
            None
        };
        let bias = get(self.weights, &format!("{key}.bias"), bias_len)?;
        let noise_weight = if demodulate {
            self.vecs
                .push(&get(self.weights, &format!("{key}.weight"), 1)?)
        } else {
            0
        };
        Ok(ModW {
            weight: self.gpu.buffer_with(&mc, &w),
            cin,
            cout,
            k,
            // Filled in once the styles' place in the vector buffer is known.
            style: style_row as u32,
            demod,
            bias: self.vecs.push(&bias),
            noise_weight,
        })
    }
}

struct Block {
    conv1: ConvWeights,
    conv2: ConvWeights,
    skip: ConvWeights,
}

/// The renderer, bound to its input buffer (`[color_dim, S, S]`, the splatted image).
pub struct GpuRenderer {
    pub size: usize,
    /// `[3, S, S]` in [0, 1].
    pub output: wgpu::Buffer,
    noise: wgpu::Buffer,
    noise_offsets: Vec<usize>,
    /// The U-Net (encoder and SFT branches), then the mapping network and decoder.
    unet: Vec<Step>,
    decoder: Vec<Step>,
}

impl GpuRenderer {
    /// Uploads the weights (keys relative to `upsampler.`) and records the forward pass
    /// reading `input`.
    pub fn new(
        gpu: &Gpu,
        tuning: &Tuning,
        cfg: &ModelConfig,
        weights: &WeightFn,
        input: &wgpu::Buffer,
    ) -> Result<Self> {
        cfg.validate().map_err(GpuError::Unsupported)?;
        let tuning = &tuning.for_device(gpu);
        tuning.check(&gpu.limits)?;
        let s = cfg.image_size;
        let levels = cfg.renderer_levels();
        let u = |r: usize| cfg.unet_channels(r);
        let dc = |r: usize| cfg.decoder_channels(r);
        let sd = cfg.style_dim;
        let mut ld = Loader {
            gpu,
            weights,
            vecs: Vecs::default(),
            mod_w: Vec::new(),
            mod_b: Vec::new(),
            style_dim: sd,
        };

        // Weights, in the CPU module's order.
        let first = ld.conv("conv_body_first", cfg.color_dim, u(s), 1, true)?;
        let mut down = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = s >> k;
            let p = format!("conv_body_down.{k}");
            down.push(Block {
                conv1: ld.conv(&format!("{p}.conv1"), u(r), u(r), 3, true)?,
                conv2: ld.conv(&format!("{p}.conv2"), u(r), u(r / 2), 3, true)?,
                skip: ld.conv(&format!("{p}.skip"), u(r), u(r / 2), 1, false)?,
            });
        }
        let final_conv = ld.conv("final_conv", u(4), u(4), 3, true)?;
        let fl_in = u(4) * 16;
        let fl_w = gpu.buffer_with(
            "final_linear",
            &get(weights, "final_linear.weight", sd * fl_in)?,
        );
        let fl_b = gpu.buffer_with("final_linear.bias", &get(weights, "final_linear.bias", sd)?);
        let mut up = Vec::with_capacity(levels);
        let mut cond0 = Vec::with_capacity(levels);
        let mut cond_scale = Vec::with_capacity(levels);
        let mut cond_shift = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = 8 << k;
            let p = format!("conv_body_up.{k}");
            up.push(Block {
                conv1: ld.conv(&format!("{p}.conv1"), u(r / 2), u(r / 2), 3, true)?,
                conv2: ld.conv(&format!("{p}.conv2"), u(r / 2), u(r), 3, true)?,
                skip: ld.conv(&format!("{p}.skip"), u(r / 2), u(r), 1, false)?,
            });
            cond0.push(ld.conv_pair(
                &format!("condition_scale.{k}.0"),
                &format!("condition_shift.{k}.0"),
                u(r),
                u(r),
            )?);
            cond_scale.push(ld.conv(&format!("condition_scale.{k}.2"), u(r), dc(r), 3, true)?);
            cond_shift.push(ld.conv(&format!("condition_shift.{k}.2"), u(r), dc(r), 3, true)?);
        }
        let dp = "stylegan_decoder";
        let mut mlp = Vec::with_capacity(cfg.style_mlp_layers);
        for i in 0..cfg.style_mlp_layers {
            let key = format!("{dp}.style_mlp.{}", 2 * i + 1);
            mlp.push((
                gpu.buffer_with(&key, &get(weights, &format!("{key}.weight"), sd * sd)?),
                gpu.buffer_with(&key, &get(weights, &format!("{key}.bias"), sd)?),
            ));
        }
        let c4 = dc(4);
        let constant = gpu.buffer_with(
            "constant_input",
            &get(weights, &format!("{dp}.constant_input.weight"), c4 * 16)?,
        );
        let style_conv1 = ld.modconv(&format!("{dp}.style_conv1"), c4, c4, 3, true, c4)?;
        let to_rgb1 = ld.modconv(&format!("{dp}.to_rgb1"), c4, 3, 1, false, 3)?;
        let mut style_convs = Vec::with_capacity(2 * levels);
        let mut to_rgbs = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = 8 << k;
            let (cin, cout) = (dc(r / 2), dc(r));
            style_convs.push(ld.modconv(
                &format!("{dp}.style_convs.{}", 2 * k),
                cin,
                cout,
                3,
                true,
                cout,
            )?);
            style_convs.push(ld.modconv(
                &format!("{dp}.style_convs.{}", 2 * k + 1),
                cout,
                cout,
                3,
                true,
                cout,
            )?);
            to_rgbs.push(ld.modconv(&format!("{dp}.to_rgbs.{k}"), cout, 3, 1, false, 3)?);
        }
        let mut noise_host = Vec::new();
        let mut noise_offsets = Vec::new();
        for i in 0..2 * levels + 1 {
            let r = noise_resolution(i);
            noise_offsets.push(noise_host.len());
            noise_host.extend(get(weights, &format!("{dp}.noises.noise{i}"), r * r)?);
        }
        let noise = gpu.buffer_with("renderer noise", &noise_host);

        // The styles of every modulated convolution, in one block of the vector buffer.
        let styles_rows = ld.mod_b.len();
        let styles_at = ld.vecs.reserve(styles_rows);
        let mod_w = gpu.buffer_with("style modulations", &ld.mod_w);
        let mod_b = gpu.buffer_with("style modulation biases", &ld.mod_b);
        let vecs = gpu.buffer_with("renderer vectors", &ld.vecs.host);
        let dummy = gpu.buffer("unused", 16);
        let mut split_need = 0usize;
        let mut need = |cin: usize, cout: usize, r: usize, k: usize| {
            split_need = split_need.max(Ops::split_need(tuning, cin, cout, r, r, k));
        };
        for (k, b) in down.iter().enumerate() {
            let r = s >> k;
            need(b.conv1.cin, b.conv1.cout, r, 3);
            need(b.conv2.cin, b.conv2.cout, r / 2, 3);
            need(b.skip.cin, b.skip.cout, r / 2, 1);
        }
        need(u(4), u(4), 4, 3);
        for k in 0..levels {
            let r = 8 << k;
            let b = &up[k];
            need(b.conv1.cin, b.conv1.cout, r / 2, 3);
            need(b.conv2.cin, b.conv2.cout, r, 3);
            need(b.skip.cin, b.skip.cout, r / 2, 1);
            need(cond0[k].cin, cond0[k].cout, r, 3);
            need(cond_scale[k].cin, cond_scale[k].cout, r, 3);
            need(cond_shift[k].cin, cond_shift[k].cout, r, 3);
            need(style_convs[2 * k].cin, style_convs[2 * k].cout, r, 3);
            need(
                style_convs[2 * k + 1].cin,
                style_convs[2 * k + 1].cout,
                r,
                3,
            );
            need(to_rgbs[k].cin, 3, r, 1);
        }
        need(c4, c4, 4, 3);
        need(c4, 3, 4, 1);
        let split_scratch = gpu.buffer("split-K partial sums", 4 * split_need as u64);
        let ops = Ops {
            gpu,
            tuning,
            vecs: &vecs,
            dummy: &dummy,
            split_scratch: &split_scratch,
        };
        let act = |label: &str, c: usize, r: usize| gpu.buffer(label, 4 * (c * r * r) as u64);
        let plain = |cw: &ConvWeights, r: usize, input: At<'_>, out: At<'_>| -> Result<Vec<Step>> {
            ops.conv(&Conv::plain(cw, (r, r), input, out))
        };
        let conv_lrelu =
            |cw: &ConvWeights, r: usize, input: At<'_>, out: At<'_>, residual: Option<At<'_>>| {
                ops.conv(&Conv {
                    act: Act::Lrelu,
                    residual,
                    ..Conv::plain(cw, (r, r), input, out)
                })
            };

        // U-Net encoder.
        let mut unet = Vec::new();
        let mut f = act("conv_body_first", u(s), s);
        unet.extend(conv_lrelu(&first, s, At::new(input), At::new(&f), None)?);
        let mut skips = Vec::with_capacity(levels);
        for (k, b) in down.iter().enumerate() {
            let r = s >> k;
            let (ci, co) = (b.conv1.cin, b.conv2.cout);
            let h = act("down h", ci, r);
            unet.extend(conv_lrelu(&b.conv1, r, At::new(&f), At::new(&h), None)?);
            let hd = act("down h/2", ci, r / 2);
            unet.push(ops.resize(false, ci, r, r, At::new(&h), At::new(&hd))?);
            let xd = act("down x/2", ci, r / 2);
            unet.push(ops.resize(false, ci, r, r, At::new(&f), At::new(&xd))?);
            let sk = act("down skip", co, r / 2);
            unet.extend(plain(&b.skip, r / 2, At::new(&xd), At::new(&sk))?);
            let out = act("down out", co, r / 2);
            unet.extend(conv_lrelu(
                &b.conv2,
                r / 2,
                At::new(&hd),
                At::new(&out),
                Some(At::new(&sk)),
            )?);
            skips.push(out.clone());
            f = out;
        }
        let feat = act("final_conv", u(4), 4);
        unet.extend(conv_lrelu(
            &final_conv,
            4,
            At::new(&f),
            At::new(&feat),
            None,
        )?);
        let code = gpu.buffer("style code", 4 * sd as u64);
        unet.push(ops.linear(
            fl_in,
            sd,
            At::new(&feat),
            &fl_w,
            &fl_b,
            false,
            At::new(&code),
        )?);
        // U-Net decoder and the SFT maps (scale channels, then shift channels).
        let mut sfts = Vec::with_capacity(levels);
        let mut prev = feat.clone();
        for k in 0..levels {
            let r = 8 << k;
            let b = &up[k];
            let (ci, co) = (b.conv1.cin, b.conv2.cout);
            let x = act("up in", ci, r / 2);
            unet.push(ops.add(ci * r * r / 4, &prev, &skips[levels - 1 - k], &x)?);
            let h = act("up h", ci, r / 2);
            unet.extend(conv_lrelu(&b.conv1, r / 2, At::new(&x), At::new(&h), None)?);
            let hu = act("up h x2", ci, r);
            unet.push(ops.resize(true, ci, r / 2, r / 2, At::new(&h), At::new(&hu))?);
            let sk = act("up skip", co, r / 2);
            unet.extend(plain(&b.skip, r / 2, At::new(&x), At::new(&sk))?);
            let su = act("up skip x2", co, r);
            unet.push(ops.resize(true, co, r / 2, r / 2, At::new(&sk), At::new(&su))?);
            let out = act("up out", co, r);
            unet.extend(conv_lrelu(
                &b.conv2,
                r,
                At::new(&hu),
                At::new(&out),
                Some(At::new(&su)),
            )?);
            let c0 = act("condition 0", 2 * co, r);
            unet.extend(conv_lrelu(&cond0[k], r, At::new(&out), At::new(&c0), None)?);
            let d = dc(r);
            let sft = act("sft", 2 * d, r);
            unet.extend(plain(&cond_scale[k], r, At::new(&c0), At::off(&sft, 0))?);
            unet.extend(plain(
                &cond_shift[k],
                r,
                At::off(&c0, co * r * r),
                At::off(&sft, d * r * r),
            )?);
            sfts.push(sft);
            prev = out;
        }

        // Mapping network, styles and demodulation factors.
        let mut decoder = Vec::new();
        let mut lat = gpu.buffer("latent", 4 * sd as u64);
        decoder.push(ops.rms_norm(sd, &code, &lat)?);
        for (w, b) in &mlp {
            let next = gpu.buffer("latent", 4 * sd as u64);
            decoder.push(ops.linear(sd, sd, At::new(&lat), w, b, true, At::new(&next))?);
            lat = next;
        }
        decoder.push(ops.linear(
            sd,
            styles_rows,
            At::new(&lat),
            &mod_w,
            &mod_b,
            false,
            At::off(&vecs, styles_at as usize),
        )?);
        let style_of = |m: &ModW| styles_at + m.style;
        for m in std::iter::once(&style_conv1).chain(&style_convs) {
            if let Some((off, energy)) = &m.demod {
                decoder.push(ops.demod(m.cin, m.cout, energy, style_of(m), *off, SQRT_2)?);
            }
        }
        let modconv = |m: &ModW,
                       r: usize,
                       input: At<'_>,
                       out: At<'_>,
                       noise_map: Option<usize>,
                       residual: Option<At<'_>>,
                       sft: Option<&wgpu::Buffer>,
                       sigmoid: bool|
         -> Result<Vec<Step>> {
            ops.conv(&Conv {
                cin: m.cin,
                cout: m.cout,
                h: r,
                w: r,
                k: m.k,
                input,
                weight: &m.weight,
                bias: Some(m.bias),
                in_scale: Some(style_of(m)),
                out_scale: m.demod.as_ref().map(|(off, _)| *off),
                noise: noise_map.map(|i| (At::off(&noise, noise_offsets[i]), m.noise_weight)),
                in_relu: false,
                act: if m.demod.is_some() {
                    Act::Lrelu
                } else {
                    Act::None
                },
                residual,
                sft: sft.map(|b| (b, 0, (m.cout * r * r) as u32)),
                sigmoid,
                out,
            })
        };
        let mut out = act("style_conv1", c4, 4);
        decoder.extend(modconv(
            &style_conv1,
            4,
            At::new(&constant),
            At::new(&out),
            Some(0),
            None,
            None,
            false,
        )?);
        let mut rgb = act("to_rgb1", 3, 4);
        decoder.extend(modconv(
            &to_rgb1,
            4,
            At::new(&out),
            At::new(&rgb),
            None,
            None,
            None,
            false,
        )?);
        for k in 0..levels {
            let r = 8 << k;
            let (a, b) = (&style_convs[2 * k], &style_convs[2 * k + 1]);
            let upo = act("decoder x2", a.cin, r);
            decoder.push(ops.resize(true, a.cin, r / 2, r / 2, At::new(&out), At::new(&upo))?);
            let o1 = act("style conv up", a.cout, r);
            decoder.extend(modconv(
                a,
                r,
                At::new(&upo),
                At::new(&o1),
                Some(2 * k + 1),
                None,
                Some(&sfts[k]),
                false,
            )?);
            let o2 = act("style conv", b.cout, r);
            decoder.extend(modconv(
                b,
                r,
                At::new(&o1),
                At::new(&o2),
                Some(2 * k + 2),
                None,
                None,
                false,
            )?);
            let rgbu = act("rgb x2", 3, r);
            decoder.push(ops.resize(true, 3, r / 2, r / 2, At::new(&rgb), At::new(&rgbu))?);
            let next = act("to_rgb", 3, r);
            decoder.extend(modconv(
                &to_rgbs[k],
                r,
                At::new(&o2),
                At::new(&next),
                None,
                Some(At::new(&rgbu)),
                None,
                k + 1 == levels,
            )?);
            rgb = next;
            out = o2;
        }
        Ok(Self {
            size: s,
            output: rgb,
            noise,
            noise_offsets,
            unet,
            decoder,
        })
    }

    /// Replaces the decoder's noise maps (`[r * r]` each, in order; the fixed buffers are
    /// the default) for the next frames.
    pub fn set_noise(&self, gpu: &Gpu, maps: &[Vec<f32>]) -> Result<()> {
        if maps.len() != self.noise_offsets.len() {
            return Err(GpuError::Input {
                name: "renderer noise".into(),
                reason: format!("{} maps, expected {}", maps.len(), self.noise_offsets.len()),
            });
        }
        for (i, m) in maps.iter().enumerate() {
            let r = noise_resolution(i);
            if m.len() != r * r {
                return Err(GpuError::Input {
                    name: "renderer noise".into(),
                    reason: format!("map {i} has {} values, expected {}", m.len(), r * r),
                });
            }
            gpu.queue.write_buffer(
                &self.noise,
                4 * self.noise_offsets[i] as u64,
                bytemuck::cast_slice(m),
            );
        }
        Ok(())
    }

    /// Noise maps the decoder uses, with their sides.
    pub fn noise_sides(&self) -> Vec<usize> {
        (0..self.noise_offsets.len())
            .map(noise_resolution)
            .collect()
    }

    pub fn unet_steps(&self) -> &[Step] {
        &self.unet
    }

    pub fn decoder_steps(&self) -> &[Step] {
        &self.decoder
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::kernel::record_all;
    use crate::testutil::{assert_close, gpu};
    use candle_core::{DType, Device, Tensor};
    use gagavatar_net::checkpoint::init_weights_where;
    use gagavatar_net::style_unet::{Noise, StyleUNet};
    use gagavatar_splat::testscene::Rng;
    use std::collections::HashMap;

    /// The fine image's parity bound at the tiny preset: ~40 f32 convolutions summed in other
    /// orders than the CPU's, then a sigmoid. Measured on lavapipe: at most 6.0e-7 (renderer
    /// tests, every tuning) and 4.8e-7 (drive tests); the bound leaves ~16x for another
    /// driver's summation order. The tests print what they measure.
    pub const FINE_TOL: f64 = 1e-5;
    /// The same at release size (512x512, channels up to 512: fan-ins ~20x the tiny ones, so
    /// the reordered f32 sums drift further). Measured on lavapipe: 1.09e-4
    /// (`release_drive_matches_the_cpu`); the bound leaves ~4.5x.
    pub const RELEASE_FINE_TOL: f64 = 5e-4;

    /// The CPU renderer of `cfg` with seeded weights (the same values as
    /// `gagavatar init-weights` writes for those keys).
    pub fn cpu_renderer(cfg: &ModelConfig, seed: u64) -> StyleUNet {
        let data = init_weights_where(cfg, seed, &|k| k.starts_with("upsampler.")).unwrap();
        let map: HashMap<String, Tensor> = data
            .into_iter()
            .map(|(k, (shape, v))| (k, Tensor::from_vec(v, shape, &Device::Cpu).unwrap()))
            .collect();
        let vb = candle_nn::VarBuilder::from_tensors(map, DType::F32, &Device::Cpu);
        StyleUNet::new(cfg, vb.pp("upsampler")).unwrap()
    }

    /// The weights of a CPU renderer as the GPU renderer takes them.
    pub fn weight_fn(r: &StyleUNet) -> impl Fn(&str) -> Result<Vec<f32>> {
        let map: HashMap<String, Tensor> = r.named_weights().into_iter().collect();
        move |k: &str| {
            let t = map
                .get(k)
                .ok_or_else(|| GpuError::Weights(format!("no key upsampler.{k}")))?;
            t.flatten_all()
                .and_then(|t| t.to_vec1::<f32>())
                .map_err(|e| GpuError::Weights(e.to_string()))
        }
    }

    fn compare(cfg: &ModelConfig, tuning: &Tuning, seed: u64, what: &str, tol: f64) {
        let Some(g) = gpu() else { return };
        let cpu = cpu_renderer(cfg, seed);
        let s = cfg.image_size;
        let mut rng = Rng::new(seed + 100);
        let x: Vec<f32> = (0..cfg.color_dim * s * s)
            .map(|_| rng.range(-0.2, 1.2) as f32)
            .collect();
        let xt = Tensor::from_slice(&x, (1, cfg.color_dim, s, s), &Device::Cpu).unwrap();
        let want: Vec<f32> = cpu
            .forward(&xt, Noise::Fixed)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let input = g.buffer_with("coarse", &x);
        let wf = weight_fn(&cpu);
        let r = GpuRenderer::new(g, tuning, cfg, &wf, &input).unwrap();
        let mut enc = g
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            record_all(&mut pass, r.unet_steps());
            record_all(&mut pass, r.decoder_steps());
        }
        g.queue.submit([enc.finish()]);
        let got = g.read_f32(&r.output, 3 * s * s).unwrap();
        let mean = want
            .iter()
            .zip(&got)
            .map(|(a, b)| f64::from((a - b).abs()))
            .sum::<f64>()
            / want.len() as f64;
        eprintln!("{what}: mean abs difference {mean:e}");
        assert_close(what, &want, &got, tol);
    }

    #[test]
    fn tiny_renderer_matches_the_cpu() {
        let cfg = ModelConfig::tiny();
        compare(
            &cfg,
            &Tuning::default(),
            1,
            "tiny renderer, default tuning",
            FINE_TOL,
        );
        let mut t = Tuning::default();
        t.apply("conv_split_k=32,conv_bm=16,conv_bn=32,conv_bk=8,conv_tm=2,conv_tn=4,conv_small_bm=8,conv_small_bn=8,conv_small_bk=4,conv_small_tm=1,conv_small_tn=1")
            .unwrap();
        compare(
            &cfg,
            &t,
            2,
            "tiny renderer, split-K and other tiles",
            FINE_TOL,
        );
    }

    /// The fine image with every convolution on the tensor cores (f16 inputs, f32 sums), at
    /// the tiny and the release size, where the device has them.
    #[test]
    fn mma_renderer_matches_the_cpu() {
        if crate::testutil::mma_gpu().is_none() {
            return;
        }
        let t = Tuning {
            mma: true,
            ..Tuning::default()
        };
        compare(
            &ModelConfig::tiny(),
            &t,
            1,
            "tiny renderer, tensor cores",
            MMA_FINE_TOL,
        );
        compare(
            &ModelConfig::release(),
            &t,
            3,
            "release renderer, tensor cores",
            MMA_FINE_TOL,
        );
    }

    /// The fine image (a sigmoid's output in 0..1) from f16 convolution inputs: ~40 layers
    /// each adding a few 1e-4 relative.
    const MMA_FINE_TOL: f64 = 2e-2;
}
