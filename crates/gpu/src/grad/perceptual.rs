//! The loss's perceptual term on the GPU (`gagavatar_train::perceptual`): the frozen AlexNet
//! and VGG-Face features of the target's head-box crop and of both predictions' (coarse RGB,
//! fine), the ten weighted layer distances per prediction, and their backward to the two
//! crops, added to the crops' gradients that the box terms wrote. Only input gradients: the
//! networks are fixed.
//!
//! Each 3x3 convolution runs on the renderer's kernels (its input gradient is the rotated
//! kernel's convolution, [`super::conv::input_grad`]); AlexNet's 11x11 stride-4 and 5x5 layers
//! are im2col + a 1x1 product forward and the transposed product + col2im backward.
//! Max-pooling gives each window's gradient to its first maximum (PyTorch's rule, the CPU op's).

use std::collections::HashMap;

use gagavatar_train::perceptual::{
    ALEX, IMAGENET_MEAN, IMAGENET_STD, LAYER_WEIGHTS, VGG, VGGFACE_MEAN, VGG_BLOCKS, VGG_FACTOR,
};

use super::conv::{input_grad, ConvGrad};
use super::layers::{act_backward, col2im, l1_sum, Kept};
use crate::conv::{Act, At, Conv, Ops};
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Params, Step};
use crate::tuning::Tuning;

const AFFINE: &str = include_str!("../shaders/channel_affine.wgsl");
const MAXPOOL: &str = include_str!("../shaders/maxpool.wgsl");
const MAXPOOL_BACKWARD: &str = include_str!("../shaders/maxpool_backward.wgsl");
const DISTANCE: &str = include_str!("../shaders/percep_distance.wgsl");

/// The three `[3, size, size]` crops and the two prediction crops' gradients, shared by the
/// box terms (which write them) and the perceptual term (which reads the crops and adds to the
/// gradients).
#[derive(Clone)]
pub struct CropBuffers {
    pub size: usize,
    pub coarse: wgpu::Buffer,
    pub fine: wgpu::Buffer,
    pub target: wgpu::Buffer,
    pub grad_coarse: wgpu::Buffer,
    pub grad_fine: wgpu::Buffer,
}

impl CropBuffers {
    pub fn new(gpu: &Gpu, size: usize) -> Self {
        let b = |what: &str| gpu.buffer(what, 4 * (3 * size * size) as u64);
        Self {
            size,
            coarse: b("coarse crop"),
            fine: b("fine crop"),
            target: b("target crop"),
            grad_coarse: b("dL/dcoarse crop"),
            grad_fine: b("dL/dfine crop"),
        }
    }

    pub fn floats(&self) -> usize {
        3 * self.size * self.size
    }
}

/// One layer of a network as the GPU runs it.
#[derive(Debug, Clone, Copy)]
enum Layer {
    /// Input normalisation `a x + b` per channel.
    Affine {
        a: [f32; 3],
        b: [f32; 3],
    },
    /// Convolution `conv` (index into the convolutions) and ReLU; `feature`: the weight of its
    /// output's layer distance.
    Conv {
        conv: usize,
        feature: Option<f64>,
    },
    Pool {
        k: usize,
        s: usize,
    },
}

/// A frozen convolution's weights on the device.
struct FrozenConv {
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    pad: usize,
    weight: wgpu::Buffer,
    /// `[cin k k, cout]`: the transposed product of an im2col layer's backward.
    weight_t: Option<wgpu::Buffer>,
    bias: u32,
}

impl FrozenConv {
    fn im2col(&self) -> bool {
        self.weight_t.is_some()
    }
    fn out_hw(&self, h: usize, w: usize) -> (usize, usize) {
        (
            (h + 2 * self.pad - self.k) / self.stride + 1,
            (w + 2 * self.pad - self.k) / self.stride + 1,
        )
    }
}

/// The perceptual term of one sample at a time (see the module's text), recorded once.
pub struct GpuPerceptual {
    /// `[2, 10]`: the weighted layer terms of the coarse and the fine prediction.
    values: wgpu::Buffer,
    steps: Vec<Step>,
    // The buffers the recorded steps bind, kept alive with them.
    _held: Vec<wgpu::Buffer>,
}

fn shape_after(layers: &[Layer], convs: &[FrozenConv], size: usize) -> Vec<(usize, usize, usize)> {
    let mut shapes = Vec::with_capacity(layers.len());
    let (mut c, mut h, mut w) = (3, size, size);
    for l in layers {
        match *l {
            Layer::Affine { .. } => {}
            Layer::Conv { conv, .. } => {
                let f = &convs[conv];
                (h, w) = f.out_hw(h, w);
                c = f.cout;
            }
            Layer::Pool { k, s } => {
                h = (h - k) / s + 1;
                w = (w - k) / s + 1;
            }
        }
        shapes.push((c, h, w));
    }
    shapes
}

impl GpuPerceptual {
    /// Uploads the networks (`weights` by key without `percep_loss.`, as
    /// `PerceptualLoss::host_weights` gives them) and records the term for the crops of
    /// `crops`, scaled by `weight` (the loss's perceptual factor); the gradients are added to
    /// `crops.grad_coarse` and `crops.grad_fine`. Needs `crops.size >= 31` (AlexNet's pooling).
    pub fn new(
        gpu: &Gpu,
        tuning: &Tuning,
        weights: &HashMap<String, Vec<f32>>,
        crops: &CropBuffers,
        weight: f64,
    ) -> Result<Self> {
        let size = crops.size;
        if size < 31 {
            return Err(GpuError::Input {
                name: "perceptual crops".into(),
                reason: format!("{size}x{size}: AlexNet needs at least 31x31"),
            });
        }
        // f32 throughout, as the other training kernels.
        let tuning = &Tuning {
            mma: false,
            ..tuning.for_device(gpu)
        };
        let get = |key: &str, n: usize| -> Result<&Vec<f32>> {
            let v = weights
                .get(key)
                .ok_or_else(|| GpuError::Weights(format!("no percep_loss.{key}")))?;
            if v.len() != n {
                return Err(GpuError::Weights(format!(
                    "percep_loss.{key}: {} values, expected {n}",
                    v.len()
                )));
            }
            Ok(v)
        };
        let mut convs = Vec::new();
        let mut biases: Vec<f32> = Vec::new();
        let mut add_conv = |key: &str,
                            (cin, cout, k, stride, pad): (usize, usize, usize, usize, usize)|
         -> Result<usize> {
            let w = get(&format!("{key}.weight"), cout * cin * k * k)?;
            let b = get(&format!("{key}.bias"), cout)?;
            let bias = biases.len() as u32;
            biases.extend_from_slice(b);
            let weight_t = (k != 1 && k != 3 || stride != 1).then(|| {
                let rows = cin * k * k;
                let mut t = vec![0f32; rows * cout];
                for o in 0..cout {
                    for r in 0..rows {
                        t[r * cout + o] = w[o * rows + r];
                    }
                }
                gpu.buffer_with(&format!("{key} transposed"), &t)
            });
            convs.push(FrozenConv {
                cin,
                cout,
                k,
                stride,
                pad,
                weight: gpu.buffer_with(key, w),
                weight_t,
                bias,
            });
            Ok(convs.len() - 1)
        };

        let mut alex = vec![Layer::Affine {
            a: IMAGENET_STD.map(|s| (1.0 / s) as f32),
            b: [0, 1, 2].map(|c| (-IMAGENET_MEAN[c] / IMAGENET_STD[c]) as f32),
        }];
        for (l, &(key, cin, cout, k, stride, pad, pool)) in ALEX.iter().enumerate() {
            if pool {
                alex.push(Layer::Pool { k: 3, s: 2 });
            }
            let conv = add_conv(key, (cin, cout, k, stride, pad))?;
            alex.push(Layer::Conv {
                conv,
                feature: Some(LAYER_WEIGHTS[l] * weight),
            });
        }
        let mut vgg = vec![Layer::Affine {
            a: [255.0; 3],
            b: VGGFACE_MEAN.map(|m| -m as f32),
        }];
        for (bi, block) in VGG_BLOCKS.iter().enumerate() {
            if bi > 0 {
                vgg.push(Layer::Pool { k: 2, s: 2 });
            }
            for (j, &idx) in block.iter().enumerate() {
                let (_, cin, cout) = VGG
                    .iter()
                    .copied()
                    .find(|v| v.0 == idx)
                    .ok_or_else(|| GpuError::Weights(format!("no VGG layer {idx}")))?;
                let conv = add_conv(&format!("vggface.network.{idx}"), (cin, cout, 3, 1, 1))?;
                vgg.push(Layer::Conv {
                    conv,
                    feature: (j + 1 == block.len())
                        .then_some(LAYER_WEIGHTS[bi] * VGG_FACTOR * weight),
                });
            }
        }
        let nets = [alex, vgg];
        let shapes: Vec<Vec<(usize, usize, usize)>> =
            nets.iter().map(|n| shape_after(n, &convs, size)).collect();

        // Scratch shared by every layer: split-K sums, im2col patches, rotated weights,
        // pre-activation gradients, per-position distances.
        let (mut split, mut cols, mut flipped, mut dz, mut positions) = (1, 1, 1, 1, 1);
        for (net, sh) in nets.iter().zip(&shapes) {
            for (l, &(c, h, w)) in net.iter().zip(sh) {
                if let Layer::Conv { conv, .. } = *l {
                    let f = &convs[conv];
                    let (kk, ci) = if f.im2col() {
                        (1, f.cin * f.k * f.k)
                    } else {
                        (f.k, f.cin)
                    };
                    split = split
                        .max(Ops::split_need(tuning, ci, f.cout, h, w, kk))
                        .max(Ops::split_need(tuning, f.cout, ci, h, w, kk));
                    if f.im2col() {
                        cols = cols.max(ci * h * w);
                    } else {
                        flipped = flipped.max(f.cin * f.cout * 9);
                    }
                    dz = dz.max(c * h * w);
                    positions = positions.max(h * w);
                }
            }
        }
        let buf = |what: &str, n: usize| gpu.buffer(what, 4 * n as u64);
        let split = buf("perceptual split-K sums", split);
        let cols = buf("perceptual patches", cols);
        let flipped = buf("perceptual rotated weights", flipped);
        let dz = buf("perceptual dZ", dz);
        let d_pos = buf("perceptual distances", positions);
        let zeros = buf("zeros", positions);
        let vecs = gpu.buffer_with("perceptual biases", &biases);
        let dummy = buf("unused", 4);
        let values = buf("perceptual terms", 20);
        let ops = Ops {
            gpu,
            tuning,
            vecs: &vecs,
            dummy: &dummy,
            split_scratch: &split,
        };
        let scratch = Scratch {
            cols: &cols,
            flipped: &flipped,
            dz: &dz,
            d_pos: &d_pos,
            zeros: &zeros,
            dummy: &dummy,
            values: &values,
        };

        let mut held = Vec::new();
        let mut steps = Vec::new();
        let inputs = [&crops.target, &crops.coarse, &crops.fine];
        let grads = [&crops.grad_coarse, &crops.grad_fine];
        for (ni, (net, sh)) in nets.iter().zip(&shapes).enumerate() {
            // Forward of the three images, keeping every layer's output.
            let mut acts: Vec<Vec<wgpu::Buffer>> = Vec::new();
            for input in inputs {
                let a: Vec<wgpu::Buffer> = sh
                    .iter()
                    .map(|&(c, h, w)| buf("perceptual activation", c * h * w))
                    .collect();
                steps.extend(forward(&ops, &scratch, net, &convs, sh, size, input, &a)?);
                acts.push(a);
            }
            // Backward of both predictions into the crops' gradients.
            for p in 0..2 {
                let g: Vec<wgpu::Buffer> = sh
                    .iter()
                    .map(|&(c, h, w)| buf("perceptual gradient", c * h * w))
                    .collect();
                let slot = (p * 10 + ni * 5) as u32;
                steps.extend(backward(
                    &ops,
                    &scratch,
                    net,
                    &convs,
                    sh,
                    size,
                    (&acts[p + 1], &acts[0]),
                    inputs[p + 1],
                    &g,
                    grads[p],
                    slot,
                )?);
                held.extend(g);
            }
            held.extend(acts.into_iter().flatten());
        }
        held.extend([split, cols, flipped, dz, d_pos, zeros, vecs, dummy]);
        for c in convs {
            held.push(c.weight);
            held.extend(c.weight_t);
        }
        Ok(Self {
            values,
            steps,
            _held: held,
        })
    }

    /// Forward and backward of both predictions (after the crops and the box terms' gradients
    /// are written, before the crops' backward).
    pub fn steps(&self) -> &[Step] {
        &self.steps
    }

    /// The term's value (both predictions, weighted) after the steps ran.
    pub fn read(&self, gpu: &Gpu) -> Result<f64> {
        Ok(gpu
            .read_f32(&self.values, 20)?
            .iter()
            .map(|&v| v as f64)
            .sum())
    }
}

struct Scratch<'a> {
    cols: &'a wgpu::Buffer,
    flipped: &'a wgpu::Buffer,
    dz: &'a wgpu::Buffer,
    d_pos: &'a wgpu::Buffer,
    zeros: &'a wgpu::Buffer,
    dummy: &'a wgpu::Buffer,
    values: &'a wgpu::Buffer,
}

fn affine(
    gpu: &Gpu,
    n: usize,
    (a, b): ([f32; 3], [f32; 3]),
    x: &wgpu::Buffer,
    y: &wgpu::Buffer,
    acc: bool,
) -> Result<Step> {
    let k = gpu.kernel(
        "channel_affine",
        AFFINE,
        &[("ACC", acc.to_string())],
        &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "channel affine",
        &Params::new()
            .u(n as u32)
            .u(0)
            .u(0)
            .u(0)
            .f(a[0])
            .f(a[1])
            .f(a[2])
            .f(0.0)
            .f(b[0])
            .f(b[1])
            .f(b[2])
            .f(0.0),
    );
    let g = gpu.bind(&k, &[&u, x, y])?;
    Ok(Step::new(k, g, linear_grid(3 * n, 256)))
}

fn pool_params(gpu: &Gpu, (c, h, w): (usize, usize, usize), k: usize, s: usize) -> wgpu::Buffer {
    gpu.uniform(
        "max-pool",
        &Params::new()
            .u(c as u32)
            .u(h as u32)
            .u(w as u32)
            .u(k as u32)
            .u(s as u32)
            .u(((h - k) / s + 1) as u32)
            .u(((w - k) / s + 1) as u32)
            .u(0),
    )
}

/// Records one image's forward through `net` from `input` into `acts` (one per layer).
#[allow(clippy::too_many_arguments)]
fn forward(
    ops: &Ops,
    sc: &Scratch,
    net: &[Layer],
    convs: &[FrozenConv],
    shapes: &[(usize, usize, usize)],
    size: usize,
    input: &wgpu::Buffer,
    acts: &[wgpu::Buffer],
) -> Result<Vec<Step>> {
    let gpu = ops.gpu;
    let mut steps = Vec::new();
    let mut prev_shape = (3, size, size);
    for (i, l) in net.iter().enumerate() {
        let src = if i == 0 { input } else { &acts[i - 1] };
        let out = &acts[i];
        let (c, h, w) = shapes[i];
        match *l {
            Layer::Affine { a, b } => {
                steps.push(affine(gpu, size * size, (a, b), src, out, false)?)
            }
            Layer::Conv { conv, .. } => {
                let f = &convs[conv];
                let (pc, ph, pw) = prev_shape;
                let (input_at, cin, k) = if f.im2col() {
                    let (step, _, _) = ops.im2col(
                        (pc, ph, pw),
                        f.k,
                        f.stride,
                        f.pad,
                        At::new(src),
                        At::new(sc.cols),
                    )?;
                    steps.push(step);
                    (At::new(sc.cols), f.cin * f.k * f.k, 1)
                } else {
                    (At::new(src), f.cin, f.k)
                };
                steps.extend(ops.conv(&Conv {
                    cin,
                    cout: f.cout,
                    h,
                    w,
                    k,
                    input: input_at,
                    weight: &f.weight,
                    bias: Some(f.bias),
                    in_scale: None,
                    out_scale: None,
                    noise: None,
                    in_relu: false,
                    act: Act::Relu,
                    residual: None,
                    sft: None,
                    sigmoid: false,
                    out: At::new(out),
                })?);
            }
            Layer::Pool { k, s } => {
                let kern = gpu.kernel(
                    "maxpool",
                    MAXPOOL,
                    &[],
                    &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
                )?;
                let u = pool_params(gpu, prev_shape, k, s);
                let g = gpu.bind(&kern, &[&u, src, out])?;
                steps.push(Step::new(kern, g, linear_grid(c * h * w, 256)));
            }
        }
        prev_shape = (c, h, w);
    }
    Ok(steps)
}

/// Records the distances of one prediction's features `acts.0` to the target's `acts.1` into
/// `values[slot..slot + 5]` and their backward through `net` into `grad_input` (added).
#[allow(clippy::too_many_arguments)]
fn backward(
    ops: &Ops,
    sc: &Scratch,
    net: &[Layer],
    convs: &[FrozenConv],
    shapes: &[(usize, usize, usize)],
    size: usize,
    (pred, target): (&[wgpu::Buffer], &[wgpu::Buffer]),
    input: &wgpu::Buffer,
    g: &[wgpu::Buffer],
    grad_input: &wgpu::Buffer,
    mut slot: u32,
) -> Result<Vec<Step>> {
    let gpu = ops.gpu;
    let mut steps = Vec::new();
    let last = net.len() - 1;
    for i in (0..net.len()).rev() {
        let (c, h, w) = shapes[i];
        let n = h * w;
        let in_shape = if i == 0 {
            (3, size, size)
        } else {
            shapes[i - 1]
        };
        if let Layer::Conv {
            feature: Some(wl), ..
        } = net[i]
        {
            let scale = (wl / n as f64) as f32;
            let k = gpu.kernel(
                "percep_distance",
                DISTANCE,
                &[("ACC", (i != last).to_string())],
                &[
                    Bind::Uniform,
                    Bind::Read,
                    Bind::Read,
                    Bind::ReadWrite,
                    Bind::ReadWrite,
                ],
            )?;
            let u = gpu.uniform(
                "perceptual distance",
                &Params::new()
                    .u(c as u32)
                    .u(n as u32)
                    .u(0)
                    .u(0)
                    .f(scale)
                    .u(0)
                    .u(0)
                    .u(0),
            );
            let bg = gpu.bind(&k, &[&u, &pred[i], &target[i], sc.d_pos, &g[i]])?;
            steps.push(Step::new(k, bg, linear_grid(n, 256)));
            // The distances are non-negative: their L1 sum against zeros is their sum.
            steps.push(l1_sum(
                gpu,
                n,
                At::new(sc.d_pos),
                At::new(sc.zeros),
                scale,
                sc.values,
                slot,
            )?);
            slot += 1;
        }
        match net[i] {
            Layer::Affine { a, .. } => {
                steps.push(affine(
                    gpu,
                    size * size,
                    (a, [0.0; 3]),
                    &g[i],
                    grad_input,
                    true,
                )?);
            }
            Layer::Conv { conv, .. } => {
                let f = &convs[conv];
                steps.push(act_backward(
                    gpu,
                    Kept::ReluOutput,
                    c * n,
                    At::new(&pred[i]),
                    At::new(&g[i]),
                    At::new(sc.dz),
                )?);
                let dst = &g[i - 1];
                let src = if i == 0 { input } else { &pred[i - 1] };
                if let Some(wt) = &f.weight_t {
                    let rows = f.cin * f.k * f.k;
                    steps.extend(ops.conv(&Conv {
                        cin: f.cout,
                        cout: rows,
                        h,
                        w,
                        k: 1,
                        input: At::new(sc.dz),
                        weight: wt,
                        bias: None,
                        in_scale: None,
                        out_scale: None,
                        noise: None,
                        in_relu: false,
                        act: Act::None,
                        residual: None,
                        sft: None,
                        sigmoid: false,
                        out: At::new(sc.cols),
                    })?);
                    steps.push(col2im(
                        gpu,
                        in_shape,
                        (f.k, f.stride, f.pad),
                        (h, w),
                        sc.cols,
                        dst,
                    )?);
                } else {
                    let cg = ConvGrad {
                        cin: f.cin,
                        cout: f.cout,
                        h,
                        w,
                        k: f.k,
                        input: At::new(src),
                        weight: &f.weight,
                        grad_out: At::new(sc.dz),
                        grad_input: Some(At::new(dst)),
                        grad_weight: At::new(sc.dummy),
                        grad_bias: None,
                        accumulate: false,
                    };
                    steps.extend(input_grad(ops, &cg, sc.flipped, At::new(dst), None, None)?);
                }
            }
            Layer::Pool { k, s } => {
                let kern = gpu.kernel(
                    "maxpool_backward",
                    MAXPOOL_BACKWARD,
                    &[],
                    &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
                )?;
                let u = pool_params(gpu, in_shape, k, s);
                let (ic, ih, iw) = in_shape;
                let bg = gpu.bind(&kern, &[&u, &pred[i - 1], &g[i], &g[i - 1]])?;
                steps.push(Step::new(kern, bg, linear_grid(ic * ih * iw, 256)));
            }
        }
    }
    Ok(steps)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{assert_close_rel, gpu};
    use candle_core::{DType, Device, Tensor, Var};
    use gagavatar_splat::testscene::Rng;
    use gagavatar_train::perceptual::{seeded_weights, PerceptualLoss, PERCEP_PREFIX};

    /// The term against the CPU's (candle's autograd through the fused CPU kernels): sums of
    /// up to 512 x 9 products per value in another order, through eight layers.
    const PERCEP_RTOL: f64 = 1e-4;

    /// Crops of 40x40 (AlexNet's pooling chain down to 1x1), seeded stand-in weights, crop
    /// gradients that start non-zero (the box terms'): the value and both crops' gradients.
    #[test]
    fn perceptual_term_and_gradients_match_the_cpu() {
        let Some(g) = gpu() else { return };
        let size = 40;
        let weight = 0.01;
        let w: HashMap<String, Tensor> = seeded_weights(3)
            .unwrap()
            .into_iter()
            .map(|(k, v)| (format!("{PERCEP_PREFIX}{k}"), v))
            .collect();
        let cpu = PerceptualLoss::from_tensors(&w, DType::F32, &Device::Cpu)
            .unwrap()
            .unwrap();
        let crops = CropBuffers::new(g, size);
        let p = GpuPerceptual::new(
            g,
            &Tuning::default(),
            &cpu.host_weights().unwrap(),
            &crops,
            weight,
        )
        .unwrap();
        let mut rng = Rng::new(11);
        let n = crops.floats();
        let mut img = || -> Vec<f32> { (0..n).map(|_| rng.range(0.0, 1.0) as f32).collect() };
        let (t, c, f) = (img(), img(), img());
        let start: Vec<f32> = (0..n).map(|i| (i % 7) as f32 * 1e-3).collect();
        for (buf, v) in [
            (&crops.target, &t),
            (&crops.coarse, &c),
            (&crops.fine, &f),
            (&crops.grad_coarse, &start),
            (&crops.grad_fine, &start),
        ] {
            g.queue.write_buffer(buf, 0, bytemuck::cast_slice(v));
        }
        g.submit(p.steps());
        let got = p.read(g).unwrap();
        let got_dc = g.read_f32(&crops.grad_coarse, n).unwrap();
        let got_df = g.read_f32(&crops.grad_fine, n).unwrap();

        let dev = Device::Cpu;
        let shape = (1, 3, size, size);
        let vc = Var::from_vec(c, shape, &dev).unwrap();
        let vf = Var::from_vec(f, shape, &dev).unwrap();
        let target = cpu
            .features(&Tensor::from_vec(t, shape, &dev).unwrap())
            .unwrap();
        let pred = cpu
            .features(&Tensor::cat(&[vc.as_tensor(), vf.as_tensor()], 0).unwrap())
            .unwrap();
        let d = (PerceptualLoss::distance(&pred, &target).unwrap() * weight).unwrap();
        let want = d.to_scalar::<f32>().unwrap() as f64;
        let diff = (want - got).abs();
        eprintln!("perceptual term: GPU {got}, CPU {want} (difference {diff:e})");
        assert!(
            diff <= PERCEP_RTOL * want,
            "term: expected {want}, got {got}"
        );
        let grads = d.backward().unwrap();
        for (what, v, got) in [("d coarse crop", &vc, got_dc), ("d fine crop", &vf, got_df)] {
            let want: Vec<f32> = grads
                .get(v.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let got: Vec<f32> = got.iter().zip(&start).map(|(a, s)| a - s).collect();
            assert_close_rel(what, &want, &got, PERCEP_RTOL);
        }
    }

    /// The GPU's own gradient against central differences of the GPU's own term along random
    /// directions (f64 arithmetic on the f32 values): the backward kernels (distance, ReLU,
    /// max-pool, col2im, the rotated convolutions, the input affine) are the derivative of the
    /// forward ones. ReLU, max-pool and |.| have kinks, so a step may cross one: the bound
    /// allows that, and the directions are many.
    #[test]
    fn perceptual_gradient_matches_central_differences() {
        let Some(g) = gpu() else { return };
        let size = 36;
        let w = seeded_weights(4).unwrap();
        let host: HashMap<String, Vec<f32>> = w
            .iter()
            .map(|(k, v)| (k.clone(), v.flatten_all().unwrap().to_vec1().unwrap()))
            .collect();
        let crops = CropBuffers::new(g, size);
        let p = GpuPerceptual::new(g, &Tuning::default(), &host, &crops, 1.0).unwrap();
        let n = crops.floats();
        let mut rng = Rng::new(21);
        let t: Vec<f32> = (0..n).map(|_| rng.range(0.0, 1.0) as f32).collect();
        let f: Vec<f32> = (0..n).map(|_| rng.range(0.0, 1.0) as f32).collect();
        let c: Vec<f32> = (0..n).map(|_| rng.range(0.0, 1.0) as f32).collect();
        let zeros = vec![0f32; n];
        let run = |coarse: &[f32]| -> (f64, Vec<f32>) {
            for (buf, v) in [
                (&crops.target, &t[..]),
                (&crops.coarse, coarse),
                (&crops.fine, &f[..]),
                (&crops.grad_coarse, &zeros[..]),
                (&crops.grad_fine, &zeros[..]),
            ] {
                g.queue.write_buffer(buf, 0, bytemuck::cast_slice(v));
            }
            g.submit(p.steps());
            (
                p.read(g).unwrap(),
                g.read_f32(&crops.grad_coarse, n).unwrap(),
            )
        };
        let (_, grad) = run(&c);
        let h = 2e-4;
        let mut worst = 0f64;
        for k in 0..4 {
            let dir: Vec<f64> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
            let moved = |s: f64| -> Vec<f32> {
                c.iter()
                    .zip(&dir)
                    .map(|(&x, d)| (x as f64 + s * d) as f32)
                    .collect()
            };
            let (up, _) = run(&moved(h));
            let (down, _) = run(&moved(-h));
            let fd = (up - down) / (2.0 * h);
            let an: f64 = grad.iter().zip(&dir).map(|(&g, d)| g as f64 * d).sum();
            let rel = (fd - an).abs() / an.abs().max(1e-12);
            eprintln!(
                "direction {k}: differences {fd:.6e}, gradient {an:.6e} (relative {rel:.2e})"
            );
            worst = worst.max(rel);
        }
        assert!(
            worst <= FD_RTOL,
            "worst relative difference {worst:e} > {FD_RTOL:e}"
        );
    }

    /// Central differences (step 2e-4 along a direction over all 3888 values) of an f32
    /// forward with kinks: worst of six directions on lavapipe 1.3e-2 (at step 2e-3, where
    /// more kinks fall inside the step, 8e-2); the CPU term, which the GPU's gradient matches
    /// to 1e-6, is checked against f64 differences in crates/train/tests/perceptual.rs.
    const FD_RTOL: f64 = 2.5e-2;
}
