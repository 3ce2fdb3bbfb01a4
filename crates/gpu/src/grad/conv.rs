//! The gradients of a stride-1 convolution (1x1 or 3x3, zero padding `k/2`) of one
//! `[cin, h, w]` image, given the gradient `dZ` of its pre-activation output `[cout, h, w]`:
//! - input: `dX = conv(dZ, W')` with `W'[ci, co] = rot180(W[co, ci])`, on the forward's kernels;
//! - weight: `dW[co, ci, tap] = sum_pix dZ[co, pix] X[ci, pix + tap]` (conv_wgrad.wgsl), a
//!   GEMM over pixels, split into slices and summed in slice order (conv_wgrad_sum.wgsl);
//! - bias: the row sums of `dZ` (row_sum.wgsl, then the same sum).

use std::sync::LazyLock;

use crate::conv::{micro_body, micro_decl, micro_emit, At, Conv, Ops};
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Grid, Params, Step};
use crate::tuning::ConvTile;

static WGRAD: LazyLock<String> =
    LazyLock::new(|| include_str!("../shaders/conv_wgrad.wgsl").into());
const WGRAD_SUM: &str = include_str!("../shaders/conv_wgrad_sum.wgsl");
const ROW_SUM: &str = include_str!("../shaders/row_sum.wgsl");
const FLIP: &str = include_str!("../shaders/flip_weights.wgsl");

/// Workgroups a weight-gradient GEMM aims for: its tiles alone are few (a 64 -> 64 3x3 layer
/// has 9), so the pixels are split until the device has this many to run.
const WGRAD_WORKGROUPS: usize = 256;
/// Columns one workgroup of the bias gradient's row sums covers.
const ROW_SLICE: usize = 4096;

/// One convolution's backward: what the forward read, the gradient of its output, and where
/// the gradients go. Offsets are in f32 elements.
#[derive(Debug, Clone, Copy)]
pub struct ConvGrad<'a> {
    pub cin: usize,
    pub cout: usize,
    pub h: usize,
    pub w: usize,
    /// 1 or 3.
    pub k: usize,
    /// The forward's input `[cin, h, w]`.
    pub input: At<'a>,
    /// The forward's weight `[cout, cin, k, k]` (from offset 0).
    pub weight: &'a wgpu::Buffer,
    /// `dZ`, the gradient of the output before any activation, `[cout, h, w]`.
    pub grad_out: At<'a>,
    /// `dX` `[cin, h, w]`, overwritten; `None` for a first layer (no input gradient needed).
    pub grad_input: Option<At<'a>>,
    /// `dW` `[cout, cin, k, k]`.
    pub grad_weight: At<'a>,
    /// `dB` `[cout]`.
    pub grad_bias: Option<At<'a>>,
    /// Add the weight and bias gradients to what the buffers hold (the images of a batch, or a
    /// layer used twice) instead of overwriting them.
    pub accumulate: bool,
}

/// How a weight-gradient GEMM is split: pixels per slice (a multiple of the tile's depth
/// step) and slice count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WgradPlan {
    pub tile: ConvTile,
    pub slice: usize,
    pub slices: usize,
}

/// The weight-gradient split of a layer: the forward's f32 tile, and enough pixel slices for
/// [`WGRAD_WORKGROUPS`] workgroups (or one slice per depth step when the image is smaller).
pub fn wgrad_plan(tile: ConvTile, cin: usize, cout: usize, hw: usize, k: usize) -> WgradPlan {
    let tiles = (cin * k * k).div_ceil(tile.bn as usize) * cout.div_ceil(tile.bm as usize);
    let want = WGRAD_WORKGROUPS.div_ceil(tiles).max(1);
    let bk = tile.bk as usize;
    let slice = hw.div_ceil(want).next_multiple_of(bk).max(bk);
    WgradPlan {
        tile,
        slice,
        slices: hw.div_ceil(slice).max(1),
    }
}

impl ConvGrad<'_> {
    pub(crate) fn check(&self) -> Result<()> {
        if self.k != 1 && self.k != 3 {
            return Err(GpuError::Unsupported(format!(
                "the gradient of a {}x{} convolution",
                self.k, self.k
            )));
        }
        if self.cin == 0 || self.cout == 0 || self.h == 0 || self.w == 0 {
            return Err(GpuError::Device(format!(
                "convolution gradient of an empty layer ({}->{} {}x{})",
                self.cin, self.cout, self.h, self.w
            )));
        }
        Ok(())
    }

    /// Floats of the rotated weight a backward needs (its `flipped` buffer).
    pub fn flipped_floats(&self) -> usize {
        self.cin * self.cout * self.k * self.k
    }

    /// Floats of slice partial sums a backward needs (its `part` buffer; the weight's and the
    /// bias's sums reuse it one after the other).
    pub fn part_floats(&self, ops: &Ops) -> usize {
        part_floats(
            ops.tuning.conv,
            (self.cin, self.cout, self.h * self.w, self.k),
            self.grad_bias.is_some(),
        )
    }
}

/// Floats of slice partial sums the backward of a `cin -> cout` layer of `hw` pixels and
/// kernel `k` needs, with a bias or noise weight (row sums) or not; see
/// [`ConvGrad::part_floats`]. For sizing a scratch shared by several layers.
pub fn part_floats(
    tile: ConvTile,
    (cin, cout, hw, k): (usize, usize, usize, usize),
    row_sums: bool,
) -> usize {
    let p = wgrad_plan(tile, cin, cout, hw, k);
    let rows = if row_sums {
        hw.div_ceil(ROW_SLICE) * cout
    } else {
        0
    };
    (p.slices * cout * cin * k * k).max(rows)
}

pub(crate) fn fits(what: &str, buf: &wgpu::Buffer, floats: usize) -> Result<()> {
    if 4 * floats as u64 > buf.size() {
        return Err(GpuError::Device(format!(
            "convolution gradient: the {what} buffer holds {} bytes, the layer needs {}",
            buf.size(),
            4 * floats
        )));
    }
    Ok(())
}

/// Records a convolution's backward ([`ConvGrad`]); `flipped` and `part` are scratch of at
/// least [`ConvGrad::flipped_floats`] and [`ConvGrad::part_floats`] floats, and the input
/// gradient's convolution uses `ops.split_scratch` as the forward does.
pub fn conv_backward(
    ops: &Ops,
    c: &ConvGrad,
    flipped: &wgpu::Buffer,
    part: &wgpu::Buffer,
) -> Result<Vec<Step>> {
    c.check()?;
    fits("rotated weight", flipped, c.flipped_floats())?;
    fits("partial sum", part, c.part_floats(ops))?;
    let mut steps = Vec::new();
    if let Some(grad_input) = c.grad_input {
        steps.extend(input_grad(ops, c, flipped, grad_input, None, None)?);
    }
    steps.extend(weight_grad(ops, c, part, c.grad_weight, c.accumulate)?);
    if let Some(grad_bias) = c.grad_bias {
        steps.extend(bias_grad(ops, c, part, grad_bias, c.accumulate)?);
    }
    Ok(steps)
}

fn note(c: &ConvGrad) -> String {
    format!("{}->{} {}x{} k{}", c.cin, c.cout, c.h, c.w, c.k)
}

/// `dX = out_scale * conv(in_scale * dZ, W')` into `grad_input`, the scales' offsets in
/// `ops.vecs` (per channel of dZ and of dX; a modulated convolution's demodulation and style).
pub(crate) fn input_grad(
    ops: &Ops,
    c: &ConvGrad,
    flipped: &wgpu::Buffer,
    grad_input: At,
    in_scale: Option<u32>,
    out_scale: Option<u32>,
) -> Result<Vec<Step>> {
    let gpu = ops.gpu;
    let k = gpu.kernel(
        "flip_weights",
        FLIP,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "flip weights",
        &Params::new()
            .u(c.cin as u32)
            .u(c.cout as u32)
            .u((c.k * c.k) as u32)
            .u(0),
    );
    let g = gpu.bind(&k, &[&u, c.weight, flipped])?;
    let mut steps = vec![Step::new(k, g, linear_grid(c.flipped_floats(), 256)).with_note(note(c))];
    steps.extend(ops.conv(&Conv {
        cin: c.cout,
        cout: c.cin,
        h: c.h,
        w: c.w,
        k: c.k,
        input: c.grad_out,
        weight: flipped,
        bias: None,
        in_scale,
        out_scale,
        noise: None,
        in_relu: false,
        act: crate::conv::Act::None,
        residual: None,
        sft: None,
        sigmoid: false,
        out: grad_input,
    })?);
    Ok(steps)
}

/// `G[co, ci, tap] = sum_pix dZ[co, pix] X[ci, pix + tap]` into `dest` (or added to it).
pub(crate) fn weight_grad(
    ops: &Ops,
    c: &ConvGrad,
    part: &wgpu::Buffer,
    dest: At,
    accumulate: bool,
) -> Result<Vec<Step>> {
    let gpu = ops.gpu;
    let hw = c.h * c.w;
    let p = wgrad_plan(ops.tuning.conv, c.cin, c.cout, hw, c.k);
    let t = p.tile;
    let consts = vec![
        ("ACC_DECL", micro_decl(t)),
        ("MICRO", micro_body(t)),
        ("EMIT", micro_emit(t)),
        ("BM", t.bm.to_string()),
        ("BN", t.bn.to_string()),
        ("BK", t.bk.to_string()),
        ("TM", t.tm.to_string()),
        ("TN", t.tn.to_string()),
        ("KSIZE", c.k.to_string()),
    ];
    let k = gpu.kernel(
        "conv_wgrad",
        &WGRAD,
        &consts,
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let u = gpu.uniform(
        "conv wgrad",
        &Params::new()
            .u(c.cin as u32)
            .u(c.cout as u32)
            .u(c.h as u32)
            .u(c.w as u32)
            .u(c.input.off)
            .u(c.grad_out.off)
            .u(p.slice as u32)
            .u(0),
    );
    let g = gpu.bind(&k, &[&u, c.input.buf, c.grad_out.buf, part])?;
    let cols = c.cin * c.k * c.k;
    Ok(vec![
        Step::new(
            k,
            g,
            Grid::Fixed([
                cols.div_ceil(t.bn as usize) as u32,
                c.cout.div_ceil(t.bm as usize) as u32,
                p.slices as u32,
            ]),
        )
        .with_note(note(c)),
        slice_sum(ops, part, c.cout * cols, p.slices, dest, accumulate)?,
    ])
}

/// The row sums of dZ (a bias's gradient) into `dest` (or added to it).
pub(crate) fn bias_grad(
    ops: &Ops,
    c: &ConvGrad,
    part: &wgpu::Buffer,
    dest: At,
    accumulate: bool,
) -> Result<Vec<Step>> {
    row_sums(
        ops,
        (c.cout, c.h * c.w),
        c.grad_out,
        None,
        part,
        dest,
        accumulate,
        false,
    )
}

/// Sums of the rows of `a` `[rows, cols]`, each value times `weight[col]` when given, into
/// `dest` (`rows` values; with `total`, their sum, one value); written or added to.
#[allow(clippy::too_many_arguments)]
pub(crate) fn row_sums(
    ops: &Ops,
    (rows, cols): (usize, usize),
    a: At,
    weight: Option<At>,
    part: &wgpu::Buffer,
    dest: At,
    accumulate: bool,
    total: bool,
) -> Result<Vec<Step>> {
    let slices = cols.div_ceil(ROW_SLICE);
    fits("partial sum", part, rows * slices)?;
    let k = ops.gpu.kernel(
        "row_sum",
        ROW_SUM,
        &[("WEIGHTED", weight.is_some().to_string())],
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let w = weight.unwrap_or(At::new(ops.dummy));
    let u = ops.gpu.uniform(
        "row sum",
        &Params::new()
            .u(rows as u32)
            .u(cols as u32)
            .u(a.off)
            .u(ROW_SLICE as u32)
            .u(w.off)
            .u(0)
            .u(0)
            .u(0),
    );
    let g = ops.gpu.bind(&k, &[&u, a.buf, w.buf, part])?;
    let (n, s) = if total {
        (1, rows * slices)
    } else {
        (rows, slices)
    };
    Ok(vec![
        Step::new(k, g, Grid::Fixed([rows as u32, slices as u32, 1])),
        slice_sum(ops, part, n, s, dest, accumulate)?,
    ])
}

/// `out[i] (+)= sum_s part[s n + i]` for `i < n`, slices added in order.
fn slice_sum(
    ops: &Ops,
    part: &wgpu::Buffer,
    n: usize,
    slices: usize,
    out: At,
    accumulate: bool,
) -> Result<Step> {
    if part == out.buf {
        return Err(GpuError::Device(
            "convolution gradient: the partial sums and a gradient share a buffer".into(),
        ));
    }
    let k = ops.gpu.kernel(
        "conv_wgrad_sum",
        WGRAD_SUM,
        &[(
            "ACCUMULATE",
            if accumulate { "true" } else { "false" }.into(),
        )],
        &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
    )?;
    let u = ops.gpu.uniform(
        "slice sum",
        &Params::new().u(n as u32).u(slices as u32).u(out.off).u(0),
    );
    let g = ops.gpu.bind(&k, &[&u, part, out.buf])?;
    Ok(Step::new(k, g, linear_grid(n, 256)))
}
