//! The renderer's StyleGAN2 decoder (`upsampler.stylegan_decoder`, spec section 8) for training:
//! a forward that keeps every value its backward reads, and the backward to the gradients of
//! all its parameters, of the style code and of the SFT conditions. The CPU module is
//! `gagavatar_net::style_unet::StyleGan2Decoder`; the forward computes what it computes (RGB
//! before the sigmoid) with the fixed noise maps.
//!
//! Layout. The biases, noise weights, styles and demodulation factors share one vector buffer
//! (the convolutions' epilogues read them there), and so do their gradients, at the same
//! offsets; the style modulations of all layers are one stacked linear layer, as in the
//! inference renderer. Parameters are listed by checkpoint key with where their values and
//! gradients live ([`Param`]).

use std::f32::consts::SQRT_2;

use gagavatar_net::style_unet::noise_resolution;
use gagavatar_net::ModelConfig;

use super::conv::{conv_backward, part_floats, row_sums, ConvGrad};
use super::layers::{act_backward, resize_backward, rms_norm_backward, Kept};
use super::modconv::{modconv_backward, ModConvGrad, ModConvScratch};
pub use super::params::Param;
use super::params::{Packed, ParamSource, Store};
use crate::conv::{Act, At, Conv, Ops};
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Params, Step};
use crate::renderer::{get, WeightFn};
use crate::tuning::Tuning;

const ENERGY: &str = include_str!("../shaders/energy.wgsl");
const SFT: &str = include_str!("../shaders/sft.wgsl");

/// One modulated convolution's buffers and offsets.
struct ModLayer {
    cin: usize,
    cout: usize,
    k: usize,
    weight: usize,
    grad_weight: usize,
    style: u32,
    demod: Option<u32>,
    energy: Option<wgpu::Buffer>,
    bias: u32,
    noise_weight: Option<u32>,
}

/// The decoder's training forward and backward, recorded once.
pub struct GpuDecoderGrad {
    pub size: usize,
    /// Input: the style code `[style_dim]`.
    pub code: wgpu::Buffer,
    /// Input: the SFT conditions of resolutions 8 .. size, each `[2 c, r, r]` (scale, then
    /// shift; `c` the decoder's channels at `r`).
    pub conditions: Vec<wgpu::Buffer>,
    /// Output: RGB before the sigmoid `[3, size, size]`.
    pub rgb: wgpu::Buffer,
    /// Input of the backward: the loss gradient of `rgb`.
    pub grad_rgb: wgpu::Buffer,
    pub grad_code: wgpu::Buffer,
    /// The gradients of `conditions`, laid out as they are.
    pub grad_conditions: Vec<wgpu::Buffer>,
    /// Parameter and gradient buffers ([`Param`] indexes them).
    pub buffers: Vec<wgpu::Buffer>,
    pub params: Vec<Param>,
    /// The noise maps the style convolutions add, `noise{i}` at `noise_at[i]`.
    noise: wgpu::Buffer,
    noise_at: Vec<usize>,
    forward: Vec<Step>,
    backward: Vec<Step>,
}

impl GpuDecoderGrad {
    /// Uploads the decoder's weights (keys relative to `upsampler.`) and records its forward
    /// and backward.
    pub fn new(gpu: &Gpu, tuning: &Tuning, cfg: &ModelConfig, weights: &WeightFn) -> Result<Self> {
        cfg.validate().map_err(GpuError::Unsupported)?;
        // f32 throughout: f16 tensor-core inputs need loss scaling for the gradients first.
        let tuning = &Tuning {
            mma: false,
            ..tuning.for_device(gpu)
        };
        tuning.check(&gpu.limits)?;
        let s = cfg.image_size;
        let levels = cfg.renderer_levels();
        let dc = |r: usize| cfg.decoder_channels(r);
        let sd = cfg.style_dim;
        let dp = "stylegan_decoder";
        let mut st = Store::new(gpu);
        // The shared vectors: biases and noise weights, then the styles and demodulation
        // factors (reserved: kernels write them).
        let mut vecs_host = Packed::default();

        let mut mlp = Vec::with_capacity(cfg.style_mlp_layers);
        for i in 0..cfg.style_mlp_layers {
            let key = format!("{dp}.style_mlp.{}", 2 * i + 1);
            let w = st.param(
                &format!("{key}.weight"),
                get(weights, &format!("{key}.weight"), sd * sd)?,
            );
            let b = st.param(
                &format!("{key}.bias"),
                get(weights, &format!("{key}.bias"), sd)?,
            );
            mlp.push((w, b));
        }
        let c4 = dc(4);
        let constant = st.param(
            &format!("{dp}.constant_input.weight"),
            get(weights, &format!("{dp}.constant_input.weight"), c4 * 16)?,
        );
        // Modulated layers in the forward's order: style_conv1, to_rgb1, then per level the
        // two style convs and the to_rgb.
        let (mut mod_w, mut mod_b) = (Packed::default(), Packed::default());
        let mut layers: Vec<ModLayer> = Vec::new();
        let mut load = |st: &mut Store,
                        host: &mut Packed,
                        key: &str,
                        (cin, cout, k): (usize, usize, usize),
                        demodulate: bool|
         -> Result<ModLayer> {
            let mc = format!("{key}.modulated_conv");
            let w = get(weights, &format!("{mc}.weight"), cout * cin * k * k)?;
            let (wv, wg) = st.param(&format!("{mc}.weight"), w);
            let mk = format!("{mc}.modulation");
            mod_w.push(
                format!("{mk}.weight"),
                &get(weights, &format!("{mk}.weight"), cin * sd)?,
            );
            let row = mod_b.push(
                format!("{mk}.bias"),
                &get(weights, &format!("{mk}.bias"), cin)?,
            );
            let bias = host.push(
                format!("{key}.bias"),
                &get(weights, &format!("{key}.bias"), cout)?,
            ) as u32;
            let noise_weight = if demodulate {
                Some(host.push(
                    format!("{key}.weight"),
                    &get(weights, &format!("{key}.weight"), 1)?,
                ) as u32)
            } else {
                None
            };
            Ok(ModLayer {
                cin,
                cout,
                k,
                weight: wv,
                grad_weight: wg,
                // Relative to the styles' block; made absolute below.
                style: row as u32,
                demod: demodulate.then_some(0),
                energy: demodulate.then(|| gpu.buffer("kernel energy", 4 * (cout * cin) as u64)),
                bias,
                noise_weight,
            })
        };
        layers.push(load(
            &mut st,
            &mut vecs_host,
            &format!("{dp}.style_conv1"),
            (c4, c4, 3),
            true,
        )?);
        layers.push(load(
            &mut st,
            &mut vecs_host,
            &format!("{dp}.to_rgb1"),
            (c4, 3, 1),
            false,
        )?);
        for k in 0..levels {
            let r = 8 << k;
            let (cin, cout) = (dc(r / 2), dc(r));
            let a = format!("{dp}.style_convs.{}", 2 * k);
            let b = format!("{dp}.style_convs.{}", 2 * k + 1);
            layers.push(load(&mut st, &mut vecs_host, &a, (cin, cout, 3), true)?);
            layers.push(load(&mut st, &mut vecs_host, &b, (cout, cout, 3), true)?);
            layers.push(load(
                &mut st,
                &mut vecs_host,
                &format!("{dp}.to_rgbs.{k}"),
                (cout, 3, 1),
                false,
            )?);
        }
        let styles_rows = mod_b.host.len();
        let styles_at = vecs_host.reserve(styles_rows);
        for l in &mut layers {
            l.style += styles_at as u32;
            if l.demod.is_some() {
                l.demod = Some(vecs_host.reserve(l.cout) as u32);
            }
        }
        let (vecs, grad_vecs) = st.packed("decoder vectors", vecs_host);
        let (mod_wb, mod_wg) = st.packed("style modulations", mod_w);
        let (mod_bb, mod_bg) = st.packed("style modulation biases", mod_b);
        let mut noise_host = Vec::new();
        let mut noise_at = Vec::new();
        for i in 0..2 * levels + 1 {
            let r = noise_resolution(i);
            noise_at.push(noise_host.len());
            noise_host.extend(get(weights, &format!("{dp}.noises.noise{i}"), r * r)?);
        }
        let noise = gpu.buffer_with("decoder noise", &noise_host);

        let b = |i: usize| &st.buffers[i];
        let dummy = gpu.buffer("unused", 16);
        let mut split_need = 0;
        for (i, l) in layers.iter().enumerate() {
            let r = layer_resolution(i);
            split_need = split_need
                .max(Ops::split_need(tuning, l.cin, l.cout, r, r, l.k))
                .max(Ops::split_need(tuning, l.cout, l.cin, r, r, l.k));
        }
        // The linear layers' input gradients run as 1x1 convolutions of one pixel.
        split_need = split_need
            .max(Ops::split_need(tuning, styles_rows, sd, 1, 1, 1))
            .max(Ops::split_need(tuning, sd, sd, 1, 1, 1));
        let split = gpu.buffer("split-K partial sums", 4 * split_need.max(1) as u64);
        let ops = Ops {
            gpu,
            tuning,
            vecs: b(vecs),
            dummy: &dummy,
            split_scratch: &split,
        };
        let act = |label: &str, n: usize| gpu.buffer(label, 4 * n as u64);

        // ---- Forward.
        let mut fwd = Vec::new();
        let code = act("style code", sd);
        let mut lats = vec![act("latent 0", sd)];
        fwd.push(ops.rms_norm(sd, &code, &lats[0])?);
        for (w, bb) in &mlp {
            let next = act("latent", sd);
            fwd.push(ops.linear(
                sd,
                sd,
                At::new(&lats[lats.len() - 1]),
                b(w.0),
                b(bb.0),
                true,
                At::new(&next),
            )?);
            lats.push(next);
        }
        let lat = &lats[lats.len() - 1];
        fwd.push(ops.linear(
            sd,
            styles_rows,
            At::new(lat),
            b(mod_wb),
            b(mod_bb),
            false,
            At::off(b(vecs), styles_at),
        )?);
        let energy_kernel = gpu.kernel(
            "energy",
            ENERGY,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        for l in &layers {
            if let (Some(off), Some(e)) = (l.demod, &l.energy) {
                let n = l.cout * l.cin;
                let u = gpu.uniform(
                    "energy",
                    &Params::new().u(n as u32).u((l.k * l.k) as u32).u(0).u(0),
                );
                let g = gpu.bind(&energy_kernel, &[&u, b(l.weight), e])?;
                fwd.push(Step::new(energy_kernel.clone(), g, linear_grid(n, 256)));
                fwd.push(ops.demod(l.cin, l.cout, e, l.style, off, SQRT_2)?);
            }
        }
        let modconv = |l: &ModLayer,
                       r: usize,
                       input: At<'_>,
                       out: At<'_>,
                       noise_i: Option<usize>,
                       residual: Option<At<'_>>| {
            ops.conv(&Conv {
                cin: l.cin,
                cout: l.cout,
                h: r,
                w: r,
                k: l.k,
                input,
                weight: b(l.weight),
                bias: Some(l.bias),
                in_scale: Some(l.style),
                out_scale: l.demod,
                noise: noise_i
                    .zip(l.noise_weight)
                    .map(|(i, w)| (At::off(&noise, noise_at[i]), w)),
                in_relu: false,
                act: if l.demod.is_some() {
                    Act::Lrelu
                } else {
                    Act::None
                },
                residual,
                sft: None,
                sigmoid: false,
                out,
            })
        };
        let sft_kernel = |mode: u32| {
            gpu.kernel(
                "sft",
                SFT,
                &[("MODE", mode.to_string())],
                &[
                    Bind::Uniform,
                    Bind::Read,
                    Bind::Read,
                    Bind::Read,
                    Bind::ReadWrite,
                    Bind::ReadWrite,
                ],
            )
        };
        // Activations: `outs[j]` the layer outputs (after leaky ReLU), `rgbs` the RGB skips.
        let out0 = act("style_conv1", c4 * 16);
        fwd.extend(modconv(
            &layers[0],
            4,
            At::new(b(constant.0)),
            At::new(&out0),
            Some(0),
            None,
        )?);
        let rgb0 = act("to_rgb1", 3 * 16);
        fwd.extend(modconv(
            &layers[1],
            4,
            At::new(&out0),
            At::new(&rgb0),
            None,
            None,
        )?);
        let conditions: Vec<wgpu::Buffer> = (0..levels)
            .map(|k| {
                let r = 8 << k;
                act("sft condition", 2 * dc(r) * r * r)
            })
            .collect();
        struct Level {
            up: wgpu::Buffer,
            o1a: wgpu::Buffer,
            o1: wgpu::Buffer,
            o2: wgpu::Buffer,
            rgb_up: wgpu::Buffer,
            rgb: wgpu::Buffer,
        }
        let mut lv: Vec<Level> = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = 8 << k;
            let (la, lb, lr) = (&layers[2 + 3 * k], &layers[3 + 3 * k], &layers[4 + 3 * k]);
            let (prev_out, prev_rgb) = match k {
                0 => (&out0, &rgb0),
                _ => (&lv[k - 1].o2, &lv[k - 1].rgb),
            };
            let level = Level {
                up: act("decoder x2", la.cin * r * r),
                o1a: act("style conv up", la.cout * r * r),
                o1: act("style conv up, SFT", la.cout * r * r),
                o2: act("style conv", lb.cout * r * r),
                rgb_up: act("rgb x2", 3 * r * r),
                rgb: act("to_rgb", 3 * r * r),
            };
            fwd.push(ops.resize(
                true,
                la.cin,
                r / 2,
                r / 2,
                At::new(prev_out),
                At::new(&level.up),
            )?);
            fwd.extend(modconv(
                la,
                r,
                At::new(&level.up),
                At::new(&level.o1a),
                Some(2 * k + 1),
                None,
            )?);
            let n = la.cout * r * r;
            let sk = sft_kernel(0)?;
            let u = gpu.uniform("sft", &Params::new().u(n as u32).u(0).u(0).u(0));
            let g = gpu.bind(
                &sk,
                &[
                    &u,
                    &level.o1a,
                    &conditions[k],
                    &dummy,
                    &level.o1,
                    &spare_output(gpu),
                ],
            )?;
            fwd.push(Step::new(sk, g, linear_grid(n, 256)));
            fwd.extend(modconv(
                lb,
                r,
                At::new(&level.o1),
                At::new(&level.o2),
                Some(2 * k + 2),
                None,
            )?);
            fwd.push(ops.resize(
                true,
                3,
                r / 2,
                r / 2,
                At::new(prev_rgb),
                At::new(&level.rgb_up),
            )?);
            fwd.extend(modconv(
                lr,
                r,
                At::new(&level.o2),
                At::new(&level.rgb),
                None,
                Some(At::new(&level.rgb_up)),
            )?);
            lv.push(level);
        }
        let rgb = match lv.last() {
            Some(l) => l.rgb.clone(),
            None => rgb0.clone(),
        };

        // ---- Backward.
        let mut bwd = Vec::new();
        let gvecs = b(grad_vecs);
        let grad_rgb = act("rgb gradient", 3 * s * s);
        let grad_conditions: Vec<wgpu::Buffer> = conditions
            .iter()
            .map(|c| gpu.buffer("sft condition gradient", c.size()))
            .collect();
        // Scratch shared by the layers: the rotated weights and the partial sums.
        let mut flipped_need = 1;
        let mut part_need = 1;
        for (i, l) in layers.iter().enumerate() {
            let r = layer_resolution(i);
            flipped_need = flipped_need.max(l.cin * l.cout * l.k * l.k);
            // Row sums for the bias and, in the style convs, the noise weight.
            part_need = part_need.max(part_floats(tuning.conv, (l.cin, l.cout, r * r, l.k), true));
        }
        part_need = part_need.max(styles_rows * sd).max(sd * sd);
        flipped_need = flipped_need.max(styles_rows * sd).max(sd * sd);
        let flipped = act("rotated weights", flipped_need);
        let part = act("partial sums", part_need);
        let mut scratches = Vec::new();
        // d(layer output) -> gradients of the layer; returns the input-gradient buffer.
        let mut layer_backward = |bwd: &mut Vec<Step>,
                                  i: usize,
                                  input: &wgpu::Buffer,
                                  kept_out: Option<&wgpu::Buffer>,
                                  grad_out: &wgpu::Buffer,
                                  noise_i: Option<usize>,
                                  grad_input: Option<&wgpu::Buffer>|
         -> Result<()> {
            let l = &layers[i];
            let r = layer_resolution(i);
            let n = l.cout * r * r;
            // dZ: through the leaky ReLU where the layer has one.
            let dz = match kept_out {
                Some(y) => {
                    let dz = act("dZ", n);
                    bwd.push(act_backward(
                        gpu,
                        Kept::LreluOutput,
                        n,
                        At::new(y),
                        At::new(grad_out),
                        At::new(&dz),
                    )?);
                    dz
                }
                None => grad_out.clone(),
            };
            let m = ModConvGrad {
                conv: ConvGrad {
                    cin: l.cin,
                    cout: l.cout,
                    h: r,
                    w: r,
                    k: l.k,
                    input: At::new(input),
                    weight: b(l.weight),
                    grad_out: At::new(&dz),
                    grad_input: grad_input.map(At::new),
                    grad_weight: At::new(b(l.grad_weight)),
                    grad_bias: Some(At::off(gvecs, l.bias as usize)),
                    accumulate: false,
                },
                style: l.style,
                demod: l.demod,
                gain: if l.demod.is_some() { SQRT_2 } else { 1.0 },
                grad_style: At::off(gvecs, l.style as usize),
            };
            let scratch = ModConvScratch::new(gpu, &m);
            bwd.extend(modconv_backward(&ops, &m, &flipped, &part, &scratch)?);
            scratches.push(scratch);
            if let (Some(ni), Some(w)) = (noise_i, l.noise_weight) {
                bwd.extend(row_sums(
                    &ops,
                    (l.cout, r * r),
                    At::new(&dz),
                    Some(At::off(&noise, noise_at[ni])),
                    &part,
                    At::off(gvecs, w as usize),
                    false,
                    true,
                )?);
            }
            Ok(())
        };
        // Levels, last first. `d_out` / `d_rgb`: the gradients of the previous level's outputs.
        let mut d_rgb = grad_rgb.clone();
        let mut d_out_from_next: Option<wgpu::Buffer> = None;
        for k in (0..levels).rev() {
            let r = 8 << k;
            let l = &lv[k];
            let (ia, ib, ir) = (2 + 3 * k, 3 + 3 * k, 4 + 3 * k);
            let cb = layers[ib].cout;
            // to_rgb: its input o2 gets dX; the upsampled skip gets d_rgb.
            let d_o2_rgb = act("d o2 (rgb)", cb * r * r);
            layer_backward(&mut bwd, ir, &l.o2, None, &d_rgb, None, Some(&d_o2_rgb))?;
            let d_rgb_prev = act("d rgb", 3 * (r / 2) * (r / 2));
            bwd.push(resize_backward(
                gpu,
                true,
                (3, r / 2, r / 2),
                At::new(&d_rgb),
                At::new(&d_rgb_prev),
            )?);
            let d_o2 = match d_out_from_next.take() {
                Some(from_next) => {
                    let sum = act("d o2", cb * r * r);
                    bwd.push(ops.add(cb * r * r, &d_o2_rgb, &from_next, &sum)?);
                    sum
                }
                None => d_o2_rgb,
            };
            // Second style conv.
            let ca = layers[ia].cout;
            let d_o1 = act("d o1", ca * r * r);
            layer_backward(
                &mut bwd,
                ib,
                &l.o1,
                Some(&l.o2),
                &d_o2,
                Some(2 * k + 2),
                Some(&d_o1),
            )?;
            // SFT.
            let n = ca * r * r;
            let d_o1a = act("d o1a", n);
            let sk = sft_kernel(1)?;
            let u = gpu.uniform("sft backward", &Params::new().u(n as u32).u(0).u(0).u(0));
            let g = gpu.bind(
                &sk,
                &[
                    &u,
                    &l.o1a,
                    &conditions[k],
                    &d_o1,
                    &d_o1a,
                    &grad_conditions[k],
                ],
            )?;
            bwd.push(Step::new(sk, g, linear_grid(n, 256)));
            // First style conv (after the x2 upsampling).
            let cin = layers[ia].cin;
            let d_up = act("d up", cin * r * r);
            layer_backward(
                &mut bwd,
                ia,
                &l.up,
                Some(&l.o1a),
                &d_o1a,
                Some(2 * k + 1),
                Some(&d_up),
            )?;
            let d_prev = act("d out", cin * (r / 2) * (r / 2));
            bwd.push(resize_backward(
                gpu,
                true,
                (cin, r / 2, r / 2),
                At::new(&d_up),
                At::new(&d_prev),
            )?);
            d_out_from_next = Some(d_prev);
            d_rgb = d_rgb_prev;
        }
        // to_rgb1 and style_conv1 at 4x4.
        let d_out0_rgb = act("d out0 (rgb)", c4 * 16);
        layer_backward(&mut bwd, 1, &out0, None, &d_rgb, None, Some(&d_out0_rgb))?;
        let d_out0 = match d_out_from_next.take() {
            Some(from_next) => {
                let sum = act("d out0", c4 * 16);
                bwd.push(ops.add(c4 * 16, &d_out0_rgb, &from_next, &sum)?);
                sum
            }
            None => d_out0_rgb,
        };
        layer_backward(
            &mut bwd,
            0,
            b(constant.0),
            Some(&out0),
            &d_out0,
            Some(0),
            Some(b(constant.1)),
        )?;
        // The styles' gradients (all layers) through the stacked modulation to the latent.
        let d_lat = act("d latent", sd);
        let stacked = ConvGrad {
            cin: sd,
            cout: styles_rows,
            h: 1,
            w: 1,
            k: 1,
            input: At::new(lat),
            weight: b(mod_wb),
            grad_out: At::off(gvecs, styles_at),
            grad_input: Some(At::new(&d_lat)),
            grad_weight: At::new(b(mod_wg)),
            grad_bias: Some(At::new(b(mod_bg))),
            accumulate: false,
        };
        bwd.extend(conv_backward(&ops, &stacked, &flipped, &part)?);
        // The mapping network, last layer first, then the normalisation.
        let mut d = d_lat;
        for (i, (w, bb)) in mlp.iter().enumerate().rev() {
            let dz = act("d mapping", sd);
            bwd.push(act_backward(
                gpu,
                Kept::LreluOutput,
                sd,
                At::new(&lats[i + 1]),
                At::new(&d),
                At::new(&dz),
            )?);
            let dx = act("d latent", sd);
            let lin = ConvGrad {
                cin: sd,
                cout: sd,
                h: 1,
                w: 1,
                k: 1,
                input: At::new(&lats[i]),
                weight: b(w.0),
                grad_out: At::new(&dz),
                grad_input: Some(At::new(&dx)),
                grad_weight: At::new(b(w.1)),
                grad_bias: Some(At::new(b(bb.1))),
                accumulate: false,
            };
            bwd.extend(conv_backward(&ops, &lin, &flipped, &part)?);
            d = dx;
        }
        let grad_code = act("style code gradient", sd);
        bwd.push(rms_norm_backward(gpu, sd, &code, &d, &grad_code)?);

        Ok(Self {
            size: s,
            code,
            conditions,
            rgb,
            grad_rgb,
            grad_code,
            grad_conditions,
            buffers: st.buffers,
            params: st.params,
            noise,
            noise_at,
            forward: fwd,
            backward: bwd,
        })
    }

    /// Replaces the noise maps (the checkpoint's at construction) for the next forward: map
    /// `i` is `[noise_resolution(i)^2]`, as `gagavatar_net::style_unet::seeded_noise` draws
    /// one sample's.
    pub fn set_noise(&self, gpu: &Gpu, maps: &[Vec<f32>]) -> Result<()> {
        if maps.len() != self.noise_at.len() {
            return Err(GpuError::Input {
                name: "decoder noise".into(),
                reason: format!("{} maps, expected {}", maps.len(), self.noise_at.len()),
            });
        }
        for (i, (m, &at)) in maps.iter().zip(&self.noise_at).enumerate() {
            let r = noise_resolution(i);
            if m.len() != r * r {
                return Err(GpuError::Input {
                    name: format!("decoder noise map {i}"),
                    reason: format!("{} values, expected {r}x{r}", m.len()),
                });
            }
            gpu.queue
                .write_buffer(&self.noise, 4 * at as u64, bytemuck::cast_slice(m));
        }
        Ok(())
    }

    /// Overwrites every trained parameter with `value(key)` (keys relative to `upsampler.`,
    /// values flattened in the checkpoint's layout).
    pub fn set_weights(&self, gpu: &Gpu, value: &ParamSource) -> Result<()> {
        super::params::write_params(gpu, &self.buffers, &self.params, value)
    }

    pub fn forward_steps(&self) -> &[Step] {
        &self.forward
    }

    /// Needs the forward's values of the same inputs (run the forward first).
    pub fn backward_steps(&self) -> &[Step] {
        &self.backward
    }

    /// Every parameter's gradient, read back, by key.
    pub fn read_grads(&self, gpu: &Gpu) -> Result<Vec<(String, Vec<f32>)>> {
        super::params::read_grads(gpu, &self.buffers, &self.params)
    }
}

/// The resolution of modulated layer `i` in forward order (style_conv1, to_rgb1, then three
/// per level from 8 up).
fn layer_resolution(i: usize) -> usize {
    if i < 2 {
        4
    } else {
        8 << ((i - 2) / 3)
    }
}

/// A 4-byte buffer bound where the forward SFT pass has no second output.
fn spare_output(gpu: &Gpu) -> wgpu::Buffer {
    gpu.buffer("unused sft output", 4)
}
