//! `gagavatar bench splat --device gpu`: the splatting's training forward (projection, sort,
//! binning, compositing with the per-pixel state) and its backward (to the Gaussians' features,
//! means, opacities, scales and quaternions and the background) on a GPU, on `bench splat`'s
//! scenes.

use std::time::Instant;

use anyhow::Result;
use gagavatar_gpu::grad::splat::GpuSplatGrad;
use gagavatar_gpu::splat::{GpuSplat, SplatInputs};
use gagavatar_gpu::{Gpu, Tuning};
use gagavatar_splat::{Camera, GaussianScene};

use crate::bench_stats::median;

/// One regime's figures: forward and backward medians (ms), pairs, GPU MiB.
pub struct GpuSplatTimes {
    pub forward: f64,
    pub backward: f64,
    pub pairs: usize,
    pub mib: f64,
}

/// Times `runs` training forwards and backwards of `scene` from `cam` (after one warm-up that
/// grows the pair buffers), each submitted and waited for alone; the backward's input is the
/// gradient of the image's mean, as the CPU bench uses.
pub fn time(
    gpu: &Gpu,
    tuning: &Tuning,
    scene: &GaussianScene,
    background: &[f32],
    cam: &Camera,
    runs: usize,
) -> Result<GpuSplatTimes> {
    let inputs = SplatInputs::from_scene(scene, background);
    let mut splat = GpuSplat::new(gpu, tuning, &inputs, None, 0, cam.width, cam.height)?;
    let mut grad = GpuSplatGrad::new(gpu, &splat)?;
    let values = scene.channels * cam.width * cam.height;
    let dl = vec![1.0 / values as f32; values];
    grad.run(gpu, &mut splat, cam, &dl)?;
    let pairs = gpu.read_u32(splat.sizes(), 1)?[0] as usize;
    let (mut fwd, mut bwd) = (Vec::with_capacity(runs), Vec::with_capacity(runs));
    let bar = crate::animate::progress(runs, "bench splat (GPU)");
    for _ in 0..runs {
        crate::check_interrupt()?;
        let t = Instant::now();
        grad.submit_forward(gpu, &splat);
        gpu.wait()?;
        fwd.push(1e3 * t.elapsed().as_secs_f64());
        let t = Instant::now();
        grad.submit_backward(gpu);
        gpu.wait()?;
        bwd.push(1e3 * t.elapsed().as_secs_f64());
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(GpuSplatTimes {
        forward: median(&mut fwd),
        backward: median(&mut bwd),
        pairs,
        mib: gpu.allocated_bytes() as f64 / (1 << 20) as f64,
    })
}
