//! `gagavatar bench drive`: the per-frame drive (expression -> FLAME vertices -> 32-channel
//! splat -> neural renderer -> RGB) on the CPU or a GPU, the avatar prepared once and not
//! timed. Prints the time per stage and frames/s (the median over the frames).

use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor};
use clap::Args;
use gagavatar_flame::{synthesize, FlameConfig, FlameIdentity, FlameModel};
use gagavatar_gpu::drive::{GpuDrive, STAGES};
use gagavatar_gpu::flame::FrameCodes;
use gagavatar_gpu::wgpu as wgpu_features;
use gagavatar_net::model::Avatar;
use gagavatar_net::style_unet::{Noise, StyleUNet};
use gagavatar_net::ModelConfig;
use gagavatar_splat::testscene::{avatar_scene, Regime, Rng};
use gagavatar_splat::Camera;

use crate::bench_stats::{
    by_kernel as by_kernel_of, dispatches_json, median, print_dispatches, KernelTotal,
};
use crate::device_args::DeviceArgs;
use gagavatar_avatar::{CpuDrive, Drive};

#[derive(Debug, Args)]
pub struct DriveBench {
    #[command(flatten)]
    device: DeviceArgs,
    /// Architecture: release, small or tiny.
    #[arg(long, default_value = "release")]
    preset: String,
    /// Renderer weights to use instead of seeded random ones (`upsampler.*` of a checkpoint).
    #[arg(long)]
    ckpt: Option<std::path::PathBuf>,
    /// Timed frames (the median is reported); default 300 on a GPU, 10 on the CPU.
    #[arg(long)]
    frames: Option<usize>,
    /// Gaussian sizes of the avatar-like scene: small (world scales ~0.005) or large (~0.025).
    #[arg(long, value_enum, default_value = "small")]
    regime: RegimeArg,
    /// CPU worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Also time every dispatch of one frame (GPU timestamps, each dispatch in a pass of its
    /// own) and print the kernels (by name and grid) that take the most time; GPU only.
    #[arg(long)]
    dispatches: bool,
    /// Also write the figures as JSON (adapter features, per-stage ms, frame ms, frames/s,
    /// GPU memory, tuning) to this file; GPU only.
    #[arg(long)]
    json: Option<std::path::PathBuf>,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum RegimeArg {
    Small,
    Large,
}

/// An avatar of the model's size: the benchmark scene's two lifted planes, its head points'
/// attributes for the expression Gaussians (whose positions FLAME gives each frame).
fn bench_avatar(cfg: &ModelConfig, regime: Regime) -> Result<Avatar> {
    let nl = cfg.lifted_points();
    let nv = cfg.n_vertices;
    let (scene, _) = avatar_scene(cfg.plane_size(), nv, cfg.color_dim, regime, 1);
    let dev = Device::Cpu;
    let head_first = |v: &[f32], k: usize| -> Result<Tensor> {
        let mut out = v[nl * k..].to_vec();
        out.extend_from_slice(&v[..nl * k]);
        Ok(Tensor::from_vec(out, (1, nl + nv, k), &dev)?)
    };
    Ok(Avatar {
        lifted_xyz: Tensor::from_slice(&scene.means[..3 * nl], (1, nl, 3), &dev)?,
        colors: head_first(&scene.features, cfg.color_dim)?,
        opacities: head_first(&scene.opacities, 1)?,
        scales: head_first(&scene.scales, 3)?,
        rotations: head_first(&scene.rotations, 4)?,
    })
}

fn renderer(cfg: &ModelConfig, ckpt: Option<&std::path::Path>) -> Result<StyleUNet> {
    let dev = Device::Cpu;
    let map: std::collections::HashMap<String, Tensor> = match ckpt {
        Some(p) => gagavatar_net::checkpoint::read_weights(p)
            .with_context(|| format!("reading {}", p.display()))?
            .tensors
            .into_iter()
            .filter(|(k, _)| k.starts_with("upsampler."))
            .collect(),
        None => {
            let w = gagavatar_net::checkpoint::init_weights_where(cfg, 0, &|k| {
                k.starts_with("upsampler.")
            })?;
            let mut m = std::collections::HashMap::new();
            for (k, (s, v)) in w {
                m.insert(k, Tensor::from_vec(v, s, &dev)?);
            }
            m
        }
    };
    let vb = candle_nn::VarBuilder::from_tensors(map, DType::F32, &dev);
    Ok(StyleUNet::new(cfg, vb.pp("upsampler"))?)
}

/// Expression codes that change every frame (a slow random walk), so nothing is cached.
fn codes(rng: &mut Rng, n_exp: usize, frame: usize) -> FrameCodes {
    let t = frame as f32 * 0.05;
    FrameCodes {
        expression: (0..n_exp)
            .map(|i| (0.8 * (t + i as f32).sin()) + 0.05 * rng.normal() as f32)
            .collect(),
        pose: [0.0, 0.0, 0.0, 0.1 * t.sin().abs(), 0.0, 0.0],
        eye: [0.02 * t.cos(), 0.0, 0.0, 0.02 * t.cos(), 0.0, 0.0],
    }
}

pub fn bench_drive(a: DriveBench) -> Result<()> {
    let cfg =
        ModelConfig::preset(&a.preset).with_context(|| format!("unknown preset `{}`", a.preset))?;
    let regime = match a.regime {
        RegimeArg::Small => Regime::Small,
        RegimeArg::Large => Regime::Large,
    };
    let threads = a.threads.unwrap_or_else(|| {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    });
    std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    let gpu = a.device.open()?;
    if gpu.is_none() && a.json.is_some() {
        anyhow::bail!("bench drive --json is for the GPU drive (--device gpu)");
    }
    let t0 = Instant::now();
    let renderer = renderer(&cfg, a.ckpt.as_deref())?;
    let avatar = bench_avatar(&cfg, regime)?;
    let flame = FlameModel::new(
        &synthesize(1),
        FlameConfig::default(),
        &Device::Cpu,
        DType::F32,
    )?;
    let identity = flame.identity(&Tensor::zeros((1, 300), DType::F32, &Device::Cpu)?)?;
    let tm = Camera::look_at_origin_matrix(9.0, std::f64::consts::PI + 0.1, 0.05);
    eprintln!("prepared in {:.1} s", t0.elapsed().as_secs_f64());
    let mut rng = Rng::new(7);
    let n_gauss = cfg.n_gaussians();
    match gpu {
        Some(gpu) => bench_gpu(
            &a, &cfg, gpu, &renderer, &avatar, &flame, &identity, &tm, &mut rng, n_gauss,
        ),
        None => {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .context("building the thread pool")?;
            pool.install(|| {
                bench_cpu(
                    &a, &cfg, &renderer, &avatar, &flame, &identity, &tm, &mut rng, threads,
                )
            })
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn bench_gpu(
    a: &DriveBench,
    cfg: &ModelConfig,
    gpu: Arc<gagavatar_gpu::Gpu>,
    renderer: &StyleUNet,
    avatar: &Avatar,
    flame: &FlameModel,
    identity: &FlameIdentity,
    tm: &[[f64; 4]; 3],
    rng: &mut Rng,
    n_gauss: usize,
) -> Result<()> {
    let frames = a.frames.unwrap_or(300).max(1);
    let emulated = gpu.is_cpu();
    let desc = gpu.describe();
    let tuning = a.device.tuning(&gpu)?;
    let t0 = Instant::now();
    let mut drive = GpuDrive::new(
        gpu,
        &tuning,
        cfg,
        renderer,
        avatar,
        flame,
        identity,
        Noise::Fixed,
    )?;
    let upload = t0.elapsed();
    // Warm-up: first use of each pipeline, and the pair buffers reach their size.
    let t0 = Instant::now();
    drive.frame(&codes(rng, flame.config.n_exp, 0), tm)?;
    let first = t0.elapsed();
    let bar = crate::animate::progress(frames, "bench drive (GPU)");
    let mut wall = Vec::with_capacity(frames);
    for f in 0..frames {
        crate::check_interrupt()?;
        let c = codes(rng, flame.config.n_exp, f + 1);
        let t = Instant::now();
        drive.frame(&c, tm)?;
        wall.push(1e3 * t.elapsed().as_secs_f64());
        bar.inc(1);
    }
    bar.finish_and_clear();
    // The same number of frames streamed as reenact streams them: one rendering while the last
    // is read back and turned into bytes, so the GPU never waits for the host.
    let jobs: Vec<_> = (0..frames)
        .map(|f| (codes(rng, flame.config.n_exp, f + 1), *tm))
        .collect();
    let t = Instant::now();
    drive.stream_rgb8(&jobs, |_, _| ControlFlow::Continue(()))?;
    let streamed_ms = 1e3 * t.elapsed().as_secs_f64() / frames as f64;
    let profiled = 10.min(frames).max(1);
    let mut per_stage: Vec<Vec<f64>> = vec![Vec::new(); STAGES.len()];
    let mut timestamps = false;
    for f in 0..profiled {
        let st = drive.profile(&codes(rng, flame.config.n_exp, f), tm)?;
        timestamps = st.timestamps;
        for (k, v) in st.ms.iter().enumerate() {
            per_stage[k].push(*v);
        }
    }
    let mut by_kernel: Vec<KernelTotal> = Vec::new();
    let mut have_timestamps = true;
    if a.dispatches {
        match drive.profile_dispatches(&codes(rng, flame.config.n_exp, 0), tm)? {
            Some(times) => by_kernel = by_kernel_of(times),
            None => have_timestamps = false,
        }
    }
    let g = drive.gpu();
    // For the tuning notes (crates/gpu/README.md): what faster kernels could use on this adapter.
    let has = |f: wgpu_features::Features| g.adapter_features.contains(f);
    let coop: Vec<String> = g
        .cooperative_matrices
        .iter()
        .map(|c| {
            format!(
                "{}x{}x{} {:?}->{:?}",
                c.m_size, c.n_size, c.k_size, c.ab_type, c.cr_type
            )
        })
        .collect();
    println!(
        "adapter: shader-f16 {}, subgroups {}, timestamps {}, cooperative matrices [{}]",
        has(wgpu_features::Features::SHADER_F16),
        has(wgpu_features::Features::SUBGROUP),
        has(wgpu_features::Features::TIMESTAMP_QUERY),
        coop.join(", ")
    );
    println!(
        "drive on the GPU: {desc}{}",
        if emulated {
            " -- CPU-EMULATED (lavapipe/llvmpipe): these numbers say nothing about a real GPU"
        } else {
            ""
        }
    );
    println!(
        "  convolutions: {}",
        if tuning.mma {
            "tensor cores (f16 inputs, f32 sums)"
        } else {
            "f32"
        }
    );
    println!(
        "  {} {}x{}, {n_gauss} Gaussians ({:?} regime), {} channels; upload {:.0} ms, first frame {:.0} ms",
        cfg.name,
        cfg.image_size,
        cfg.image_size,
        a.regime,
        cfg.color_dim,
        1e3 * upload.as_secs_f64(),
        1e3 * first.as_secs_f64(),
    );
    println!(
        "  per stage (median of {profiled} frames, {}):",
        if timestamps {
            "GPU timestamps"
        } else {
            "each stage submitted and waited for alone (no timestamp queries on this adapter)"
        }
    );
    let mut device_total = 0.0;
    let mut stage_json = serde_json::Map::new();
    for (k, name) in STAGES.iter().enumerate() {
        let m = median(&mut per_stage[k]);
        device_total += m;
        println!("    {name:<30} {m:>9.2} ms");
        stage_json.insert(name.to_string(), m.into());
    }
    println!("    {:<30} {device_total:>9.2} ms", "sum");
    // (median sorts, so the first and last are the fastest and slowest frames)
    let med = median(&mut wall);
    println!(
        "  frame (codes in, RGB read back): median {med:.2} ms over {frames} frames (min {:.2}, max {:.2}) = {:.1} frames/s",
        wall.first().copied().unwrap_or(f64::NAN),
        wall.last().copied().unwrap_or(f64::NAN),
        1e3 / med
    );
    println!(
        "  streamed (frame i + 1 rendering while frame i is read back, as reenact does): {streamed_ms:.2} ms a frame over {frames} frames = {:.1} frames/s",
        1e3 / streamed_ms
    );
    if a.dispatches {
        if have_timestamps {
            print_dispatches(&by_kernel, "one frame", 15);
        } else {
            println!("  dispatches: this adapter has no timestamp queries");
        }
    }
    let mib = g.allocated_bytes() as f64 / (1 << 20) as f64;
    println!(
        "  GPU buffers allocated: {mib:.0} MiB; (tile, Gaussian) pair capacity {}",
        drive.pair_capacity()
    );
    if let Some(path) = &a.json {
        let doc = serde_json::json!({
            "adapter": {
                "description": desc,
                "emulated": emulated,
                "shader_f16": has(wgpu_features::Features::SHADER_F16),
                "subgroups": has(wgpu_features::Features::SUBGROUP),
                "timestamps": has(wgpu_features::Features::TIMESTAMP_QUERY),
                "cooperative_matrices": coop,
            },
            "preset": cfg.name,
            "image_size": cfg.image_size,
            "gaussians": n_gauss,
            "regime": format!("{:?}", a.regime).to_lowercase(),
            "tuning": format!("{tuning:?}"),
            "tensor_core_convs": tuning.mma,
            "upload_ms": 1e3 * upload.as_secs_f64(),
            "first_frame_ms": 1e3 * first.as_secs_f64(),
            "stage_ms": stage_json,
            "stage_ms_from": if timestamps { "timestamps" } else { "submit-and-wait" },
            "stage_sum_ms": device_total,
            "frames": frames,
            "frame_ms": {
                "median": med,
                "min": wall.first().copied(),
                "max": wall.last().copied(),
            },
            "frames_per_s": 1e3 / med,
            "streamed_frame_ms": streamed_ms,
            "streamed_frames_per_s": 1e3 / streamed_ms,
            "gpu_buffers_mib": mib,
            "pair_capacity": drive.pair_capacity(),
            "dispatches": dispatches_json(&by_kernel),
        });
        let text = serde_json::to_string_pretty(&doc)? + "\n";
        gagavatar_formats::atomic::write_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn bench_cpu(
    a: &DriveBench,
    cfg: &ModelConfig,
    renderer: &StyleUNet,
    avatar: &Avatar,
    flame: &FlameModel,
    identity: &FlameIdentity,
    tm: &[[f64; 4]; 3],
    rng: &mut Rng,
    threads: usize,
) -> Result<()> {
    let frames = a.frames.unwrap_or(10).max(1);
    // The library's CPU drive, the one `reenact` and `eval` use, built from parts (no ViT).
    let mut drive = CpuDrive::from_parts(
        cfg.clone(),
        renderer.clone(),
        Arc::new(flame.clone()),
        avatar.clone(),
        identity.clone(),
        Noise::Fixed,
    );
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); 4];
    let bar = crate::animate::progress(frames + 1, "bench drive (CPU)");
    for f in 0..=frames {
        crate::check_interrupt()?;
        let c = codes(rng, flame.config.n_exp, f);
        let before = drive.times();
        let t = Instant::now();
        let _rgb = drive.render(&c, tm)?;
        let wall = t.elapsed();
        let after = drive.times();
        if f > 0 {
            let ms = |d: std::time::Duration| 1e3 * d.as_secs_f64();
            let t_flame = after.flame - before.flame;
            let t_splat = after.splat - before.splat;
            times[0].push(ms(t_flame));
            times[1].push(ms(t_splat));
            times[2].push(ms(wall.saturating_sub(t_flame + t_splat)));
            times[3].push(ms(wall));
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    println!(
        "drive on the CPU ({threads} threads): {} {}x{}, {} Gaussians ({:?} regime), median of {frames} frames after a warm-up",
        cfg.name,
        cfg.image_size,
        cfg.image_size,
        cfg.n_gaussians(),
        a.regime
    );
    for (k, name) in ["FLAME", "splat", "renderer + RGB", "frame"]
        .iter()
        .enumerate()
    {
        println!("    {name:<30} {:>9.1} ms", median(&mut times[k]));
    }
    println!("  {:.2} frames/s", 1e3 / median(&mut times[3]));
    Ok(())
}
