//! The gradients of the renderer's elementwise and small layers: activations, the x2 resizes,
//! the mapping network's normalisation, and of an L1 loss.

use crate::conv::At;
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Grid, Params, Step};

const ACT_BACKWARD: &str = include_str!("../shaders/act_backward.wgsl");
const RESIZE_BACKWARD: &str = include_str!("../shaders/resize_backward.wgsl");
const RMS_NORM_BACKWARD: &str = include_str!("../shaders/rms_norm_backward.wgsl");
const L1_GRAD: &str = include_str!("../shaders/l1_grad.wgsl");
const L1_SUM: &str = include_str!("../shaders/l1_sum.wgsl");
const COL2IM: &str = include_str!("../shaders/col2im.wgsl");

/// An activation and the value its backward reads (what the forward keeps).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kept {
    /// Leaky ReLU (0.2), from its output (same sign as its input).
    LreluOutput,
    /// ReLU, from its output.
    ReluOutput,
    /// GELU (erf), from its input.
    GeluInput,
    /// The logistic sigmoid, from its output: `y (1 - y)`.
    SigmoidOutput,
}

impl Kept {
    fn code(self) -> u32 {
        match self {
            Kept::LreluOutput => 1,
            Kept::ReluOutput => 2,
            Kept::GeluInput => 3,
            Kept::SigmoidOutput => 4,
        }
    }
}

/// Records `dZ = dY * act'(.)` over `n` values, from what `kept` names; `out` may not share a
/// buffer with `kept` or `dy`.
pub fn act_backward(gpu: &Gpu, act: Kept, n: usize, kept: At, dy: At, out: At) -> Result<Step> {
    let k = gpu.kernel(
        "act_backward",
        ACT_BACKWARD,
        &[("ACT", act.code().to_string())],
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "act backward",
        &Params::new().u(n as u32).u(kept.off).u(dy.off).u(out.off),
    );
    let g = gpu.bind(&k, &[&u, kept.buf, dy.buf, out.buf])?;
    Ok(Step::new(k, g, linear_grid(n, 256)))
}

/// Records the input gradient `dx` `[c, h_in, w_in]` of `Ops::resize` (x2 bilinear `up`, or
/// the 2x2 mean) from its output's gradient `dy`; `dx` is overwritten.
pub fn resize_backward(
    gpu: &Gpu,
    up: bool,
    (c, h_in, w_in): (usize, usize, usize),
    dy: At,
    dx: At,
) -> Result<Step> {
    if c == 0 || h_in == 0 || w_in == 0 || (!up && (h_in < 2 || w_in < 2)) {
        return Err(GpuError::Device(format!(
            "resize gradient of a {c}x{h_in}x{w_in} input"
        )));
    }
    let k = gpu.kernel(
        "resize_backward",
        RESIZE_BACKWARD,
        &[("UP", if up { "true" } else { "false" }.into())],
        &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "resize backward",
        &Params::new()
            .u(c as u32)
            .u(h_in as u32)
            .u(w_in as u32)
            .u(dy.off)
            .u(dx.off)
            .u(0)
            .u(0)
            .u(0),
    );
    let g = gpu.bind(&k, &[&u, dy.buf, dx.buf])?;
    Ok(Step::new(k, g, linear_grid(c * h_in * w_in, 256)))
}

/// Records the input gradient `dx` `[c, h, w]` of a `k x k`, `stride`, `pad` convolution's
/// patch matrix (`Ops::im2col`) from the matrix's gradient `cols` `[c k k, oh ow]` (whole
/// buffers; `dx` is overwritten).
#[allow(clippy::too_many_arguments)]
pub fn col2im(
    gpu: &Gpu,
    (c, h, w): (usize, usize, usize),
    (k, stride, pad): (usize, usize, usize),
    (oh, ow): (usize, usize),
    cols: &wgpu::Buffer,
    dx: &wgpu::Buffer,
) -> Result<Step> {
    let kern = gpu.kernel(
        "col2im",
        COL2IM,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "col2im",
        &Params::new()
            .u(c as u32)
            .u(h as u32)
            .u(w as u32)
            .u(k as u32)
            .u(stride as u32)
            .u(pad as u32)
            .u(oh as u32)
            .u(ow as u32),
    );
    let bg = gpu.bind(&kern, &[&u, cols, dx])?;
    Ok(Step::new(kern, bg, linear_grid(c * h * w, 256)))
}

/// Records the input gradient of `Ops::rms_norm` over `n` values: `x` is the forward's input,
/// `dy` its output's gradient, `dx` (overwritten) the result. Whole buffers from offset 0.
pub fn rms_norm_backward(
    gpu: &Gpu,
    n: usize,
    x: &wgpu::Buffer,
    dy: &wgpu::Buffer,
    dx: &wgpu::Buffer,
) -> Result<Step> {
    let k = gpu.kernel(
        "rms_norm_backward",
        RMS_NORM_BACKWARD,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform("rms backward", &Params::new().u(n as u32).u(0).u(0).u(0));
    let g = gpu.bind(&k, &[&u, x, dy, dx])?;
    Ok(Step::new(k, g, Grid::Fixed([1, 1, 1])))
}

/// Records the gradient of `scale * sum |pred - target|` over `n` values with respect to
/// `pred` into `out`: `scale * sign(pred - target)`, 0 where they are equal.
pub fn l1_grad(gpu: &Gpu, n: usize, pred: At, target: At, scale: f32, out: At) -> Result<Step> {
    let k = gpu.kernel(
        "l1_grad",
        L1_GRAD,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "l1 grad",
        &Params::new()
            .u(n as u32)
            .u(pred.off)
            .u(target.off)
            .u(out.off)
            .f(scale)
            .u(0)
            .u(0)
            .u(0),
    );
    let g = gpu.bind(&k, &[&u, pred.buf, target.buf, out.buf])?;
    Ok(Step::new(k, g, linear_grid(n, 256)))
}

/// `out[slot] = scale * sum |a - b|` over `n` values, in one workgroup's fixed order.
pub fn l1_sum(
    gpu: &Gpu,
    n: usize,
    a: At,
    b: At,
    scale: f32,
    out: &wgpu::Buffer,
    slot: u32,
) -> Result<Step> {
    let k = gpu.kernel(
        "l1_sum",
        L1_SUM,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "l1 sum",
        &Params::new()
            .u(n as u32)
            .u(a.off)
            .u(b.off)
            .u(slot)
            .f(scale)
            .u(0)
            .u(0)
            .u(0),
    );
    let g = gpu.bind(&k, &[&u, a.buf, b.buf, out])?;
    Ok(Step::new(k, g, Grid::Fixed([1, 1, 1])))
}
