//! Adam on the GPU: the update of one parameter tensor ([`adam`]), and [`GpuAdam`] over all of a
//! module's parameters with per-parameter learning rates, the moments kept on the device.

use super::params::Param;
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Params, Step};

const ADAM: &str = include_str!("../shaders/adam.wgsl");

/// Adam's constants (torch.optim.Adam without weight decay; see crates/train's `adam.rs`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamStep {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// This step's learning rate (the schedule applied).
    pub lr: f64,
    /// The parameter's own step count, this step included (1 for its first update).
    pub t: u64,
}

/// One parameter tensor of `n` values at `off` of `param` (its gradient at `off` of `grad`) with
/// its moments (`n` floats from 0 each).
pub struct AdamBuffers<'a> {
    pub grad: &'a wgpu::Buffer,
    pub param: &'a wgpu::Buffer,
    pub off: usize,
    pub m: &'a wgpu::Buffer,
    pub v: &'a wgpu::Buffer,
}

fn adam_params(s: AdamStep, n: usize, off: usize) -> Result<Params> {
    if s.t == 0 {
        return Err(GpuError::Device(
            "Adam step 0: the first update is step 1".into(),
        ));
    }
    let t = s.t as f64;
    let step_size = s.lr / (1.0 - s.beta1.powf(t));
    let bc2_sqrt = (1.0 - s.beta2.powf(t)).sqrt();
    Ok(Params::new()
        .u(n as u32)
        .f(s.beta1 as f32)
        .f((1.0 - s.beta1) as f32)
        .f(s.beta2 as f32)
        .f((1.0 - s.beta2) as f32)
        .f(s.eps as f32)
        .f(step_size as f32)
        .f(bc2_sqrt as f32)
        .u(off as u32)
        .u(0)
        .u(0)
        .u(0))
}

/// Records one Adam update of `n` values. The bias corrections are computed here in f64, as
/// the CPU optimiser computes them, and rounded once to f32.
pub fn adam(gpu: &Gpu, s: AdamStep, n: usize, b: &AdamBuffers) -> Result<Step> {
    let params = adam_params(s, n, b.off)?;
    adam_with(gpu, &gpu.uniform("adam", &params), n, b)
}

/// The update of [`adam`] reading its constants from `uniform` (rewritten before each step).
fn adam_with(gpu: &Gpu, uniform: &wgpu::Buffer, n: usize, b: &AdamBuffers) -> Result<Step> {
    for (what, buf, need) in [
        ("gradient", b.grad, b.off + n),
        ("parameter", b.param, b.off + n),
        ("m", b.m, n),
        ("v", b.v, n),
    ] {
        if buf.size() < 4 * need as u64 {
            return Err(GpuError::Device(format!(
                "Adam: the {what} buffer holds {} bytes, {need} values need {}",
                buf.size(),
                4 * need
            )));
        }
    }
    let k = gpu.kernel(
        "adam",
        ADAM,
        &[],
        &[
            Bind::Uniform,
            Bind::Read,
            Bind::ReadWrite,
            Bind::ReadWrite,
            Bind::ReadWrite,
        ],
    )?;
    let g = gpu.bind(&k, &[uniform, b.grad, b.param, b.m, b.v])?;
    Ok(Step::new(k, g, linear_grid(n, 256)))
}

/// Adam over a module's parameters (as its [`Param`] list names them in its buffers): the
/// moments on the device, each parameter with its own learning rate and step count, the
/// updates recorded once and their constants rewritten each step.
pub struct GpuAdam {
    beta1: f64,
    beta2: f64,
    eps: f64,
    entries: Vec<Entry>,
    steps: Vec<Step>,
}

struct Entry {
    n: usize,
    off: usize,
    lr0: f64,
    t: u64,
    uniform: wgpu::Buffer,
    // The moments, kept alive beside the recorded step that binds them.
    _m: wgpu::Buffer,
    _v: wgpu::Buffer,
}

impl GpuAdam {
    /// `lr0(key)`: the base learning rate of the parameter named `key` (its group's).
    pub fn new(
        gpu: &Gpu,
        (buffers, params): (&[wgpu::Buffer], &[Param]),
        (beta1, beta2, eps): (f64, f64, f64),
        lr0: &dyn Fn(&str) -> f64,
    ) -> Result<Self> {
        let mut entries = Vec::with_capacity(params.len());
        let mut steps = Vec::with_capacity(params.len());
        for p in params {
            let (Some(param), Some(grad)) = (buffers.get(p.value), buffers.get(p.grad)) else {
                return Err(GpuError::Device(format!(
                    "Adam: parameter {} names a buffer the module does not have",
                    p.key
                )));
            };
            let m = gpu.buffer("adam m", 4 * p.len as u64);
            let v = gpu.buffer("adam v", 4 * p.len as u64);
            let placeholder = AdamStep {
                beta1,
                beta2,
                eps,
                lr: 0.0,
                t: 1,
            };
            let uniform = gpu.uniform("adam", &adam_params(placeholder, p.len, p.offset)?);
            let b = AdamBuffers {
                grad,
                param,
                off: p.offset,
                m: &m,
                v: &v,
            };
            steps.push(adam_with(gpu, &uniform, p.len, &b)?);
            entries.push(Entry {
                n: p.len,
                off: p.offset,
                lr0: lr0(&p.key),
                t: 0,
                uniform,
                _m: m,
                _v: v,
            });
        }
        Ok(Self {
            beta1,
            beta2,
            eps,
            entries,
            steps,
        })
    }

    /// Advances every parameter's step count, writes this step's constants (the rate
    /// `factor * lr0`, the schedule's factor being the caller's) and returns the updates to
    /// submit after the backward.
    pub fn step(&mut self, gpu: &Gpu, factor: f64) -> Result<&[Step]> {
        for e in &mut self.entries {
            e.t += 1;
            let s = AdamStep {
                beta1: self.beta1,
                beta2: self.beta2,
                eps: self.eps,
                lr: e.lr0 * factor,
                t: e.t,
            };
            gpu.queue.write_buffer(
                &e.uniform,
                0,
                bytemuck::cast_slice(&adam_params(s, e.n, e.off)?.words()),
            );
        }
        Ok(&self.steps)
    }
}
