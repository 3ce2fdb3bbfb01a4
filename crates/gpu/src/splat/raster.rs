//! Splatting step 8: per-tile alpha compositing of the feature channels.

use crate::device::Gpu;
use crate::error::Result;
use crate::kernel::{Bind, Grid, Params, Step};

const RASTER: &str = include_str!("../shaders/raster.wgsl");

/// The compositing step; with `state` (training: the final transmittance `[H, W]` f32 and one
/// past the last contributor's list position `[H, W]` u32) it also keeps what the backward
/// needs.
#[allow(clippy::too_many_arguments)]
pub fn step(
    gpu: &Gpu,
    channels: usize,
    width: usize,
    height: usize,
    ranges: &wgpu::Buffer,
    pair_vals: &wgpu::Buffer,
    splats: &wgpu::Buffer,
    features: &wgpu::Buffer,
    background: &wgpu::Buffer,
    image: &wgpu::Buffer,
    state: Option<(&wgpu::Buffer, &wgpu::Buffer)>,
) -> Result<Step> {
    let mut binds = vec![Bind::Uniform];
    binds.extend([Bind::Read; 5]);
    binds.extend([Bind::ReadWrite; 3]);
    let k = gpu.kernel(
        "raster",
        RASTER,
        &[
            ("CHANNELS", channels.to_string()),
            ("STATE", state.is_some().to_string()),
        ],
        &binds,
    )?;
    let unused;
    let (state_t, state_n) = match state {
        Some(s) => s,
        None => {
            // Two: writable bindings must not alias.
            unused = [0, 1].map(|_| gpu.buffer("raster state (inference: unused)", 16));
            (&unused[0], &unused[1])
        }
    };
    let grid_x = width.div_ceil(16);
    let grid_y = height.div_ceil(16);
    let p = gpu.uniform(
        "raster",
        &Params::new()
            .u(width as u32)
            .u(height as u32)
            .u(grid_x as u32),
    );
    let g = gpu.bind(
        &k,
        &[
            &p, ranges, pair_vals, splats, features, background, image, state_t, state_n,
        ],
    )?;
    Ok(Step::new(
        k,
        g,
        Grid::Fixed([grid_x as u32, grid_y as u32, 1]),
    ))
}
