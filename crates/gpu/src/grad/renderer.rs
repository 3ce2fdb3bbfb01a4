//! The whole neural renderer (`upsampler`, the StyleUNet of spec section 8) for training on the
//! GPU: the U-Net encoder with its SFT condition branches (here), the StyleGAN2 decoder
//! ([`super::decoder`]) and the final sigmoid, forward with every value the backward reads
//! kept, and backward to the gradients of every parameter and of the splatted input image. The
//! CPU module is `gagavatar_net::style_unet::StyleUNet` with its fixed noise maps.
//!
//! Unlike the inference renderer, each convolution keeps its output before a residual is
//! added, and the condition branches' first convolutions run separately (the inference path
//! fuses the pair into one).

use gagavatar_net::ModelConfig;

use super::conv::{conv_backward, part_floats, ConvGrad};
use super::decoder::GpuDecoderGrad;
use super::layers::{act_backward, resize_backward, Kept};
use super::params::{read_grads, write_params, Packed, Param, ParamSource, Store};
use crate::conv::{Act, At, Conv, Ops};
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Params, Step};
use crate::renderer::{get, WeightFn};
use crate::tuning::Tuning;

const SIGMOID: &str = include_str!("../shaders/sigmoid.wgsl");

/// A plain convolution's parameters: weight and gradient buffers (indices into the store),
/// the bias's offset in the vector buffers.
#[derive(Debug, Clone, Copy)]
struct Layer {
    cin: usize,
    cout: usize,
    k: usize,
    weight: usize,
    grad_weight: usize,
    bias: Option<u32>,
}

/// One ResBlock's layers.
struct Block {
    conv1: Layer,
    conv2: Layer,
    skip: Layer,
}

/// What a ResBlock's forward keeps (see [`GpuRendererGrad::new`]).
struct BlockActs {
    /// `lrelu(conv1(x))` at the input resolution.
    h: wgpu::Buffer,
    /// `h` resized.
    h_resized: wgpu::Buffer,
    /// down: `x` resized (the skip's input); up: unused (the skip reads `x`).
    x_resized: Option<wgpu::Buffer>,
    /// The skip's output, before (up) its x2 resize.
    skip: wgpu::Buffer,
    /// up: the skip resized.
    skip_up: Option<wgpu::Buffer>,
    /// `lrelu(conv2(h_resized))`.
    main: wgpu::Buffer,
    /// `main + skip` (the block's output).
    out: wgpu::Buffer,
}

/// The renderer's training forward and backward, recorded once.
pub struct GpuRendererGrad {
    pub size: usize,
    /// Input: the splatted image `[color_dim, size, size]`.
    pub input: wgpu::Buffer,
    /// Output: RGB in [0, 1] `[3, size, size]`.
    pub output: wgpu::Buffer,
    /// Input of the backward: the loss gradient of `output`.
    pub grad_output: wgpu::Buffer,
    /// The gradient of `input`.
    pub grad_input: wgpu::Buffer,
    pub decoder: GpuDecoderGrad,
    /// The U-Net's parameter and gradient buffers ([`Param`] indexes them).
    pub buffers: Vec<wgpu::Buffer>,
    pub params: Vec<Param>,
    forward: Vec<Step>,
    backward: Vec<Step>,
}

impl GpuRendererGrad {
    /// Uploads the renderer's weights (keys relative to `upsampler.`) and records its forward
    /// and backward.
    pub fn new(gpu: &Gpu, tuning: &Tuning, cfg: &ModelConfig, weights: &WeightFn) -> Result<Self> {
        let decoder = GpuDecoderGrad::new(gpu, tuning, cfg, weights)?;
        // f32 throughout: f16 tensor-core inputs need loss scaling for the gradients first.
        let tuning = &Tuning {
            mma: false,
            ..tuning.for_device(gpu)
        };
        let s = cfg.image_size;
        let levels = cfg.renderer_levels();
        let u = |r: usize| cfg.unet_channels(r);
        let dc = |r: usize| cfg.decoder_channels(r);
        let sd = cfg.style_dim;
        let mut st = Store::new(gpu);
        let mut vecs_host = Packed::default();
        let mut conv = |st: &mut Store,
                        key: &str,
                        (cin, cout, k): (usize, usize, usize),
                        bias: bool|
         -> Result<Layer> {
            let (weight, grad_weight) = st.param(
                &format!("{key}.weight"),
                get(weights, &format!("{key}.weight"), cout * cin * k * k)?,
            );
            let bias = if bias {
                let b = get(weights, &format!("{key}.bias"), cout)?;
                Some(vecs_host.push(format!("{key}.bias"), &b) as u32)
            } else {
                None
            };
            Ok(Layer {
                cin,
                cout,
                k,
                weight,
                grad_weight,
                bias,
            })
        };
        let first = conv(&mut st, "conv_body_first", (cfg.color_dim, u(s), 1), true)?;
        let mut down = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = s >> k;
            let p = format!("conv_body_down.{k}");
            down.push(Block {
                conv1: conv(&mut st, &format!("{p}.conv1"), (u(r), u(r), 3), true)?,
                conv2: conv(&mut st, &format!("{p}.conv2"), (u(r), u(r / 2), 3), true)?,
                skip: conv(&mut st, &format!("{p}.skip"), (u(r), u(r / 2), 1), false)?,
            });
        }
        let final_conv = conv(&mut st, "final_conv", (u(4), u(4), 3), true)?;
        let fl_in = u(4) * 16;
        let final_linear = conv(&mut st, "final_linear", (fl_in, sd, 1), true)?;
        let mut up = Vec::with_capacity(levels);
        let mut branches = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = 8 << k;
            let p = format!("conv_body_up.{k}");
            up.push(Block {
                conv1: conv(
                    &mut st,
                    &format!("{p}.conv1"),
                    (u(r / 2), u(r / 2), 3),
                    true,
                )?,
                conv2: conv(&mut st, &format!("{p}.conv2"), (u(r / 2), u(r), 3), true)?,
                skip: conv(&mut st, &format!("{p}.skip"), (u(r / 2), u(r), 1), false)?,
            });
            let mut branch = |name: &str| -> Result<(Layer, Layer)> {
                Ok((
                    conv(&mut st, &format!("{name}.{k}.0"), (u(r), u(r), 3), true)?,
                    conv(&mut st, &format!("{name}.{k}.2"), (u(r), dc(r), 3), true)?,
                ))
            };
            let scale = branch("condition_scale")?;
            let shift = branch("condition_shift")?;
            branches.push((scale, shift));
        }
        let (vecs, grad_vecs) = st.packed("u-net biases", vecs_host);

        // Scratch: split-K sums of the forward and backward convolutions, rotated weights and
        // the weight gradients' partial sums.
        let dummy = gpu.buffer("unused", 16);
        let mut layers: Vec<(Layer, usize)> = vec![(first, s), (final_conv, 4), (final_linear, 1)];
        for (k, b) in down.iter().enumerate() {
            let r = s >> k;
            layers.extend([(b.conv1, r), (b.conv2, r / 2), (b.skip, r / 2)]);
        }
        for k in 0..levels {
            let r = 8 << k;
            let b = &up[k];
            let ((s0, s2), (h0, h2)) = branches[k];
            layers.extend([
                (b.conv1, r / 2),
                (b.conv2, r),
                (b.skip, r / 2),
                (s0, r),
                (s2, r),
                (h0, r),
                (h2, r),
            ]);
        }
        let (mut split_need, mut flipped_need, mut part_need) = (1, 1, 1);
        for (l, r) in &layers {
            split_need = split_need
                .max(Ops::split_need(tuning, l.cin, l.cout, *r, *r, l.k))
                .max(Ops::split_need(tuning, l.cout, l.cin, *r, *r, l.k));
            flipped_need = flipped_need.max(l.cin * l.cout * l.k * l.k);
            part_need = part_need.max(part_floats(
                tuning.conv,
                (l.cin, l.cout, r * r, l.k),
                l.bias.is_some(),
            ));
        }
        let split = gpu.buffer("split-K partial sums", 4 * split_need as u64);
        let flipped = gpu.buffer("rotated weights", 4 * flipped_need as u64);
        let part = gpu.buffer("partial sums", 4 * part_need as u64);
        let b = |i: usize| &st.buffers[i];
        let ops = Ops {
            gpu,
            tuning,
            vecs: b(vecs),
            dummy: &dummy,
            split_scratch: &split,
        };
        let act = |label: &str, n: usize| gpu.buffer(label, 4 * n as u64);
        let fconv = |l: &Layer, r: usize, input: At<'_>, out: At<'_>, lrelu: bool| {
            ops.conv(&Conv {
                cin: l.cin,
                cout: l.cout,
                h: r,
                w: r,
                k: l.k,
                input,
                weight: b(l.weight),
                bias: l.bias,
                in_scale: None,
                out_scale: None,
                noise: None,
                in_relu: false,
                act: if lrelu { Act::Lrelu } else { Act::None },
                residual: None,
                sft: None,
                sigmoid: false,
                out,
            })
        };

        // ---- Forward: U-Net encoder.
        let input = act("renderer input", cfg.color_dim * s * s);
        let mut fwd = Vec::new();
        let f0 = act("conv_body_first", u(s) * s * s);
        fwd.extend(fconv(&first, s, At::new(&input), At::new(&f0), true)?);
        let mut downs: Vec<BlockActs> = Vec::with_capacity(levels);
        for (k, blk) in down.iter().enumerate() {
            let r = s >> k;
            let (ci, co) = (blk.conv1.cin, blk.conv2.cout);
            let x = match k {
                0 => &f0,
                _ => &downs[k - 1].out,
            };
            let a = BlockActs {
                h: act("down h", ci * r * r),
                h_resized: act("down h/2", ci * r * r / 4),
                x_resized: Some(act("down x/2", ci * r * r / 4)),
                skip: act("down skip", co * r * r / 4),
                skip_up: None,
                main: act("down main", co * r * r / 4),
                out: act("down out", co * r * r / 4),
            };
            let xr = a.x_resized.as_ref().unwrap_or(&dummy);
            fwd.extend(fconv(&blk.conv1, r, At::new(x), At::new(&a.h), true)?);
            fwd.push(ops.resize(false, ci, r, r, At::new(&a.h), At::new(&a.h_resized))?);
            fwd.push(ops.resize(false, ci, r, r, At::new(x), At::new(xr))?);
            fwd.extend(fconv(
                &blk.skip,
                r / 2,
                At::new(xr),
                At::new(&a.skip),
                false,
            )?);
            fwd.extend(fconv(
                &blk.conv2,
                r / 2,
                At::new(&a.h_resized),
                At::new(&a.main),
                true,
            )?);
            fwd.push(ops.add(co * r * r / 4, &a.main, &a.skip, &a.out)?);
            downs.push(a);
        }
        let last_down = match downs.last() {
            Some(a) => &a.out,
            None => &f0,
        };
        let feat = act("final_conv", u(4) * 16);
        fwd.extend(fconv(
            &final_conv,
            4,
            At::new(last_down),
            At::new(&feat),
            true,
        )?);
        fwd.extend(fconv(
            &final_linear,
            1,
            At::new(&feat),
            At::new(&decoder.code),
            false,
        )?);
        // U-Net decoder and the condition branches, written into the decoder's inputs.
        let mut ups: Vec<(wgpu::Buffer, BlockActs, [wgpu::Buffer; 2])> = Vec::with_capacity(levels);
        for k in 0..levels {
            let r = 8 << k;
            let blk = &up[k];
            let (ci, co) = (blk.conv1.cin, blk.conv2.cout);
            let prev = match k {
                0 => &feat,
                _ => &ups[k - 1].1.out,
            };
            let x = act("up in", ci * r * r / 4);
            fwd.push(ops.add(ci * r * r / 4, prev, &downs[levels - 1 - k].out, &x)?);
            let a = BlockActs {
                h: act("up h", ci * r * r / 4),
                h_resized: act("up h x2", ci * r * r),
                x_resized: None,
                skip: act("up skip", co * r * r / 4),
                skip_up: Some(act("up skip x2", co * r * r)),
                main: act("up main", co * r * r),
                out: act("up out", co * r * r),
            };
            let su = a.skip_up.as_ref().unwrap_or(&dummy);
            fwd.extend(fconv(&blk.conv1, r / 2, At::new(&x), At::new(&a.h), true)?);
            fwd.push(ops.resize(true, ci, r / 2, r / 2, At::new(&a.h), At::new(&a.h_resized))?);
            fwd.extend(fconv(
                &blk.skip,
                r / 2,
                At::new(&x),
                At::new(&a.skip),
                false,
            )?);
            fwd.push(ops.resize(true, co, r / 2, r / 2, At::new(&a.skip), At::new(su))?);
            fwd.extend(fconv(
                &blk.conv2,
                r,
                At::new(&a.h_resized),
                At::new(&a.main),
                true,
            )?);
            fwd.push(ops.add(co * r * r, &a.main, su, &a.out)?);
            let ((s0, s2), (h0, h2)) = &branches[k];
            let mids = [
                act("condition_scale 0", co * r * r),
                act("condition_shift 0", co * r * r),
            ];
            let n = dc(r) * r * r;
            fwd.extend(fconv(s0, r, At::new(&a.out), At::new(&mids[0]), true)?);
            fwd.extend(fconv(
                s2,
                r,
                At::new(&mids[0]),
                At::off(&decoder.conditions[k], 0),
                false,
            )?);
            fwd.extend(fconv(h0, r, At::new(&a.out), At::new(&mids[1]), true)?);
            fwd.extend(fconv(
                h2,
                r,
                At::new(&mids[1]),
                At::off(&decoder.conditions[k], n),
                false,
            )?);
            ups.push((x, a, mids));
        }
        fwd.extend(decoder.forward_steps().iter().cloned());
        let output = act("renderer output", 3 * s * s);
        let sig = gpu.kernel(
            "sigmoid",
            SIGMOID,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let n_out = 3 * s * s;
        let u_sig = gpu.uniform("sigmoid", &Params::new().u(n_out as u32).u(0).u(0).u(0));
        let g_sig = gpu.bind(&sig, &[&u_sig, &decoder.rgb, &output])?;
        fwd.push(Step::new(sig, g_sig, linear_grid(n_out, 256)));

        // ---- Backward: the sigmoid, the decoder, then the U-Net.
        let mut bwd = Vec::new();
        let grad_output = act("renderer output gradient", n_out);
        bwd.push(act_backward(
            gpu,
            Kept::SigmoidOutput,
            n_out,
            At::new(&output),
            At::new(&grad_output),
            At::new(&decoder.grad_rgb),
        )?);
        bwd.extend(decoder.backward_steps().iter().cloned());
        let gvecs = b(grad_vecs);
        // A convolution's backward from dY (through its leaky ReLU when `kept` is its output).
        let cback = |bwd: &mut Vec<Step>,
                     l: &Layer,
                     r: usize,
                     input: At<'_>,
                     kept: Option<&wgpu::Buffer>,
                     dy: At<'_>,
                     dx: Option<&wgpu::Buffer>|
         -> Result<()> {
            let n = l.cout * r * r;
            let dz_buf;
            let dz = match kept {
                Some(y) => {
                    dz_buf = act("dZ", n);
                    bwd.push(act_backward(
                        gpu,
                        Kept::LreluOutput,
                        n,
                        At::new(y),
                        dy,
                        At::new(&dz_buf),
                    )?);
                    At::new(&dz_buf)
                }
                None => dy,
            };
            bwd.extend(conv_backward(
                &ops,
                &ConvGrad {
                    cin: l.cin,
                    cout: l.cout,
                    h: r,
                    w: r,
                    k: l.k,
                    input,
                    weight: b(l.weight),
                    grad_out: dz,
                    grad_input: dx.map(At::new),
                    grad_weight: At::new(b(l.grad_weight)),
                    grad_bias: l.bias.map(|o| At::off(gvecs, o as usize)),
                    accumulate: false,
                },
                &flipped,
                &part,
            )?);
            Ok(())
        };
        let sum = |bwd: &mut Vec<Step>,
                   n: usize,
                   a: &wgpu::Buffer,
                   c: &wgpu::Buffer|
         -> Result<wgpu::Buffer> {
            let out = act("gradient sum", n);
            bwd.push(ops.add(n, a, c, &out)?);
            Ok(out)
        };
        // Up levels, last first. `d_next`: the gradient of this level's output from the next
        // level's input.
        let mut d_next: Option<wgpu::Buffer> = None;
        let mut d_down: Vec<Option<wgpu::Buffer>> = (0..levels).map(|_| None).collect();
        for k in (0..levels).rev() {
            let r = 8 << k;
            let blk = &up[k];
            let (ci, co) = (blk.conv1.cin, blk.conv2.cout);
            let (x, a, mids) = &ups[k];
            let ((s0, s2), (h0, h2)) = &branches[k];
            let n = dc(r) * r * r;
            let (d_s, d_h) = (
                act("d condition_scale 0", co * r * r),
                act("d condition_shift 0", co * r * r),
            );
            cback(
                &mut bwd,
                s2,
                r,
                At::new(&mids[0]),
                None,
                At::off(&decoder.grad_conditions[k], 0),
                Some(&d_s),
            )?;
            cback(
                &mut bwd,
                h2,
                r,
                At::new(&mids[1]),
                None,
                At::off(&decoder.grad_conditions[k], n),
                Some(&d_h),
            )?;
            let (d_out_s, d_out_h) = (
                act("d up out (scale)", co * r * r),
                act("d up out (shift)", co * r * r),
            );
            cback(
                &mut bwd,
                s0,
                r,
                At::new(&a.out),
                Some(&mids[0]),
                At::new(&d_s),
                Some(&d_out_s),
            )?;
            cback(
                &mut bwd,
                h0,
                r,
                At::new(&a.out),
                Some(&mids[1]),
                At::new(&d_h),
                Some(&d_out_h),
            )?;
            let mut d_out = sum(&mut bwd, co * r * r, &d_out_s, &d_out_h)?;
            if let Some(dn) = d_next.take() {
                d_out = sum(&mut bwd, co * r * r, &d_out, &dn)?;
            }
            // out = main + up(skip(x)); main = lrelu(conv2(up(lrelu(conv1(x))))).
            let d_hr = act("d up h x2", ci * r * r);
            cback(
                &mut bwd,
                &blk.conv2,
                r,
                At::new(&a.h_resized),
                Some(&a.main),
                At::new(&d_out),
                Some(&d_hr),
            )?;
            let d_h1 = act("d up h", ci * r * r / 4);
            bwd.push(resize_backward(
                gpu,
                true,
                (ci, r / 2, r / 2),
                At::new(&d_hr),
                At::new(&d_h1),
            )?);
            let d_x1 = act("d up in (main)", ci * r * r / 4);
            cback(
                &mut bwd,
                &blk.conv1,
                r / 2,
                At::new(x),
                Some(&a.h),
                At::new(&d_h1),
                Some(&d_x1),
            )?;
            let d_sk = act("d up skip", co * r * r / 4);
            bwd.push(resize_backward(
                gpu,
                true,
                (co, r / 2, r / 2),
                At::new(&d_out),
                At::new(&d_sk),
            )?);
            let d_x2 = act("d up in (skip)", ci * r * r / 4);
            cback(
                &mut bwd,
                &blk.skip,
                r / 2,
                At::new(x),
                None,
                At::new(&d_sk),
                Some(&d_x2),
            )?;
            let d_x = sum(&mut bwd, ci * r * r / 4, &d_x1, &d_x2)?;
            // x = previous output + the down path's output at this resolution.
            d_down[levels - 1 - k] = Some(d_x.clone());
            d_next = Some(d_x);
        }
        // The style code and the 4x4 features.
        let d_feat_code = act("d final_conv (code)", fl_in);
        cback(
            &mut bwd,
            &final_linear,
            1,
            At::new(&feat),
            None,
            At::new(&decoder.grad_code),
            Some(&d_feat_code),
        )?;
        let d_feat = match d_next.take() {
            Some(dn) => sum(&mut bwd, fl_in, &d_feat_code, &dn)?,
            None => d_feat_code,
        };
        let mut d_f = act("d last down", u(4) * 16);
        cback(
            &mut bwd,
            &final_conv,
            4,
            At::new(last_down),
            Some(&feat),
            At::new(&d_feat),
            Some(&d_f),
        )?;
        // Down levels, last first.
        for k in (0..levels).rev() {
            let r = s >> k;
            let blk = &down[k];
            let (ci, co) = (blk.conv1.cin, blk.conv2.cout);
            let a = &downs[k];
            let x = match k {
                0 => &f0,
                _ => &downs[k - 1].out,
            };
            let d_out = match d_down[k].take() {
                Some(du) => sum(&mut bwd, co * r * r / 4, &d_f, &du)?,
                None => d_f.clone(),
            };
            let d_hr = act("d down h/2", ci * r * r / 4);
            cback(
                &mut bwd,
                &blk.conv2,
                r / 2,
                At::new(&a.h_resized),
                Some(&a.main),
                At::new(&d_out),
                Some(&d_hr),
            )?;
            let d_h1 = act("d down h", ci * r * r);
            bwd.push(resize_backward(
                gpu,
                false,
                (ci, r, r),
                At::new(&d_hr),
                At::new(&d_h1),
            )?);
            let d_x1 = act("d down in (main)", ci * r * r);
            cback(
                &mut bwd,
                &blk.conv1,
                r,
                At::new(x),
                Some(&a.h),
                At::new(&d_h1),
                Some(&d_x1),
            )?;
            let d_xr = act("d down x/2", ci * r * r / 4);
            let xr = a.x_resized.as_ref().unwrap_or(&dummy);
            cback(
                &mut bwd,
                &blk.skip,
                r / 2,
                At::new(xr),
                None,
                At::new(&d_out),
                Some(&d_xr),
            )?;
            let d_x2 = act("d down in (skip)", ci * r * r);
            bwd.push(resize_backward(
                gpu,
                false,
                (ci, r, r),
                At::new(&d_xr),
                At::new(&d_x2),
            )?);
            d_f = sum(&mut bwd, ci * r * r, &d_x1, &d_x2)?;
        }
        let grad_input = act("renderer input gradient", cfg.color_dim * s * s);
        cback(
            &mut bwd,
            &first,
            s,
            At::new(&input),
            Some(&f0),
            At::new(&d_f),
            Some(&grad_input),
        )?;

        if st.params.is_empty() {
            return Err(GpuError::Weights("the renderer has no parameters".into()));
        }
        Ok(Self {
            size: s,
            input,
            output,
            grad_output,
            grad_input,
            decoder,
            buffers: st.buffers,
            params: st.params,
            forward: fwd,
            backward: bwd,
        })
    }

    /// Uploads the splatted image `[color_dim, size, size]` for the next forward.
    pub fn set_input(&self, gpu: &Gpu, image: &[f32]) -> Result<()> {
        upload(gpu, &self.input, image, "renderer input")
    }

    /// Uploads the loss gradient of the output `[3, size, size]` for the next backward.
    pub fn set_grad_output(&self, gpu: &Gpu, grad: &[f32]) -> Result<()> {
        upload(gpu, &self.grad_output, grad, "renderer output gradient")
    }

    pub fn forward_steps(&self) -> &[Step] {
        &self.forward
    }

    /// Needs the forward's values of the same input (run the forward first).
    pub fn backward_steps(&self) -> &[Step] {
        &self.backward
    }

    /// Overwrites every trained parameter (U-Net and decoder) with `value(key)` (keys relative
    /// to `upsampler.`, values flattened in the checkpoint's layout): a trainer whose master
    /// weights live elsewhere uploads them before each step.
    pub fn set_weights(&self, gpu: &Gpu, value: &ParamSource) -> Result<()> {
        write_params(gpu, &self.buffers, &self.params, value)?;
        self.decoder.set_weights(gpu, value)
    }

    /// Replaces the decoder's noise maps for the next forward (see
    /// [`GpuDecoderGrad::set_noise`]).
    pub fn set_noise(&self, gpu: &Gpu, maps: &[Vec<f32>]) -> Result<()> {
        self.decoder.set_noise(gpu, maps)
    }

    /// Every parameter's gradient (U-Net and decoder), read back, by key relative to
    /// `upsampler.`.
    pub fn read_grads(&self, gpu: &Gpu) -> Result<Vec<(String, Vec<f32>)>> {
        let mut all = read_grads(gpu, &self.buffers, &self.params)?;
        all.extend(self.decoder.read_grads(gpu)?);
        Ok(all)
    }
}

fn upload(gpu: &Gpu, buf: &wgpu::Buffer, values: &[f32], name: &str) -> Result<()> {
    if 4 * values.len() as u64 != buf.size() {
        return Err(GpuError::Input {
            name: name.into(),
            reason: format!("{} values, expected {}", values.len(), buf.size() / 4),
        });
    }
    gpu.queue.write_buffer(buf, 0, bytemuck::cast_slice(values));
    Ok(())
}
