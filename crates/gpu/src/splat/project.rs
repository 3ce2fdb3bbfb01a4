//! Splatting step 1: the per-Gaussian projection kernel and its camera parameters.

use gagavatar_splat::project::CamK;
use gagavatar_splat::Camera;

use crate::device::Gpu;
use crate::error::Result;
use crate::kernel::{linear_grid, Bind, Kernel, Params, Step};
use std::sync::Arc;

const PROJECT: &str = include_str!("../shaders/project.wgsl");

pub fn kernel(gpu: &Gpu) -> Result<Arc<Kernel>> {
    let mut binds = vec![Bind::Uniform];
    binds.extend([Bind::Read; 5]);
    binds.extend([Bind::ReadWrite; 4]);
    gpu.kernel("project", PROJECT, &[], &binds)
}

/// The projection's uniform block for a camera: the CPU path's own f32 constants
/// ([`CamK::<f32>::new`]), so both start from the same numbers.
pub fn camera_params(cam: &Camera, n: usize, n_vertices: usize) -> Params {
    let k = CamK::<f32>::new(cam);
    let mut p = Params::new();
    for i in 0..3 {
        p = p.f(k.rot[i][0]).f(k.rot[i][1]).f(k.rot[i][2]).f(k.trans[i]);
    }
    p.f(k.focal)
        .f(k.fx)
        .f(k.fy)
        .f(k.lim)
        .f(k.w)
        .f(k.h)
        .u(k.grid_x as u32)
        .u(k.grid_y as u32)
        .u(n as u32)
        .u(n_vertices as u32)
}

/// Buffers the projection writes, one entry per Gaussian.
pub struct Projected {
    /// Two `vec4<f32>` per Gaussian.
    pub splats: wgpu::Buffer,
    pub keys: wgpu::Buffer,
    pub vals: wgpu::Buffer,
    /// `vec2<u32>` tile rectangle per Gaussian.
    pub rects: wgpu::Buffer,
}

impl Projected {
    pub fn new(gpu: &Gpu, n: usize) -> Self {
        let n = n as u64;
        Self {
            splats: gpu.buffer("splats", 32 * n),
            keys: gpu.buffer("depth keys", 4 * n),
            vals: gpu.buffer("depth ids", 4 * n),
            rects: gpu.buffer("tile rects", 8 * n),
        }
    }
}

/// The projection dispatch. `head` holds the positions of the first `n_vertices` Gaussians
/// (the FLAME vertices), `rest` those of the others.
#[allow(clippy::too_many_arguments)]
pub fn step(
    gpu: &Gpu,
    camera: &wgpu::Buffer,
    head: &wgpu::Buffer,
    rest: &wgpu::Buffer,
    opacities: &wgpu::Buffer,
    scales: &wgpu::Buffer,
    rotations: &wgpu::Buffer,
    out: &Projected,
    n: usize,
) -> Result<Step> {
    let k = kernel(gpu)?;
    let g = gpu.bind(
        &k,
        &[
            camera,
            head,
            rest,
            opacities,
            scales,
            rotations,
            &out.splats,
            &out.keys,
            &out.vals,
            &out.rects,
        ],
    )?;
    Ok(Step::new(k, g, linear_grid(n, 256)))
}
