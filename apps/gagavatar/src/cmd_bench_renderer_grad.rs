//! `gagavatar bench renderer-grad`: the neural renderer's training forward and backward on one
//! image (the StyleUNet, the largest part of a training step) on a GPU, or on the CPU through
//! candle's autograd for comparison: median time per step, GPU memory.

use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use clap::Args;
use gagavatar_gpu::grad::renderer::GpuRendererGrad;
use gagavatar_gpu::GpuError;
use gagavatar_net::checkpoint::WeightData;
use gagavatar_net::style_unet::{Noise, StyleUNet};
use gagavatar_net::ModelConfig;

use crate::bench_stats::median;
use crate::device_args::DeviceArgs;

#[derive(Debug, Args)]
pub struct RendererGradBench {
    #[command(flatten)]
    device: DeviceArgs,
    /// Architecture: release, small or tiny.
    #[arg(long, default_value = "release")]
    preset: String,
    /// Timed steps (the median is reported); default 10 on a GPU, 3 on the CPU.
    #[arg(long)]
    runs: Option<usize>,
    /// CPU worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Also write the figures as JSON to this file; GPU only.
    #[arg(long)]
    json: Option<std::path::PathBuf>,
}

/// The renderer's seeded weights by key relative to `upsampler.`.
fn renderer_weights(cfg: &ModelConfig) -> Result<WeightData> {
    let all =
        gagavatar_net::checkpoint::init_weights_where(cfg, 0, &|k| k.starts_with("upsampler."))?;
    Ok(all
        .into_iter()
        .filter_map(|(k, v)| k.strip_prefix("upsampler.").map(|k| (k.to_string(), v)))
        .collect())
}

pub fn bench_renderer_grad(a: RendererGradBench) -> Result<()> {
    let cfg =
        ModelConfig::preset(&a.preset).with_context(|| format!("unknown preset `{}`", a.preset))?;
    crate::cmd_track::set_threads(a.threads);
    let gpu = a.device.open_for_training("training the renderer")?;
    if gpu.is_none() && a.json.is_some() {
        anyhow::bail!("bench renderer-grad --json is for the GPU (--device gpu)");
    }
    let weights = renderer_weights(&cfg)?;
    let s = cfg.image_size;
    let dev = Device::Cpu;
    let input = Tensor::rand(-1f32, 1f32, (1, cfg.color_dim, s, s), &dev)?;
    let grad_out = Tensor::rand(-1f32, 1f32, (1, 3, s, s), &dev)?;
    let Some(gpu) = gpu else {
        let runs = a.runs.unwrap_or(3).max(1);
        let varmap = VarMap::new();
        let unet = StyleUNet::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev))?;
        for (key, var) in varmap
            .data()
            .lock()
            .map_err(|_| anyhow::anyhow!("poisoned"))?
            .iter()
        {
            let (shape, v) = weights
                .get(key)
                .with_context(|| format!("no seeded weight for {key}"))?;
            var.set(&Tensor::from_vec(v.clone(), shape.as_slice(), &dev)?)?;
        }
        let x = Var::from_tensor(&input)?;
        let step = || -> Result<()> {
            let y = unet.forward(x.as_tensor(), Noise::Fixed)?;
            let grads = (y * &grad_out)?.sum_all()?.backward()?;
            anyhow::ensure!(grads.get(x.as_tensor()).is_some(), "no input gradient");
            Ok(())
        };
        step()?;
        let mut wall = Vec::with_capacity(runs);
        for _ in 0..runs {
            crate::check_interrupt()?;
            let t = Instant::now();
            step()?;
            wall.push(1e3 * t.elapsed().as_secs_f64());
        }
        println!(
            "renderer forward + backward on the CPU (candle autograd): {} ({} threads): median {:.1} ms over {runs} steps",
            cfg.name,
            rayon::current_num_threads(),
            median(&mut wall)
        );
        return Ok(());
    };
    let runs = a.runs.unwrap_or(10).max(1);
    let desc = gpu.describe();
    let emulated = gpu.is_cpu();
    let tuning = a.device.tuning(&gpu)?;
    let t0 = Instant::now();
    let lookup = |key: &str| -> Result<Vec<f32>, GpuError> {
        weights
            .get(key)
            .map(|(_, v)| v.clone())
            .ok_or_else(|| GpuError::Weights(format!("no seeded weight for upsampler.{key}")))
    };
    let r = GpuRendererGrad::new(&gpu, &tuning, &cfg, &lookup)?;
    let upload = t0.elapsed();
    let host = |t: &Tensor| -> Result<Vec<f32>> { Ok(t.flatten_all()?.to_vec1()?) };
    r.set_input(&gpu, &host(&input)?)?;
    r.set_grad_output(&gpu, &host(&grad_out)?)?;
    let step = || -> Result<f64> {
        let t = Instant::now();
        gpu.submit(r.forward_steps());
        gpu.submit(r.backward_steps());
        gpu.wait()?;
        Ok(1e3 * t.elapsed().as_secs_f64())
    };
    let first = step()?;
    let bar = crate::animate::progress(runs, "bench renderer-grad (GPU)");
    let mut wall = Vec::with_capacity(runs);
    for _ in 0..runs {
        crate::check_interrupt()?;
        wall.push(step()?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let med = median(&mut wall);
    let mib = gpu.allocated_bytes() as f64 / (1 << 20) as f64;
    println!(
        "renderer forward + backward on the GPU: {desc}{}",
        if emulated {
            " -- CPU-EMULATED (lavapipe/llvmpipe): these numbers say nothing about a real GPU"
        } else {
            ""
        }
    );
    println!(
        "  {}: {} forward and {} backward dispatches, f32; upload {:.0} ms, first step {:.0} ms",
        cfg.name,
        r.forward_steps().len(),
        r.backward_steps().len(),
        1e3 * upload.as_secs_f64(),
        first
    );
    println!(
        "  one image, every parameter's gradient: median {med:.2} ms over {runs} steps (min {:.2}, max {:.2})",
        wall.first().copied().unwrap_or(f64::NAN),
        wall.last().copied().unwrap_or(f64::NAN)
    );
    println!("  GPU buffers allocated: {mib:.0} MiB (weights, activations, gradients)");
    if let Some(path) = &a.json {
        let doc = serde_json::json!({
            "adapter": desc,
            "emulated": emulated,
            "preset": cfg.name,
            "upload_ms": 1e3 * upload.as_secs_f64(),
            "first_step_ms": first,
            "runs": runs,
            "step_ms": {"median": med, "min": wall.first().copied(), "max": wall.last().copied()},
            "gpu_buffers_mib": mib,
        });
        let text = serde_json::to_string_pretty(&doc)? + "\n";
        gagavatar_formats::atomic::write_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
