//! `gagavatar bench reconstruct`: one source photo to the avatar's Gaussians on a GPU (or the
//! CPU, for comparison): time per stage, the median over runs, GPU memory.

use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{Device, Tensor};
use clap::Args;
use gagavatar_gpu::reconstruct::{GpuReconstruct, STAGES};
use gagavatar_net::model::GagAvatar;
use gagavatar_net::ModelConfig;

use crate::bench_stats::{by_kernel as by_kernel_of, dispatches_json, median, print_dispatches};
use crate::device_args::DeviceArgs;

#[derive(Debug, Args)]
pub struct ReconstructBench {
    #[command(flatten)]
    device: DeviceArgs,
    /// Architecture: release, small or tiny.
    #[arg(long, default_value = "release")]
    preset: String,
    /// Weights to use instead of seeded random ones.
    #[arg(long)]
    ckpt: Option<std::path::PathBuf>,
    /// Source photo (default: a random image).
    #[arg(long)]
    image: Option<std::path::PathBuf>,
    /// Timed runs (the median is reported); default 20 on a GPU, 3 on the CPU.
    #[arg(long)]
    runs: Option<usize>,
    /// Also time every dispatch of one run (GPU timestamps, each dispatch in a pass of its
    /// own) and print the kernels (by name and grid) that take the most time; GPU only.
    #[arg(long)]
    dispatches: bool,
    /// Also write the figures as JSON (per-stage ms, run ms, GPU memory) to this file; GPU
    /// only.
    #[arg(long)]
    json: Option<std::path::PathBuf>,
}

fn model(cfg: &ModelConfig, ckpt: Option<&std::path::Path>) -> Result<GagAvatar> {
    let dev = Device::Cpu;
    Ok(match ckpt {
        Some(p) => gagavatar_net::checkpoint::load_model(p, Some(cfg), &dev)
            .with_context(|| format!("loading {}", p.display()))?,
        None => {
            let mut map = std::collections::HashMap::new();
            for (k, (s, v)) in gagavatar_net::checkpoint::init_weights(cfg, 0)? {
                map.insert(k, Tensor::from_vec(v, s, &dev)?);
            }
            gagavatar_net::checkpoint::build_model(cfg, map, &dev)?
        }
    })
}

pub fn bench_reconstruct(a: ReconstructBench) -> Result<()> {
    let cfg =
        ModelConfig::preset(&a.preset).with_context(|| format!("unknown preset `{}`", a.preset))?;
    let gpu = a.device.open_for("reconstructing")?;
    if gpu.is_none() && a.json.is_some() {
        anyhow::bail!("bench reconstruct --json is for the GPU (--device gpu)");
    }
    let t0 = Instant::now();
    let model = model(&cfg, a.ckpt.as_deref())?;
    let dev = Device::Cpu;
    let size = cfg.image_size;
    let image = match &a.image {
        Some(p) => {
            gagavatar_avatar::image_tensor(&gagavatar_data::images::read_image_file(p)?, size)?
        }
        None => Tensor::rand(0f32, 1f32, (1, 3, size, size), &dev)?,
    };
    let tm = gagavatar_splat::Camera::look_at_origin_matrix(9.0, std::f64::consts::PI + 0.1, 0.05);
    let tm: Vec<f32> = tm.iter().flatten().map(|&x| x as f32).collect();
    let tm = Tensor::from_vec(tm, (1, 3, 4), &dev)?;
    eprintln!("model ready in {:.1} s", t0.elapsed().as_secs_f64());
    let Some(gpu) = gpu else {
        let runs = a.runs.unwrap_or(3).max(1);
        model.reconstruct(&image, &tm)?;
        let mut wall = Vec::with_capacity(runs);
        for _ in 0..runs {
            crate::check_interrupt()?;
            let t = Instant::now();
            model.reconstruct(&image, &tm)?;
            wall.push(1e3 * t.elapsed().as_secs_f64());
        }
        let med = median(&mut wall);
        println!(
            "reconstruct on the CPU: {} ({} threads): median {med:.1} ms over {runs} runs",
            cfg.name,
            rayon::current_num_threads()
        );
        return Ok(());
    };
    let runs = a.runs.unwrap_or(20).max(1);
    let desc = gpu.describe();
    let emulated = gpu.is_cpu();
    let tuning = a.device.tuning(&gpu)?;
    let t0 = Instant::now();
    let rec = GpuReconstruct::new(gpu, &tuning, &model)?;
    let upload = t0.elapsed();
    let t0 = Instant::now();
    rec.run(&image, &tm)?;
    let first = t0.elapsed();
    let bar = crate::animate::progress(runs, "bench reconstruct (GPU)");
    let mut wall = Vec::with_capacity(runs);
    let mut per_stage: Vec<Vec<f64>> = vec![Vec::new(); STAGES.len()];
    for _ in 0..runs {
        crate::check_interrupt()?;
        let t = Instant::now();
        rec.run(&image, &tm)?;
        wall.push(1e3 * t.elapsed().as_secs_f64());
        for (k, v) in rec.profile(&image, &tm)?.iter().enumerate() {
            per_stage[k].push(*v);
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    println!(
        "reconstruct on the GPU: {desc}{}",
        if emulated {
            " -- CPU-EMULATED (lavapipe/llvmpipe): these numbers say nothing about a real GPU"
        } else {
            ""
        }
    );
    println!(
        "  {} ({} Gaussians), convolutions {}; upload of the weights {:.0} ms, first run {:.0} ms",
        cfg.name,
        cfg.n_gaussians(),
        if tuning.mma {
            "on the tensor cores (f16 inputs, f32 sums)"
        } else {
            "f32"
        },
        1e3 * upload.as_secs_f64(),
        1e3 * first.as_secs_f64()
    );
    println!("  per stage (median of {runs} runs, each stage submitted and waited for alone):");
    let mut stage_json = serde_json::Map::new();
    for (k, name) in STAGES.iter().enumerate() {
        let m = median(&mut per_stage[k]);
        println!("    {name:<30} {m:>9.2} ms");
        stage_json.insert(name.to_string(), m.into());
    }
    let med = median(&mut wall);
    println!(
        "  photo + camera in, Gaussians on the GPU: median {med:.2} ms over {runs} runs (min {:.2}, max {:.2})",
        wall.first().copied().unwrap_or(f64::NAN),
        wall.last().copied().unwrap_or(f64::NAN),
    );
    let mut by_kernel = Vec::new();
    if a.dispatches {
        match rec.profile_dispatches(&image, &tm)? {
            Some(times) => {
                by_kernel = by_kernel_of(times);
                print_dispatches(&by_kernel, "one run", 20);
            }
            None => println!("  dispatches: this adapter has no timestamp queries"),
        }
    }
    let mib = rec.gpu().allocated_bytes() as f64 / (1 << 20) as f64;
    println!("  GPU buffers allocated: {mib:.0} MiB (weights, activations, the avatar)");
    if let Some(path) = &a.json {
        let doc = serde_json::json!({
            "adapter": desc,
            "emulated": emulated,
            "preset": cfg.name,
            "gaussians": cfg.n_gaussians(),
            "tensor_core_convs": tuning.mma,
            "upload_ms": 1e3 * upload.as_secs_f64(),
            "first_run_ms": 1e3 * first.as_secs_f64(),
            "stage_ms": stage_json,
            "runs": runs,
            "run_ms": {"median": med, "min": wall.first().copied(), "max": wall.last().copied()},
            "gpu_buffers_mib": mib,
            "dispatches": dispatches_json(&by_kernel),
        });
        let text = serde_json::to_string_pretty(&doc)? + "\n";
        gagavatar_formats::atomic::write_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
