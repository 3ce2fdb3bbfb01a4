//! The backward of a modulated convolution, the renderer's decoder layer (StyleGAN2), as the
//! GPU forward computes it: `y = d * conv(x * s, W) + bias` with the style `s` `[cin]` scaling
//! the input, and `d` `[cout]` the demodulation times the gain (or the gain alone).
//!
//! `conv(x * s, W) = conv(x, W s)`, so every weight and style gradient follows from
//! `G = conv_wgrad(x, dZ)`, the plain convolution's weight gradient (modconv_grad.wgsl has the
//! formulas); the input gradient is `dX = s * conv(d * dZ, W')` on the forward's kernels.

use std::sync::LazyLock;

use super::conv::{bias_grad, fits, input_grad, weight_grad, ConvGrad};
use crate::conv::{At, Ops};
use crate::error::Result;
use crate::kernel::{linear_grid, Bind, Grid, Params, Step};

static MODCONV_GRAD: LazyLock<String> =
    LazyLock::new(|| include_str!("../shaders/modconv_grad.wgsl").into());

/// One modulated convolution's backward. The style and demodulation factors are read from
/// `ops.vecs` at the forward's offsets.
#[derive(Debug, Clone, Copy)]
pub struct ModConvGrad<'a> {
    /// The layer as a plain convolution: shapes, the input `x`, the weight `W`, `dZ`, where
    /// `dX` and the bias gradient go. Its `grad_weight` receives `dW`.
    pub conv: ConvGrad<'a>,
    /// Offset of the style `s` `[cin]` in `ops.vecs`.
    pub style: u32,
    /// Offset of the demodulation factors `d` `[cout]` in `ops.vecs`; `None` when the layer
    /// does not demodulate (then `d = gain`).
    pub demod: Option<u32>,
    /// The forward's gain (`sqrt 2` for the renderer's demodulated layers, 1 for its RGB ones).
    pub gain: f32,
    /// `ds` `[cin]` (the modulation's output gradient; added to when `conv.accumulate`).
    pub grad_style: At<'a>,
}

/// Scratch one modulated convolution's backward keeps for itself: `G` and the demodulation's
/// per-channel coefficients.
pub struct ModConvScratch {
    g: wgpu::Buffer,
    coef: wgpu::Buffer,
    /// Bound as the unused output of the coefficients' pass.
    spare: wgpu::Buffer,
}

impl ModConvScratch {
    pub fn new(gpu: &crate::Gpu, m: &ModConvGrad) -> Self {
        let c = &m.conv;
        Self {
            g: gpu.buffer("modconv G", 4 * (c.cout * c.cin * c.k * c.k) as u64),
            coef: gpu.buffer("modconv coef", 4 * c.cout as u64),
            spare: gpu.buffer("modconv spare", 4),
        }
    }
}

/// Records a modulated convolution's backward; `flipped` and `part` as for
/// [`super::conv::conv_backward`] (shared by the layers), `scratch` this layer's own.
pub fn modconv_backward(
    ops: &Ops,
    m: &ModConvGrad,
    flipped: &wgpu::Buffer,
    part: &wgpu::Buffer,
    scratch: &ModConvScratch,
) -> Result<Vec<Step>> {
    let c = &m.conv;
    c.check()?;
    // The input gradient reads d from `vecs`; without demodulation it takes d = 1, which is
    // the renderer's RGB layers' gain.
    if m.demod.is_none() && m.gain != 1.0 {
        return Err(crate::GpuError::Unsupported(format!(
            "the gradient of a modulated convolution without demodulation and gain {}",
            m.gain
        )));
    }
    fits("rotated weight", flipped, c.flipped_floats())?;
    fits("partial sum", part, c.part_floats(ops))?;
    fits("G", &scratch.g, c.cout * c.cin * c.k * c.k)?;
    fits("coefficient", &scratch.coef, c.cout)?;
    let gpu = ops.gpu;
    let mut steps = Vec::new();
    if let Some(grad_input) = c.grad_input {
        steps.extend(input_grad(
            ops,
            c,
            flipped,
            grad_input,
            m.demod,
            Some(m.style),
        )?);
    }
    steps.extend(weight_grad(ops, c, part, At::new(&scratch.g), false)?);
    let taps = c.k * c.k;
    let flag = |b: bool| if b { "true" } else { "false" }.to_string();
    let kernel = |mode: u32| {
        gpu.kernel(
            "modconv_grad",
            &MODCONV_GRAD,
            &[
                ("MODE", mode.to_string()),
                ("DEMOD", flag(m.demod.is_some())),
                ("ACCUMULATE", flag(c.accumulate)),
            ],
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
    let params = |out_off: u32| {
        Params::new()
            .u(c.cin as u32)
            .u(c.cout as u32)
            .u(taps as u32)
            .u(m.style)
            .u(m.demod.unwrap_or(0))
            .u(out_off)
            .f(m.gain)
            .u(0)
    };
    let note = format!("{}->{} {}x{} k{}", c.cin, c.cout, c.h, c.w, c.k);
    let mut bind = |mode: u32, out: At, grid: Grid| -> Result<()> {
        let k = kernel(mode)?;
        let u = gpu.uniform("modconv grad", &params(out.off));
        let g = gpu.bind(
            &k,
            &[&u, ops.vecs, c.weight, &scratch.g, &scratch.coef, out.buf],
        )?;
        steps.push(Step::new(k, g, grid).with_note(note.clone()));
        Ok(())
    };
    if m.demod.is_some() {
        bind(
            0,
            At::new(&scratch.spare),
            Grid::Fixed([c.cout as u32, 1, 1]),
        )?;
    }
    bind(1, c.grad_weight, linear_grid(c.cout * c.cin * taps, 256))?;
    bind(2, m.grad_style, Grid::Fixed([c.cin as u32, 1, 1]))?;
    if let Some(grad_bias) = c.grad_bias {
        steps.extend(bias_grad(ops, c, part, grad_bias, c.accumulate)?);
    }
    Ok(steps)
}
