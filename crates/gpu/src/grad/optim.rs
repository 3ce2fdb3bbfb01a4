//! The Adam update of one parameter tensor on the GPU.

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

/// One parameter tensor of `n` values with its moments, each a buffer of at least `n` floats.
pub struct AdamBuffers<'a> {
    pub grad: &'a wgpu::Buffer,
    pub param: &'a wgpu::Buffer,
    pub m: &'a wgpu::Buffer,
    pub v: &'a wgpu::Buffer,
}

/// Records one Adam update of `n` values. The bias corrections are computed here in f64, as
/// the CPU optimiser computes them, and rounded once to f32.
pub fn adam(gpu: &Gpu, s: AdamStep, n: usize, b: &AdamBuffers) -> Result<Step> {
    if s.t == 0 {
        return Err(GpuError::Device(
            "Adam step 0: the first update is step 1".into(),
        ));
    }
    for (what, buf) in [
        ("gradient", b.grad),
        ("parameter", b.param),
        ("m", b.m),
        ("v", b.v),
    ] {
        if buf.size() < 4 * n as u64 {
            return Err(GpuError::Device(format!(
                "Adam: the {what} buffer holds {} bytes, {n} values need {}",
                buf.size(),
                4 * n
            )));
        }
    }
    let t = s.t as f64;
    let step_size = s.lr / (1.0 - s.beta1.powf(t));
    let bc2_sqrt = (1.0 - s.beta2.powf(t)).sqrt();
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
    let u = gpu.uniform(
        "adam",
        &Params::new()
            .u(n as u32)
            .f(s.beta1 as f32)
            .f((1.0 - s.beta1) as f32)
            .f(s.beta2 as f32)
            .f((1.0 - s.beta2) as f32)
            .f(s.eps as f32)
            .f(step_size as f32)
            .f(bc2_sqrt as f32),
    );
    let g = gpu.bind(&k, &[&u, b.grad, b.param, b.m, b.v])?;
    Ok(Step::new(k, g, linear_grid(n, 256)))
}
