//! The DPT head (spec section 4) for training: a forward that keeps every activation its
//! backward reads, and the backward from the gradient of `F_local` to the gradient of every
//! DPT weight (`base_model.projects`, `resize_layers`, `layer_rn`, `refinenet`,
//! `output_conv`). The backbone is frozen, so no gradient goes back into its tokens.
//!
//! The forward is the inference pass's (`reconstruct::dpt`) with two changes: every fusion
//! block keeps its own activations, and a residual unit's pre-activation ReLU is written out
//! (its convolution's weight gradient reads it) instead of applied as the convolution reads.
//! The backward is made of the convolutions' gradients (`conv_backward`: 1x1 products, 3x3
//! convolutions), the transposed convolutions' pixel spread read back
//! (`shuffle_backward.wgsl`), the stride-2 patches folded back (`col2im.wgsl`), the
//! align-corners resize's transpose (`resize_ac_backward.wgsl`) and the ReLUs'. Weight
//! gradients add up over the samples of a step, like [`super::lift::GpuLiftGrad`]'s.
//! The CPU module is `gagavatar_net::dpt::DptHead`.

use std::collections::HashMap;

use gagavatar_net::ModelConfig;

use super::conv::{conv_backward, part_floats, row_sums, ConvGrad};
use super::layers::{act_backward, col2im, Kept};
use super::params::{host_weight, read_grads, write_params, Packed, Param, ParamSource, Store};
use crate::conv::{Act, At, Conv, Ops};
use crate::device::Gpu;
use crate::error::{input_err, GpuError, Result};
use crate::kernel::{linear_grid, Bind, Params, Step};
use crate::reconstruct::ops::TapTables;
use crate::tuning::Tuning;

const RESIZE_AC_BACKWARD: &str = include_str!("../shaders/resize_ac_backward.wgsl");
const SHUFFLE_BACKWARD: &str = include_str!("../shaders/shuffle_backward.wgsl");

const PREFIX: &str = "base_model";

/// A layer as a convolution: weight and gradient buffer indices, bias offset in the shared
/// vector buffer (and its gradient).
#[derive(Debug, Clone, Copy)]
struct Layer {
    cin: usize,
    cout: usize,
    k: usize,
    weight: usize,
    grad_weight: usize,
    bias: Option<u32>,
}

/// How a level's projected tokens reach its resolution.
#[derive(Debug, Clone, Copy)]
enum Resize {
    /// A transposed convolution of kernel = stride `k`: the product `[c k k, c]` (no bias)
    /// and the bias of the spread output.
    Up(Layer, usize, u32),
    Identity,
    /// 3x3 stride 2: the product `[c, 9 c]` over the patch matrix.
    Down(Layer),
}

struct Level {
    project: Layer,
    resize: Resize,
    layer_rn: Layer,
}

struct Unit {
    conv1: Layer,
    conv2: Layer,
}

/// A transposed convolution's weight, whose checkpoint layout `[cin, cout, k, k]` the GPU
/// keeps as the product's `[cout k k, cin]`.
struct Permuted {
    key: String,
    c: usize,
    taps: usize,
}

impl Permuted {
    /// Checkpoint layout -> product layout.
    fn to_product(&self, w: &[f32]) -> Vec<f32> {
        let (c, t) = (self.c, self.taps);
        let mut out = vec![0f32; w.len()];
        for ci in 0..c {
            for co in 0..c {
                for tap in 0..t {
                    out[(co * t + tap) * c + ci] = w[(ci * c + co) * t + tap];
                }
            }
        }
        out
    }

    /// Product layout -> checkpoint layout.
    fn to_checkpoint(&self, p: &[f32]) -> Vec<f32> {
        let (c, t) = (self.c, self.taps);
        let mut out = vec![0f32; p.len()];
        for ci in 0..c {
            for co in 0..c {
                for tap in 0..t {
                    out[(ci * c + co) * t + tap] = p[(co * t + tap) * c + ci];
                }
            }
        }
        out
    }
}

/// The DPT head's training forward and backward, recorded once.
pub struct GpuDptGrad {
    /// ViT width, token grid side, DINO input side, DPT features, plane side.
    c: usize,
    g: usize,
    d: usize,
    f: usize,
    s: usize,
    /// The four token maps `[c, g^2]` (channel-major).
    tokens: [wgpu::Buffer; 4],
    /// The normalised DINO input `[3, d, d]`.
    image: wgpu::Buffer,
    /// `F_local` `[F, S, S]`.
    f_local: wgpu::Buffer,
    /// Its gradient, the backward's input.
    grad_f_local: wgpu::Buffer,
    buffers: Vec<wgpu::Buffer>,
    params: Vec<Param>,
    permuted: Vec<Permuted>,
    grad_buffers: Vec<usize>,
    forward: Vec<Step>,
    backward: Vec<Step>,
    samples: usize,
    _keep: Vec<wgpu::Buffer>,
}

impl GpuDptGrad {
    /// Uploads the DPT weights (`weights` by checkpoint key, `base_model.projects.0.weight`
    /// ...) and records the forward and backward.
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
        let (c, f, g, d, s) = (
            cfg.vit_dim,
            cfg.dpt_features,
            cfg.grid(),
            cfg.dino_size,
            cfg.plane_size(),
        );
        let g2 = g * g;
        let ch = cfg.dpt_channels;
        let sizes = [0, 1, 2, 3].map(|k| cfg.dpt_level_size(k));
        let mut st = Store::new(gpu);
        let mut vecs_host = Packed::default();
        let mut permuted = Vec::new();
        let layer = |st: &mut Store,
                     vecs_host: &mut Packed,
                     key: &str,
                     (cin, cout, k): (usize, usize, usize),
                     bias: bool|
         -> Result<Layer> {
            let wkey = format!("{key}.weight");
            let (weight, grad_weight) =
                st.param(&wkey, host_weight(weights, &wkey, cout * cin * k * k)?);
            let bias = if bias {
                let bkey = format!("{key}.bias");
                Some(vecs_host.push(bkey.clone(), &host_weight(weights, &bkey, cout)?) as u32)
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
        let mut levels = Vec::with_capacity(4);
        for (k, &ck) in ch.iter().enumerate() {
            let project = layer(
                &mut st,
                &mut vecs_host,
                &format!("{PREFIX}.projects.{k}"),
                (c, ck, 1),
                true,
            )?;
            let key = format!("{PREFIX}.resize_layers.{k}");
            let resize = match k {
                0 | 1 => {
                    let kk = if k == 0 { 4 } else { 2 };
                    let p = Permuted {
                        key: format!("{key}.weight"),
                        c: ck,
                        taps: kk * kk,
                    };
                    let w = p.to_product(&host_weight(weights, &p.key, ck * ck * kk * kk)?);
                    let (weight, grad_weight) = st.param(&p.key, w);
                    permuted.push(p);
                    let bkey = format!("{key}.bias");
                    let bias =
                        vecs_host.push(bkey.clone(), &host_weight(weights, &bkey, ck)?) as u32;
                    Resize::Up(
                        Layer {
                            cin: ck,
                            cout: ck * kk * kk,
                            k: 1,
                            weight,
                            grad_weight,
                            bias: None,
                        },
                        kk,
                        bias,
                    )
                }
                2 => Resize::Identity,
                _ => Resize::Down(layer(&mut st, &mut vecs_host, &key, (9 * ck, ck, 1), true)?),
            };
            let layer_rn = layer(
                &mut st,
                &mut vecs_host,
                &format!("{PREFIX}.layer_rn.{k}"),
                (3 + ck, f, 3),
                false,
            )?;
            levels.push(Level {
                project,
                resize,
                layer_rn,
            });
        }
        let mut fusion = Vec::with_capacity(4);
        for j in 0..4 {
            let r = format!("{PREFIX}.refinenet.{j}");
            let mut unit = |u: usize| -> Result<Unit> {
                Ok(Unit {
                    conv1: layer(
                        &mut st,
                        &mut vecs_host,
                        &format!("{r}.resConfUnit{u}.conv1"),
                        (f, f, 3),
                        true,
                    )?,
                    conv2: layer(
                        &mut st,
                        &mut vecs_host,
                        &format!("{r}.resConfUnit{u}.conv2"),
                        (f, f, 3),
                        true,
                    )?,
                })
            };
            // refinenet.0 has no skip input: its first unit is in the checkpoint but never runs
            // (no gradient; torch's Adam skips it).
            let u1 = if j == 0 { None } else { Some(unit(1)?) };
            let u2 = unit(2)?;
            let out_conv = layer(
                &mut st,
                &mut vecs_host,
                &format!("{r}.out_conv"),
                (f, f, 1),
                true,
            )?;
            fusion.push((u1, u2, out_conv));
        }
        let output_conv = layer(
            &mut st,
            &mut vecs_host,
            &format!("{PREFIX}.output_conv"),
            (f, f, 3),
            true,
        )?;
        // Zeros for the ReLUs written out through `rows` (x + 0, then ReLU).
        let zeros = vecs_host.reserve(f) as u32;
        let (vecs, grad_vecs) = st.packed("dpt biases", vecs_host);
        let mut grad_buffers: Vec<usize> = st.params.iter().map(|p| p.grad).collect();
        grad_buffers.sort_unstable();
        grad_buffers.dedup();

        // Every convolution with its plane, for the scratch sizes.
        let mut all: Vec<(Layer, usize, usize)> = Vec::new();
        for (k, l) in levels.iter().enumerate() {
            all.push((l.project, g, g));
            match l.resize {
                Resize::Up(p, _, _) => all.push((p, g, g)),
                Resize::Identity => {}
                Resize::Down(p) => all.push((p, 1, sizes[3] * sizes[3])),
            }
            all.push((l.layer_rn, sizes[k], sizes[k]));
        }
        // (input side, output side) of refinenet.0 .. 3.
        let sides = [
            (sizes[3], sizes[2]),
            (sizes[2], sizes[1]),
            (sizes[1], sizes[0]),
            (sizes[0], s),
        ];
        for ((u1, u2, oc), (si, so)) in fusion.iter().zip(sides) {
            for u in u1.iter().chain(std::iter::once(u2)) {
                all.push((u.conv1, si, si));
                all.push((u.conv2, si, si));
            }
            all.push((*oc, so, so));
        }
        all.push((output_conv, s, s));
        let (mut split_need, mut flipped_need, mut part_need) = (1, 1, 1);
        for (l, h, w) in &all {
            split_need = split_need
                .max(Ops::split_need(tuning, l.cin, l.cout, *h, *w, l.k))
                .max(Ops::split_need(tuning, l.cout, l.cin, *h, *w, l.k));
            flipped_need = flipped_need.max(l.cin * l.cout * l.k * l.k);
            part_need = part_need.max(part_floats(tuning.conv, (l.cin, l.cout, h * w, l.k), true));
        }
        // The resize layers' bias sums.
        for k in 0..2 {
            part_need = part_need.max(part_floats(
                tuning.conv,
                (1, ch[k], sizes[k] * sizes[k], 1),
                true,
            ));
        }
        let act = |label: &str, n: usize| gpu.buffer(label, 4 * n.max(1) as u64);
        let split = act("split-K partial sums", split_need);
        let flipped = act("rotated weights", flipped_need);
        let part = act("partial sums", part_need);
        let dummy = act("unused", 4);
        let b = |i: usize| &st.buffers[i];
        let ops = Ops {
            gpu,
            tuning,
            vecs: b(vecs),
            dummy: &dummy,
            split_scratch: &split,
        };
        let gvecs = b(grad_vecs);

        let tokens = [0, 1, 2, 3].map(|_| act("dpt tokens", c * g2));
        let image = act("dino input", 3 * d * d);
        let taps = TapTables::new(
            gpu,
            &sizes.map(|sk| (d, sk)),
            gagavatar_ops::ResizeMode::Antialias,
        );
        let f_local = act("F_local", f * s * s);
        let grad_f_local = act("d F_local", f * s * s);

        let mut fwd = Vec::new();
        let mut bwd_levels: Vec<Vec<Step>> = Vec::new();
        let conv = |l: &Layer, (h, w): (usize, usize), input: At<'_>, out: At<'_>, act: Act| {
            ops.conv(&Conv {
                cin: l.cin,
                cout: l.cout,
                h,
                w,
                k: l.k,
                input,
                weight: b(l.weight),
                bias: l.bias,
                in_scale: None,
                out_scale: None,
                noise: None,
                in_relu: false,
                act,
                residual: None,
                sft: None,
                sigmoid: false,
                out,
            })
        };
        // A layer's backward: input gradient into `dx` when given; weight and bias gradients
        // added to the step's sums.
        let back = |l: &Layer,
                    (h, w): (usize, usize),
                    input: At<'_>,
                    dz: At<'_>,
                    dx: Option<At<'_>>|
         -> Result<Vec<Step>> {
            conv_backward(
                &ops,
                &ConvGrad {
                    cin: l.cin,
                    cout: l.cout,
                    h,
                    w,
                    k: l.k,
                    input,
                    weight: b(l.weight),
                    grad_out: dz,
                    grad_input: dx,
                    grad_weight: At::new(b(l.grad_weight)),
                    grad_bias: l.bias.map(|o| At::off(gvecs, o as usize)),
                    accumulate: true,
                },
                &flipped,
                &part,
            )
        };

        // Levels: forward, and each level's backward from its `layer_rn` output's gradient.
        let mut rn = Vec::with_capacity(4);
        let mut d_rn = Vec::with_capacity(4);
        let mut keep = Vec::new();
        for (k, l) in levels.iter().enumerate() {
            let (ck, sk) = (ch[k], sizes[k]);
            let level = act("dpt level", (3 + ck) * sk * sk);
            let d_level = act("d dpt level", (3 + ck) * sk * sk);
            let projected = act("dpt projected", ck * g2);
            let d_projected = act("d dpt projected", ck * g2);
            let r = act("dpt layer_rn", f * sk * sk);
            let dr = act("d dpt layer_rn", f * sk * sk);
            fwd.push(ops.resize_taps(
                &taps,
                k,
                (3, d, sk),
                None,
                At::new(&image),
                At::new(&level),
            )?);
            let feat = At::off(&level, 3 * sk * sk);
            let d_feat = At::off(&d_level, 3 * sk * sk);
            let mut bwd = Vec::new();
            bwd.extend(back(
                &l.layer_rn,
                (sk, sk),
                At::new(&level),
                At::new(&dr),
                Some(At::new(&d_level)),
            )?);
            let project_to = match l.resize {
                Resize::Identity => feat,
                _ => At::new(&projected),
            };
            fwd.extend(conv(
                &l.project,
                (g, g),
                At::new(&tokens[k]),
                project_to,
                Act::None,
            )?);
            let d_project = match l.resize {
                Resize::Identity => d_feat,
                Resize::Up(p, kk, bias) => {
                    let product = act("dpt resize product", p.cout * g2);
                    let d_product = act("d dpt resize product", p.cout * g2);
                    fwd.extend(conv(
                        &p,
                        (g, g),
                        At::new(&projected),
                        At::new(&product),
                        Act::None,
                    )?);
                    fwd.push(ops.shuffle((ck, g, kk), bias, At::new(&product), feat)?);
                    bwd.extend(row_sums(
                        &ops,
                        (ck, sk * sk),
                        d_feat,
                        None,
                        &part,
                        At::off(gvecs, bias as usize),
                        true,
                        false,
                    )?);
                    bwd.push(shuffle_backward(gpu, (ck, g, kk), d_feat, &d_product)?);
                    bwd.extend(back(
                        &p,
                        (g, g),
                        At::new(&projected),
                        At::new(&d_product),
                        Some(At::new(&d_projected)),
                    )?);
                    keep.extend([product, d_product]);
                    At::new(&d_projected)
                }
                Resize::Down(p) => {
                    let cols = act("dpt patches", 9 * ck * sk * sk);
                    let d_cols = act("d dpt patches", 9 * ck * sk * sk);
                    let (step, oh, ow) =
                        ops.im2col((ck, g, g), 3, 2, 1, At::new(&projected), At::new(&cols))?;
                    if (oh, ow) != (sk, sk) {
                        return Err(GpuError::Device(format!(
                            "DPT level 3: {oh}x{ow} patches, expected {sk}x{sk}"
                        )));
                    }
                    fwd.push(step);
                    fwd.extend(conv(&p, (1, sk * sk), At::new(&cols), feat, Act::None)?);
                    bwd.extend(back(
                        &p,
                        (1, sk * sk),
                        At::new(&cols),
                        d_feat,
                        Some(At::new(&d_cols)),
                    )?);
                    bwd.push(col2im(
                        gpu,
                        (ck, g, g),
                        (3, 2, 1),
                        (sk, sk),
                        &d_cols,
                        &d_projected,
                    )?);
                    keep.extend([cols, d_cols]);
                    At::new(&d_projected)
                }
            };
            bwd.extend(back(
                &l.project,
                (g, g),
                At::new(&tokens[k]),
                d_project,
                None,
            )?);
            fwd.extend(conv(
                &l.layer_rn,
                (sk, sk),
                At::new(&level),
                At::new(&r),
                Act::None,
            )?);
            bwd_levels.push(bwd);
            keep.extend([level, d_level, projected, d_projected]);
            rn.push(r);
            d_rn.push(dr);
        }

        // Fusion blocks. Scratch for the backward, sized for the largest block.
        let big = f * sizes[0] * sizes[0];
        let d_up = act("d fusion upsampled", f * s * s);
        let (d_u, d_t, d_z, d_rx, d_tmp) = (
            act("d fusion unit output", big),
            act("d fusion hidden", big),
            act("d fusion pre-activation", big),
            act("d fusion relu input", big),
            act("d fusion relu", big),
        );
        let mut fused: Vec<wgpu::Buffer> = Vec::with_capacity(4);
        let mut d_fused: Vec<wgpu::Buffer> = Vec::with_capacity(4);
        let mut bwd_fusion: Vec<Vec<Step>> = Vec::new();
        // `out = x + conv2(relu(conv1(relu(x))))`: records the forward; returns the backward
        // from `dout` to `dx`.
        let unit = |fwd: &mut Vec<Step>,
                    keep: &mut Vec<wgpu::Buffer>,
                    u: &Unit,
                    side: usize,
                    x: &wgpu::Buffer,
                    out: &wgpu::Buffer,
                    dout: &wgpu::Buffer,
                    dx: &wgpu::Buffer|
         -> Result<Vec<Step>> {
            let n = f * side * side;
            let rx = act("fusion relu input", n);
            let t = act("fusion hidden", n);
            fwd.push(ops.rows(
                (f, side * side),
                Some(At::new(x)),
                At::off(b(vecs), zeros as usize),
                true,
                At::new(&rx),
            )?);
            fwd.extend(conv(
                &u.conv1,
                (side, side),
                At::new(&rx),
                At::new(&t),
                Act::Relu,
            )?);
            fwd.extend(ops.conv(&Conv {
                residual: Some(At::new(x)),
                ..Conv {
                    cin: f,
                    cout: f,
                    h: side,
                    w: side,
                    k: 3,
                    input: At::new(&t),
                    weight: b(u.conv2.weight),
                    bias: u.conv2.bias,
                    in_scale: None,
                    out_scale: None,
                    noise: None,
                    in_relu: false,
                    act: Act::None,
                    residual: None,
                    sft: None,
                    sigmoid: false,
                    out: At::new(out),
                }
            })?);
            let mut bwd = back(
                &u.conv2,
                (side, side),
                At::new(&t),
                At::new(dout),
                Some(At::new(&d_t)),
            )?;
            bwd.push(act_backward(
                gpu,
                Kept::ReluOutput,
                n,
                At::new(&t),
                At::new(&d_t),
                At::new(&d_z),
            )?);
            bwd.extend(back(
                &u.conv1,
                (side, side),
                At::new(&rx),
                At::new(&d_z),
                Some(At::new(&d_rx)),
            )?);
            bwd.push(act_backward(
                gpu,
                Kept::ReluOutput,
                n,
                At::new(&rx),
                At::new(&d_rx),
                At::new(&d_tmp),
            )?);
            bwd.push(ops.add(n, dout, &d_tmp, dx)?);
            keep.extend([rx, t]);
            Ok(bwd)
        };
        for (j, ((u1, u2, oc), (si, so))) in fusion.iter().zip(sides).enumerate() {
            let n_in = f * si * si;
            let (a, d_a): (&wgpu::Buffer, &wgpu::Buffer) = match j {
                0 => (&rn[3], &d_rn[3]),
                _ => (&fused[j - 1], &d_fused[j - 1]),
            };
            // The skip (layer_rn of level 2, 1, 0) through unit 1, added to `a`.
            let skip = match (j, u1) {
                (0, _) | (_, None) => None,
                (_, Some(u1)) => Some((u1, &rn[3 - j], &d_rn[3 - j])),
            };
            let mut bwd_skip = Vec::new();
            let x2 = match skip {
                Some((u1, sk, d_sk)) => {
                    let y1 = act("fusion unit 1", n_in);
                    let sum = act("fusion sum", n_in);
                    bwd_skip = unit(&mut fwd, &mut keep, u1, si, sk, &y1, d_a, d_sk)?;
                    fwd.push(ops.add(n_in, a, &y1, &sum)?);
                    keep.push(y1);
                    Some(sum)
                }
                None => None,
            };
            let x2_ref = x2.as_ref().unwrap_or(a);
            let y2 = act("fusion unit 2", n_in);
            let bwd_unit2 = unit(&mut fwd, &mut keep, u2, si, x2_ref, &y2, &d_u, d_a)?;
            let up = act("fusion upsampled", f * so * so);
            fwd.push(ops.resize_to((f, si, si), (so, so), At::new(&y2), At::new(&up))?);
            let out = act("dpt fused", f * so * so);
            let d_out = act("d dpt fused", f * so * so);
            fwd.extend(conv(oc, (so, so), At::new(&up), At::new(&out), Act::None)?);
            let mut bwd = back(
                oc,
                (so, so),
                At::new(&up),
                At::new(&d_out),
                Some(At::new(&d_up)),
            )?;
            bwd.push(resize_ac_backward(
                gpu,
                (f, si, si),
                (so, so),
                At::new(&d_up),
                At::new(&d_u),
            )?);
            bwd.extend(bwd_unit2);
            bwd.extend(bwd_skip);
            bwd_fusion.push(bwd);
            keep.extend([y2, up]);
            keep.extend(x2);
            fused.push(out);
            d_fused.push(d_out);
        }
        fwd.extend(conv(
            &output_conv,
            (s, s),
            At::new(&fused[3]),
            At::new(&f_local),
            Act::None,
        )?);
        // The backward runs last layer first: the output convolution, the fusion blocks from
        // refinenet.3 down, then the levels.
        let mut bwd = back(
            &output_conv,
            (s, s),
            At::new(&fused[3]),
            At::new(&grad_f_local),
            Some(At::new(&d_fused[3])),
        )?;
        for steps in bwd_fusion.into_iter().rev() {
            bwd.extend(steps);
        }
        for steps in bwd_levels {
            bwd.extend(steps);
        }
        keep.extend(rn);
        keep.extend(d_rn);
        keep.extend(fused);
        keep.extend(d_fused);
        keep.extend([
            split,
            flipped,
            part,
            dummy,
            d_up,
            d_u,
            d_t,
            d_z,
            d_rx,
            d_tmp,
            taps.starts,
            taps.weights,
        ]);
        Ok(Self {
            c,
            g,
            d,
            f,
            s,
            tokens,
            image,
            f_local,
            grad_f_local,
            buffers: st.buffers,
            params: st.params,
            permuted,
            grad_buffers,
            forward: fwd,
            backward: bwd,
            samples: 0,
            _keep: keep,
        })
    }

    /// Overwrites every weight with `value(key)` (checkpoint keys, checkpoint layouts); the
    /// gradient sums start again.
    pub fn set_weights(&mut self, gpu: &Gpu, value: &ParamSource) -> Result<()> {
        let mut product: HashMap<&str, Vec<f32>> = HashMap::new();
        for p in &self.permuted {
            let v = value(&p.key).ok_or_else(|| GpuError::Weights(format!("no {}", p.key)))?;
            if v.len() != p.c * p.c * p.taps {
                return Err(GpuError::Weights(format!(
                    "{}: {} values, expected {}",
                    p.key,
                    v.len(),
                    p.c * p.c * p.taps
                )));
            }
            product.insert(&p.key, p.to_product(v));
        }
        let source = |key: &str| -> Option<&[f32]> {
            match product.get(key) {
                Some(v) => Some(v.as_slice()),
                None => value(key),
            }
        };
        write_params(gpu, &self.buffers, &self.params, &source)?;
        self.samples = 0;
        Ok(())
    }

    /// One sample's forward: the four backbone outputs `[g^2, vit_dim]` each (patches
    /// row-major, as `gagavatar_net::dino::Dinov2::forward` returns them) and the normalised
    /// DINO input `[3, d, d]`. `F_local` stays on the device ([`GpuDptGrad::f_local`]).
    pub fn forward(&mut self, gpu: &Gpu, tokens: [&[f32]; 4], image: &[f32]) -> Result<()> {
        let (c, g2, d) = (self.c, self.g * self.g, self.d);
        for (k, t) in tokens.iter().enumerate() {
            if t.len() != g2 * c {
                return Err(input_err(
                    "DPT head",
                    format!(
                        "backbone output {k}: {} values, expected {}",
                        t.len(),
                        g2 * c
                    ),
                ));
            }
        }
        if image.len() != 3 * d * d {
            return Err(input_err(
                "DPT head",
                format!("{} DINO input values, expected {}", image.len(), 3 * d * d),
            ));
        }
        let mut cm = vec![0f32; c * g2];
        for (t, buf) in tokens.iter().zip(&self.tokens) {
            for (tok, row) in t.chunks_exact(c).enumerate() {
                for (ch, v) in row.iter().enumerate() {
                    cm[ch * g2 + tok] = *v;
                }
            }
            gpu.queue.write_buffer(buf, 0, bytemuck::cast_slice(&cm));
        }
        gpu.queue
            .write_buffer(&self.image, 0, bytemuck::cast_slice(image));
        gpu.submit(&self.forward);
        Ok(())
    }

    /// `F_local` `[F, S, S]` of the last forward, on the device.
    pub fn f_local(&self) -> &wgpu::Buffer {
        &self.f_local
    }

    /// Floats of `F_local`.
    pub fn f_local_len(&self) -> usize {
        self.f * self.s * self.s
    }

    /// `F_local` of the last forward, read back.
    pub fn read_f_local(&self, gpu: &Gpu) -> Result<Vec<f32>> {
        gpu.read_f32(&self.f_local, self.f_local_len())
    }

    /// The backward of the last forward from the gradient of `F_local` (host values); the
    /// weight gradients are added to the step's sums.
    pub fn backward(&mut self, gpu: &Gpu, grad_f_local: &[f32]) -> Result<()> {
        if grad_f_local.len() != self.f_local_len() {
            return Err(input_err(
                "DPT head",
                format!(
                    "{} F_local gradient values, expected {}",
                    grad_f_local.len(),
                    self.f_local_len()
                ),
            ));
        }
        gpu.queue
            .write_buffer(&self.grad_f_local, 0, bytemuck::cast_slice(grad_f_local));
        self.run_backward(gpu, None)
    }

    /// [`GpuDptGrad::backward`] from the first [`GpuDptGrad::f_local_len`] floats of a device
    /// buffer (the lifting generators' input gradient), without a trip through the host.
    pub fn backward_from(&mut self, gpu: &Gpu, grad_f_local: &wgpu::Buffer) -> Result<()> {
        let bytes = 4 * self.f_local_len() as u64;
        if grad_f_local.size() < bytes {
            return Err(GpuError::Device(format!(
                "DPT backward: the F_local gradient buffer holds {} bytes, {bytes} needed",
                grad_f_local.size()
            )));
        }
        self.run_backward(gpu, Some(grad_f_local))
    }

    fn run_backward(&mut self, gpu: &Gpu, copy_from: Option<&wgpu::Buffer>) -> Result<()> {
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("DPT backward inputs"),
            });
        if let Some(src) = copy_from {
            enc.copy_buffer_to_buffer(src, 0, &self.grad_f_local, 0, 4 * self.f_local_len() as u64);
        }
        if self.samples == 0 {
            for &i in &self.grad_buffers {
                enc.clear_buffer(&self.buffers[i], 0, None);
            }
        }
        gpu.queue.submit([enc.finish()]);
        gpu.submit(&self.backward);
        self.samples += 1;
        Ok(())
    }

    /// Every weight's gradient summed over the backward passes since the weights were set,
    /// by checkpoint key, in checkpoint layouts.
    pub fn read_grads(&mut self, gpu: &Gpu) -> Result<Vec<(String, Vec<f32>)>> {
        if self.samples == 0 {
            return Err(input_err(
                "DPT gradients",
                "no backward since the weights were set",
            ));
        }
        let mut grads = read_grads(gpu, &self.buffers, &self.params)?;
        for (key, v) in &mut grads {
            if let Some(p) = self.permuted.iter().find(|p| &p.key == key) {
                *v = p.to_checkpoint(v);
            }
        }
        Ok(grads)
    }
}

/// Records `dx` `[c k k, g, g]`, the gradient of `shuffle`'s product, from its output's
/// gradient `dy` `[c, g k, g k]`.
fn shuffle_backward(
    gpu: &Gpu,
    (c, g, k): (usize, usize, usize),
    dy: At,
    dx: &wgpu::Buffer,
) -> Result<Step> {
    let kern = gpu.kernel(
        "shuffle_backward",
        SHUFFLE_BACKWARD,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "shuffle backward",
        &Params::new()
            .u(c as u32)
            .u(g as u32)
            .u(k as u32)
            .u(dy.off)
            .u(0)
            .u(0)
            .u(0)
            .u(0),
    );
    let bg = gpu.bind(&kern, &[&u, dy.buf, dx])?;
    Ok(Step::new(kern, bg, linear_grid(c * k * k * g * g, 256)))
}

/// Records the input gradient `dx` `[c, h, w]` of `Ops::resize_to` (bilinear, align_corners)
/// from its output's gradient `dy` `[c, oh, ow]`; `dx` is overwritten.
pub fn resize_ac_backward(
    gpu: &Gpu,
    (c, h, w): (usize, usize, usize),
    (oh, ow): (usize, usize),
    dy: At,
    dx: At,
) -> Result<Step> {
    if c == 0 || h == 0 || w == 0 || oh == 0 || ow == 0 {
        return Err(GpuError::Device(format!(
            "align-corners resize gradient of {c}x{h}x{w} -> {oh}x{ow}"
        )));
    }
    let kern = gpu.kernel(
        "resize_ac_backward",
        RESIZE_AC_BACKWARD,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "resize ac backward",
        &Params::new()
            .u(c as u32)
            .u(h as u32)
            .u(w as u32)
            .u(oh as u32)
            .u(ow as u32)
            .u(dy.off)
            .u(dx.off)
            .u(0),
    );
    let bg = gpu.bind(&kern, &[&u, dy.buf, dx.buf])?;
    Ok(Step::new(kern, bg, linear_grid(c * h * w, 256)))
}
