//! The lifting generators (`gs_generator_l0` / `l1`, spec section 5) for training: a forward
//! that keeps every activation its backward reads, and the backward from the gradients of the
//! lifted Gaussians to the gradient of `F_local` and of every generator weight.
//!
//! Per plane: `x = [F_local | encoding broadcast]`, three 3x3 convolutions with ReLU and a 1x1
//! one to the raw `[C + 9, S^2]`, activated by the inference kernel (`gaussians.wgsl`, the
//! release's colour-sigmoid quirk included) into Gaussian-major buffers; the backward is that
//! activation's gradient (`lift_backward.wgsl`), then the convolutions' (`conv_backward`, the
//! forward's kernels). Weight and bias gradients are added over the samples of a step (the
//! trainer weights each sample's Gaussian gradients by its share of the loss) and read once.
//! The CPU module is `gagavatar_net::gs_generator::ConvGsGenerator`.

use std::collections::HashMap;

use gagavatar_net::config::DIR_ENCODING_DIM;
use gagavatar_net::ModelConfig;
use gagavatar_train::LiftedGaussians;

use super::conv::{conv_backward, part_floats, ConvGrad};
use super::layers::{act_backward, Kept};
use super::lifting::GpuLiftingLoss;
use super::params::{host_weight, read_grads, write_params, Packed, Param, ParamSource, Store};
use crate::conv::{Act, At, Conv, Ops};
use crate::device::Gpu;
use crate::error::{input_err, GpuError, Result};
use crate::kernel::{linear_grid, Bind, Params, Step};
use crate::reconstruct::ops::GaussianOut;
use crate::tuning::Tuning;

const LIFT_BACKWARD: &str = include_str!("../shaders/lift_backward.wgsl");
const ACCUMULATE: &str = include_str!("../shaders/accumulate.wgsl");

/// The lifting term on the lifted points of the last forward (`GpuLiftingLoss` on the means
/// buffer), its gradient added to the means' in the backward.
struct Term {
    loss: GpuLiftingLoss,
    /// dL/dlifted `[n, 3]`, copied out of the loss's output.
    grad: wgpu::Buffer,
    /// The scale of that gradient (the sample's share of the step's loss), `accumulate.wgsl`'s.
    scale: wgpu::Buffer,
    add: Step,
    /// Whether the last forward computed the term (its gradient is then due).
    pending: bool,
}

/// One convolution of a generator: weight and gradient buffer indices, bias offset (in the
/// shared vector buffer and its gradient).
#[derive(Debug, Clone, Copy)]
struct Layer {
    cin: usize,
    cout: usize,
    k: usize,
    weight: usize,
    grad_weight: usize,
    bias: u32,
}

/// The lifting generators' training forward and backward, recorded once.
pub struct GpuLiftGrad {
    /// Plane side `S`, `F_local` channels, colour channels, planes (2, or 1 with `one_plane`).
    s: usize,
    f: usize,
    c: usize,
    planes: usize,
    /// `[F + E, S^2]`: `F_local`, then the encoding broadcast over the plane.
    input: wgpu::Buffer,
    /// The plane's points `[S^2, 3]`, then the view direction `[3]`.
    plane: wgpu::Buffer,
    /// features, opacities, scales, rotations, means of `P S^2` Gaussians.
    outs: [wgpu::Buffer; 5],
    /// Their gradients (the backward's input), laid out as they are.
    grads: [wgpu::Buffer; 5],
    /// `[F + E, S^2]`: the gradient of `input`, both planes summed.
    grad_input: wgpu::Buffer,
    buffers: Vec<wgpu::Buffer>,
    params: Vec<Param>,
    /// The gradient buffers (zeroed before a step's first backward).
    grad_buffers: Vec<usize>,
    forward: Vec<Step>,
    backward: Vec<Step>,
    /// Backward passes added since the last read.
    samples: usize,
    term: Option<Term>,
}

/// Where a forward's `F_local` `[F, S, S]` comes from.
#[derive(Debug, Clone, Copy)]
pub enum LiftInput<'a> {
    /// Host values.
    Host(&'a [f32]),
    /// The first `F S^2` floats of a device buffer (the DPT head's output on this device).
    Device(&'a wgpu::Buffer),
}

/// Attribute widths in [`GpuLiftGrad::outs`]' order, for `c` colour channels.
fn widths(c: usize) -> [usize; 5] {
    [c, 1, 3, 4, 3]
}

impl GpuLiftGrad {
    /// Uploads both generators' weights (`weights` by checkpoint key, `gs_generator_l0.` ...)
    /// and records the forward and backward.
    pub fn new(
        gpu: &Gpu,
        tuning: &Tuning,
        cfg: &ModelConfig,
        weights: &HashMap<String, Vec<f32>>,
    ) -> Result<Self> {
        cfg.validate().map_err(GpuError::Unsupported)?;
        // f32 throughout: f16 tensor-core inputs need loss scaling for the gradients first.
        let tuning = &Tuning {
            mma: false,
            ..tuning.for_device(gpu)
        };
        tuning.check(&gpu.limits)?;
        let (s, f, c, hc) = (
            cfg.plane_size(),
            cfg.dpt_features,
            cfg.color_dim,
            cfg.gs_conv_hidden,
        );
        let e = DIR_ENCODING_DIM;
        let (m, out) = (s * s, c + 9);
        let planes = if cfg.one_plane { 1 } else { 2 };
        let get = |key: &str, len: usize| host_weight(weights, key, len);
        let mut st = Store::new(gpu);
        let mut vecs_host = Packed::default();
        let mut gens: Vec<[Layer; 4]> = Vec::with_capacity(planes);
        for l in 0..planes {
            let shapes = [(f + e, hc, 3), (hc, hc, 3), (hc, hc, 3), (hc, out, 1)];
            let mut layer = |i: usize| -> Result<Layer> {
                let (cin, cout, k) = shapes[i];
                let key = format!("gs_generator_l{l}.gaussian_conv.{}", 2 * i);
                let (weight, grad_weight) = st.param(
                    &format!("{key}.weight"),
                    get(&format!("{key}.weight"), cout * cin * k * k)?,
                );
                let bias = vecs_host
                    .push(format!("{key}.bias"), &get(&format!("{key}.bias"), cout)?)
                    as u32;
                Ok(Layer {
                    cin,
                    cout,
                    k,
                    weight,
                    grad_weight,
                    bias,
                })
            };
            gens.push([layer(0)?, layer(1)?, layer(2)?, layer(3)?]);
        }
        let (vecs, grad_vecs) = st.packed("lifting biases", vecs_host);
        let mut grad_buffers: Vec<usize> = gens.iter().flatten().map(|l| l.grad_weight).collect();
        grad_buffers.push(grad_vecs);

        let (mut split_need, mut flipped_need, mut part_need) = (1, 1, 1);
        for l in gens.iter().flatten() {
            split_need = split_need
                .max(Ops::split_need(tuning, l.cin, l.cout, s, s, l.k))
                .max(Ops::split_need(tuning, l.cout, l.cin, s, s, l.k));
            flipped_need = flipped_need.max(l.cin * l.cout * l.k * l.k);
            part_need = part_need.max(part_floats(tuning.conv, (l.cin, l.cout, m, l.k), true));
        }
        let split = gpu.buffer("split-K partial sums", 4 * split_need as u64);
        let flipped = gpu.buffer("rotated weights", 4 * flipped_need as u64);
        let part = gpu.buffer("partial sums", 4 * part_need as u64);
        let dummy = gpu.buffer("unused", 16);
        let spare = gpu.buffer("unused (written)", 16);
        let b = |i: usize| &st.buffers[i];
        let ops = Ops {
            gpu,
            tuning,
            vecs: b(vecs),
            dummy: &dummy,
            split_scratch: &split,
        };
        let act = |label: &str, n: usize| gpu.buffer(label, 4 * n as u64);
        let input = act("lifting input", (f + e) * m);
        let plane = act("plane points and direction", 3 * m + 3);
        let w = widths(c);
        let outs = w.map(|k| act("lifted Gaussians", planes * m * k));
        let grads = w.map(|k| act("lifted Gaussians' gradients", planes * m * k));
        let grad_input = act("lifting input gradient", (f + e) * m);

        let mut fwd = Vec::new();
        let mut bwd = Vec::new();
        let d_raw = act("d raw", out * m);
        let (d_a, d_z) = (act("d hidden", hc * m), act("d pre-activation", hc * m));
        // Each plane's input gradient; with two planes, summed into `grad_input` at the end.
        let gx: Vec<wgpu::Buffer> = if planes > 1 {
            (0..planes)
                .map(|_| act("d input (one plane)", (f + e) * m))
                .collect()
        } else {
            Vec::new()
        };
        let lk = gpu.kernel(
            "lift_backward",
            LIFT_BACKWARD,
            &[],
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
            ],
        )?;
        let gvecs = b(grad_vecs);
        for (l, gen) in gens.iter().enumerate() {
            let sign = if l == 0 { 1.0 } else { -1.0 };
            let hidden = [
                act("lift h0", hc * m),
                act("lift h1", hc * m),
                act("lift h2", hc * m),
            ];
            let raw = act("lift raw", out * m);
            let fconv = |layer: &Layer, input: At<'_>, out: At<'_>, relu: bool| {
                ops.conv(&Conv {
                    cin: layer.cin,
                    cout: layer.cout,
                    h: s,
                    w: s,
                    k: layer.k,
                    input,
                    weight: b(layer.weight),
                    bias: Some(layer.bias),
                    in_scale: None,
                    out_scale: None,
                    noise: None,
                    in_relu: false,
                    act: if relu { Act::Relu } else { Act::None },
                    residual: None,
                    sft: None,
                    sigmoid: false,
                    out,
                })
            };
            fwd.extend(fconv(&gen[0], At::new(&input), At::new(&hidden[0]), true)?);
            fwd.extend(fconv(
                &gen[1],
                At::new(&hidden[0]),
                At::new(&hidden[1]),
                true,
            )?);
            fwd.extend(fconv(
                &gen[2],
                At::new(&hidden[1]),
                At::new(&hidden[2]),
                true,
            )?);
            fwd.extend(fconv(&gen[3], At::new(&hidden[2]), At::new(&raw), false)?);
            let [of, oo, os, or, om] = &outs;
            fwd.push(ops.gaussians(
                &GaussianOut {
                    m,
                    c,
                    g0: l * m,
                    lift: Some((s, &plane, 3 * l * m, sign)),
                    buffers: [of, oo, os, or, om],
                },
                At::new(&raw),
                &spare,
            )?);

            // Backward: the activation, then the convolutions last first.
            let u = gpu.uniform(
                "lift backward",
                &Params::new()
                    .u(m as u32)
                    .u(c as u32)
                    .u(s as u32)
                    .u((l * m) as u32)
                    .u((3 * l * m) as u32)
                    .u(0)
                    .f(sign)
                    .u(0),
            );
            let [gf, go, gs, gr, gm] = &grads;
            let bg = gpu.bind(&lk, &[&u, &raw, &plane, gf, go, gs, gr, gm, &d_raw])?;
            bwd.push(Step::new(lk.clone(), bg, linear_grid(m, 256)));
            let back = |bwd: &mut Vec<Step>,
                        layer: &Layer,
                        input: &wgpu::Buffer,
                        dz: &wgpu::Buffer,
                        dx: &wgpu::Buffer|
             -> Result<()> {
                bwd.extend(conv_backward(
                    &ops,
                    &ConvGrad {
                        cin: layer.cin,
                        cout: layer.cout,
                        h: s,
                        w: s,
                        k: layer.k,
                        input: At::new(input),
                        weight: b(layer.weight),
                        grad_out: At::new(dz),
                        grad_input: Some(At::new(dx)),
                        grad_weight: At::new(b(layer.grad_weight)),
                        grad_bias: Some(At::off(gvecs, layer.bias as usize)),
                        accumulate: true,
                    },
                    &flipped,
                    &part,
                )?);
                Ok(())
            };
            back(&mut bwd, &gen[3], &hidden[2], &d_raw, &d_a)?;
            for i in (0..3).rev() {
                bwd.push(act_backward(
                    gpu,
                    Kept::ReluOutput,
                    hc * m,
                    At::new(&hidden[i]),
                    At::new(&d_a),
                    At::new(&d_z),
                )?);
                let (x, dx) = match (i, gx.get(l)) {
                    (0, Some(g)) => (&input, g),
                    (0, None) => (&input, &grad_input),
                    _ => (&hidden[i - 1], &d_a),
                };
                back(&mut bwd, &gen[i], x, &d_z, dx)?;
            }
        }
        if let [g0, g1] = gx.as_slice() {
            bwd.push(ops.add((f + e) * m, g0, g1, &grad_input)?);
        }
        Ok(Self {
            s,
            f,
            c,
            planes,
            input,
            plane,
            outs,
            grads,
            grad_input,
            buffers: st.buffers,
            params: st.params,
            grad_buffers,
            forward: fwd,
            backward: bwd,
            samples: 0,
            term: None,
        })
    }

    /// Also computes the lifting term against `targets` points per sample
    /// ([`GpuLiftGrad::lifting_term`]).
    pub fn with_lifting_term(mut self, gpu: &Gpu, targets: usize) -> Result<Self> {
        let n = self.planes * self.s * self.s;
        let loss = GpuLiftingLoss::new(gpu, &self.outs[4], n, targets)?;
        let grad = gpu.buffer("lifting term gradient", 12 * n as u64);
        let scale = gpu.uniform("lifting term scale", &Params::new().f(1.0).u(0).u(0).u(0));
        let k = gpu.kernel(
            "accumulate",
            ACCUMULATE,
            &[],
            &[Bind::Uniform, Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = gpu.uniform(
            "lifting term add",
            &Params::new().u((3 * n) as u32).u(0).u(0).u(0),
        );
        let bg = gpu.bind(&k, &[&u, &scale, &grad, &self.grads[4]])?;
        self.term = Some(Term {
            loss,
            grad,
            scale,
            add: Step::new(k, bg, linear_grid(3 * n, 256)),
            pending: false,
        });
        Ok(self)
    }

    /// The lifting term of the last forward's points against `targets` `[m, 3]` (the target's
    /// scaled FLAME vertices): returns its value; the next backward adds `scale` times its
    /// gradient to the lifted means' (the trainer's `1 / B`).
    pub fn lifting_term(&mut self, gpu: &Gpu, targets: &[f32], scale: f32) -> Result<f64> {
        let Some(t) = &mut self.term else {
            return Err(input_err(
                "lifting term",
                "the lifting generators were built without it",
            ));
        };
        t.loss.set_targets(gpu, targets)?;
        gpu.queue.write_buffer(
            &t.scale,
            0,
            bytemuck::cast_slice(&Params::new().f(scale).u(0).u(0).u(0).words()),
        );
        gpu.submit(t.loss.steps());
        t.pending = true;
        Ok(f64::from(gpu.read_f32(&t.loss.out, 1)?[0]))
    }

    /// Overwrites every weight with `value(key)` (checkpoint keys); the gradient sums start
    /// again.
    pub fn set_weights(&mut self, gpu: &Gpu, value: &ParamSource) -> Result<()> {
        write_params(gpu, &self.buffers, &self.params, value)?;
        self.samples = 0;
        Ok(())
    }

    /// One sample's lifted Gaussians: `f_local` `[F, S, S]`, `encoding` `[27]`, the plane's
    /// points `[S^2, 3]` and the view direction `[3]`.
    pub fn forward(
        &mut self,
        gpu: &Gpu,
        f_local: LiftInput,
        encoding: &[f32],
        points: &[f32],
        dir: &[f32],
    ) -> Result<LiftedGaussians> {
        let m = self.s * self.s;
        let e = DIR_ENCODING_DIM;
        let f_bytes = 4 * (self.f * m) as u64;
        let f_len = match f_local {
            LiftInput::Host(v) => v.len(),
            LiftInput::Device(b) if b.size() >= f_bytes => self.f * m,
            LiftInput::Device(b) => (b.size() / 4) as usize,
        };
        for (what, got, want) in [
            ("F_local", f_len, self.f * m),
            ("direction encoding", encoding.len(), e),
            ("plane points", points.len(), 3 * m),
            ("view direction", dir.len(), 3),
        ] {
            if got != want {
                return Err(input_err(
                    "lifting generators",
                    format!("{got} {what} values, expected {want}"),
                ));
            }
        }
        let mut x = Vec::with_capacity(e * m);
        for &v in encoding {
            x.extend(std::iter::repeat_n(v, m));
        }
        gpu.queue
            .write_buffer(&self.input, f_bytes, bytemuck::cast_slice(&x));
        match f_local {
            LiftInput::Host(v) => gpu
                .queue
                .write_buffer(&self.input, 0, bytemuck::cast_slice(v)),
            LiftInput::Device(b) => {
                let mut enc = gpu
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("F_local into the lifting input"),
                    });
                enc.copy_buffer_to_buffer(b, 0, &self.input, 0, f_bytes);
                gpu.queue.submit([enc.finish()]);
            }
        }
        let plane = [points, dir].concat();
        gpu.queue
            .write_buffer(&self.plane, 0, bytemuck::cast_slice(&plane));
        gpu.submit(&self.forward);
        if let Some(t) = &mut self.term {
            t.pending = false;
        }
        let n = self.planes * m;
        let w = widths(self.c);
        let srcs: Vec<(&wgpu::Buffer, usize)> =
            self.outs.iter().zip(w).map(|(b, k)| (b, n * k)).collect();
        let mut read = gpu.read_f32_many(&srcs)?.into_iter();
        let mut next = || read.next().unwrap_or_default();
        Ok(LiftedGaussians {
            features: next(),
            opacities: next(),
            scales: next(),
            rotations: next(),
            means: next(),
            point: None,
        })
    }

    /// The backward of the last forward from its Gaussians' gradients: returns the gradient of
    /// `F_local` `[F, S, S]`; the weight gradients are added to the step's sums.
    pub fn backward(&mut self, gpu: &Gpu, grads: &LiftedGaussians) -> Result<Vec<f32>> {
        self.backward_on_device(gpu, grads)?;
        gpu.read_f32(&self.grad_input, self.f * self.s * self.s)
    }

    /// The first `F S^2` floats of this buffer: the gradient of `F_local` after
    /// [`GpuLiftGrad::backward_on_device`].
    pub fn grad_f_local(&self) -> &wgpu::Buffer {
        &self.grad_input
    }

    /// [`GpuLiftGrad::backward`] with the gradient of `F_local` left on the device
    /// ([`GpuLiftGrad::grad_f_local`]).
    pub fn backward_on_device(&mut self, gpu: &Gpu, grads: &LiftedGaussians) -> Result<()> {
        let n = self.planes * self.s * self.s;
        let w = widths(self.c);
        let term_pending = self.term.as_ref().is_some_and(|t| t.pending);
        let given = [
            &grads.features,
            &grads.opacities,
            &grads.scales,
            &grads.rotations,
            &grads.means,
        ];
        for ((g, k), buf) in given.iter().zip(w).zip(&self.grads) {
            if g.len() != n * k {
                return Err(input_err(
                    "lifted Gaussians' gradients",
                    format!("{} values for {n} Gaussians of width {k}", g.len()),
                ));
            }
            gpu.queue.write_buffer(buf, 0, bytemuck::cast_slice(g));
        }
        if let (Some(t), true) = (&mut self.term, term_pending) {
            let mut enc = gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("lifting term gradient"),
                });
            enc.copy_buffer_to_buffer(&t.loss.out, 4, &t.grad, 0, 12 * n as u64);
            gpu.queue.submit([enc.finish()]);
            gpu.submit(std::slice::from_ref(&t.add));
            t.pending = false;
        }
        if self.samples == 0 {
            let mut enc = gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("zero the lifting gradients"),
                });
            for &i in &self.grad_buffers {
                enc.clear_buffer(&self.buffers[i], 0, None);
            }
            gpu.queue.submit([enc.finish()]);
        }
        gpu.submit(&self.backward);
        self.samples += 1;
        Ok(())
    }

    /// Every weight's gradient summed over the backward passes since the weights were set,
    /// by checkpoint key.
    pub fn read_grads(&mut self, gpu: &Gpu) -> Result<Vec<(String, Vec<f32>)>> {
        if self.samples == 0 {
            return Err(input_err(
                "lifting gradients",
                "no backward since the weights were set",
            ));
        }
        read_grads(gpu, &self.buffers, &self.params)
    }
}
