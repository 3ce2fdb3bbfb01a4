//! `gagavatar bench dpt-grad`: the DPT head's training forward and backward for one sample
//! (the four frozen backbone outputs in, `F_local` out, every DPT weight's gradient from a
//! gradient of `F_local`) on a GPU, or on the CPU through candle's autograd for comparison:
//! median time per sample, GPU memory. What `train --device gpu` runs per sample with a
//! frozen backbone (the release's).

use std::collections::HashMap;
use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use clap::Args;
use gagavatar_gpu::grad::dpt::GpuDptGrad;
use gagavatar_net::dpt::DptHead;
use gagavatar_net::ModelConfig;

use crate::bench_stats::median;
use crate::device_args::DeviceArgs;

#[derive(Debug, Args)]
pub struct DptGradBench {
    #[command(flatten)]
    device: DeviceArgs,
    /// Architecture: release, small or tiny.
    #[arg(long, default_value = "release")]
    preset: String,
    /// Timed samples (the median is reported); default 10 on a GPU, 3 on the CPU.
    #[arg(long)]
    runs: Option<usize>,
    /// CPU worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Also write the figures as JSON to this file; GPU only.
    #[arg(long)]
    json: Option<std::path::PathBuf>,
}

const PREFIX: &str = "base_model.";

pub fn bench_dpt_grad(a: DptGradBench) -> Result<()> {
    let cfg =
        ModelConfig::preset(&a.preset).with_context(|| format!("unknown preset `{}`", a.preset))?;
    crate::cmd_track::set_threads(a.threads);
    let gpu = a.device.open_for_training("training the DPT head")?;
    if gpu.is_none() && a.json.is_some() {
        anyhow::bail!("bench dpt-grad --json is for the GPU (--device gpu)");
    }
    let is_dpt = |k: &str| k.starts_with(PREFIX) && !k.starts_with("base_model.dino_model.");
    let weights = gagavatar_net::checkpoint::init_weights_where(&cfg, 0, &is_dpt)?;
    let dev = Device::Cpu;
    let (g2, d) = (cfg.grid() * cfg.grid(), cfg.dino_size);
    let tokens: Vec<Tensor> = (0..4)
        .map(|_| Tensor::rand(-1f32, 1f32, (1, g2, cfg.vit_dim), &dev))
        .collect::<candle_core::Result<_>>()?;
    let image = Tensor::rand(-2f32, 2f32, (1, 3, d, d), &dev)?;
    let s = cfg.plane_size();
    let grad_out = Tensor::rand(-1f32, 1f32, (1, cfg.dpt_features, s, s), &dev)?;
    let Some(gpu) = gpu else {
        let runs = a.runs.unwrap_or(3).max(1);
        let varmap = VarMap::new();
        let head = DptHead::new(
            &cfg,
            VarBuilder::from_varmap(&varmap, DType::F32, &dev).pp("base_model"),
        )?;
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
        let feats = [
            tokens[0].clone(),
            tokens[1].clone(),
            tokens[2].clone(),
            tokens[3].clone(),
        ];
        let step = || -> Result<()> {
            let y = head.forward(&feats, &image)?;
            let grads = (y * &grad_out)?.sum_all()?.backward()?;
            let any = varmap
                .all_vars()
                .iter()
                .any(|v| grads.get(v.as_tensor()).is_some());
            anyhow::ensure!(any, "no weight gradient");
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
            "DPT head forward + backward on the CPU (candle autograd): {} ({} threads): median {:.1} ms over {runs} samples",
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
    let host: HashMap<String, Vec<f32>> = weights.into_iter().map(|(k, (_, v))| (k, v)).collect();
    let mut dpt = GpuDptGrad::new(&gpu, &tuning, &cfg, &host)?;
    let upload = t0.elapsed();
    let flat = |t: &Tensor| -> Result<Vec<f32>> { Ok(t.flatten_all()?.to_vec1()?) };
    let tok: Vec<Vec<f32>> = tokens.iter().map(flat).collect::<Result<_>>()?;
    let tok_refs = [
        tok[0].as_slice(),
        tok[1].as_slice(),
        tok[2].as_slice(),
        tok[3].as_slice(),
    ];
    let img = flat(&image)?;
    let gout = flat(&grad_out)?;
    // Each sample as the trainer sends it: the tokens and the image uploaded, the forward, the
    // gradient of F_local uploaded (the trainer's comes from the lifting generators on the
    // device), the backward.
    let mut step = || -> Result<f64> {
        let t = Instant::now();
        dpt.forward(&gpu, tok_refs, &img)?;
        dpt.backward(&gpu, &gout)?;
        gpu.wait()?;
        Ok(1e3 * t.elapsed().as_secs_f64())
    };
    let first = step()?;
    let bar = crate::animate::progress(runs, "bench dpt-grad (GPU)");
    let mut wall = Vec::with_capacity(runs);
    for _ in 0..runs {
        crate::check_interrupt()?;
        wall.push(step()?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let grads = dpt.read_grads(&gpu)?;
    anyhow::ensure!(
        grads.iter().all(|(_, v)| v.iter().all(|x| x.is_finite())),
        "a DPT gradient is not finite"
    );
    let med = median(&mut wall);
    let mib = gpu.allocated_bytes() as f64 / (1 << 20) as f64;
    println!(
        "DPT head forward + backward on the GPU: {desc}{}",
        if emulated {
            " -- CPU-EMULATED (lavapipe/llvmpipe): these numbers say nothing about a real GPU"
        } else {
            ""
        }
    );
    println!(
        "  {}: {} weight tensors, f32; upload {:.0} ms, first sample {:.0} ms",
        cfg.name,
        grads.len(),
        1e3 * upload.as_secs_f64(),
        first
    );
    println!(
        "  one sample, every DPT weight's gradient: median {med:.2} ms over {runs} samples (min {:.2}, max {:.2})",
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
            "first_sample_ms": first,
            "runs": runs,
            "sample_ms": {"median": med, "min": wall.first().copied(), "max": wall.last().copied()},
            "gpu_buffers_mib": mib,
        });
        let text = serde_json::to_string_pretty(&doc)? + "\n";
        gagavatar_formats::atomic::write_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
