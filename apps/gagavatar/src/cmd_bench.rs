//! `gagavatar bench ...`: timings of the hot paths on this machine.

use anyhow::{Context, Result};
use candle_core::{Device, Tensor, Var};
use clap::{Args, Subcommand, ValueEnum};
use gagavatar_splat::testscene::{avatar_scene, Regime};
use gagavatar_splat::{splat, Gaussians};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Subcommand)]
pub enum BenchCmd {
    /// Splatting forward and backward on the avatar-like scene (2 lifted 296x296 planes + 5023
    /// head points, camera at distance 9, focal 12, 512x512, 32 channels): on the CPU, or the
    /// training forward and backward (every Gaussian's gradients) on a GPU.
    #[command(
        after_help = "Example:\n  gagavatar bench splat --regime small --runs 20 --threads 2\n  \
gagavatar bench splat --device gpu --regime both --runs 20"
    )]
    Splat(SplatBench),
    /// The network: reconstruct (per module) and drive (splat + renderer) on one frame.
    #[command(
        after_help = "Seeded random weights of the preset unless --ckpt is given.\n\nExample:\n  gagavatar bench model --preset release --runs 3 --threads 2"
    )]
    Model(ModelBench),
    /// Video reading: decode speed (frames/s delivered as RGB) at 512x512 and 1080p through
    /// ffmpeg and the built-in OpenH264 path, and peak memory while streaming 1080p. The clips
    /// are made with ffmpeg first (x264 High with B-frames, like phone videos).
    #[command(after_help = "Example:\n  gagavatar bench video --threads 2 --runs 5")]
    Video(VideoBench),
    /// The per-frame drive (expression -> FLAME -> splat -> renderer -> RGB) on the CPU or a
    /// GPU: time per stage, frames/s (median over the frames), GPU memory.
    #[command(
        after_help = "The avatar is the avatar-like benchmark scene at the model's size \
(5023 + 2 x 296^2 Gaussians for release), prepared and uploaded once and not timed; renderer \
weights are seeded random ones unless --ckpt is given. GAGAVATAR_GPU_TUNE=key=value,... tries \
other kernel tile sizes (crates/gpu/README.md).\n\nExample:\n  gagavatar bench drive --device gpu\n  \
gagavatar bench drive --device cpu --threads 2 --frames 10"
    )]
    Drive(crate::cmd_bench_drive::DriveBench),
    /// `reconstruct` (photo + camera -> the avatar's Gaussians) on a GPU or the CPU: time per
    /// stage (preprocessing, DINOv2, DPT, the generators), median over runs, GPU memory.
    #[command(
        after_help = "Seeded random weights of the preset unless --ckpt is given; a random \
image unless --image.\n\nExample:\n  gagavatar bench reconstruct --device gpu --runs 20\n  \
gagavatar bench reconstruct --device gpu --preset tiny --json rec.json"
    )]
    Reconstruct(crate::cmd_bench_reconstruct::ReconstructBench),
    /// The neural renderer's training forward and backward on one image (every parameter's
    /// gradient and the input's) on a GPU, or on the CPU through candle's autograd.
    #[command(
        after_help = "Seeded random weights of the preset; the convolutions run in f32 on the GPU.\n\nExample:\n  gagavatar bench renderer-grad --device gpu --preset release --runs 10\n  \
gagavatar bench renderer-grad --device cpu --preset small --threads 2"
    )]
    RendererGrad(crate::cmd_bench_renderer_grad::RendererGradBench),
    /// The DPT head's training forward and backward for one sample (every DPT weight's
    /// gradient from a gradient of F_local) on a GPU, or on the CPU through candle's autograd.
    #[command(
        after_help = "Seeded random weights of the preset, random backbone outputs; the convolutions run in f32 on the GPU.\n\nExample:\n  gagavatar bench dpt-grad --device gpu --preset release --runs 10\n  \
gagavatar bench dpt-grad --device cpu --preset release --threads 2"
    )]
    DptGrad(crate::cmd_bench_dpt_grad::DptGradBench),
    /// Face perception: tracking-mode landmarks per video frame, detection, the 256x256 matte.
    #[command(
        after_help = "Frames are images (a folder of them, or files), used in order as a video. Each frame is\ncopied right before it is timed, as a decoder would have just written it.\n\nExample:\n  ffmpeg -i clip.mp4 frames/%04d.png\n  gagavatar bench face frames --threads 2 --runs 3"
    )]
    Face(FaceBench),
    /// The paper's evaluation protocol on self-reenactment pairs: the metrics' time per pair
    /// (realignment, landmarks, CSIM, AED / APD fits, AKD, PSNR, SSIM, LPIPS with --lpips),
    /// apart from the model's rendering.
    #[command(
        after_help = "Without --ckpt the ground truth is scored as the result (no rendering), which \
exercises every metric on real faces. Prints the load average before and after.\n\nExample:\n  \
gagavatar bench eval --data tracked_test --pairs 100 --threads 2"
    )]
    Eval(EvalBench),
    /// The server under load on loopback: concurrent clients rendering frames of several
    /// avatars, with batching and one request at a time, every answer checked.
    #[command(
        after_help = "Runs the server in this process (the demo model unless --ckpt), makes an \
avatar of the astronaut photo and of its mirror image, then for each --max-batch value lets \
--clients clients send --requests render requests each. Prints frames/s, client-side p50/p99 \
latency, renderer calls, upload-to-first-frame time, memory per cached avatar and peak \
memory.\n\nExample:\n  gagavatar bench serve --clients 32 --requests 8 --threads 2\n  \
gagavatar bench serve --ckpt release.safetensors --flame synthetic --clients 32 --requests 1"
    )]
    Serve(crate::cmd_bench_serve::ServeBench),
    /// Tracking: a 512x512 video end to end (decode, detection + landmarks, matte, FLAME fit,
    /// crop, JPEG and LMDB write) in frames/s, and a photo's latency.
    #[command(
        after_help = "The clip is made first (not timed): the demo's public-domain astronaut photo \
(assets/demo/astronaut.jpg) seen through a slowly zooming and panning window, 512x512, written \
as H.264 mp4 and read back like any video.\n\nExample:\n  gagavatar bench track --threads 2"
    )]
    Track(TrackBench),
}

#[derive(Debug, Args)]
pub struct EvalBench {
    /// Dataset with faces (e.g. a tracker output), 512 crops.
    #[arg(long)]
    data: PathBuf,
    /// Model weights; without them the ground truth is the result.
    #[arg(long)]
    ckpt: Option<PathBuf>,
    #[arg(long)]
    flame: Option<PathBuf>,
    #[arg(long, default_value = "test")]
    split: String,
    #[arg(long, default_value_t = 100)]
    pairs: usize,
    #[arg(long)]
    lpips: Option<PathBuf>,
    #[arg(long, default_value_t = 2)]
    threads: usize,
    #[arg(long, default_value_t = 8)]
    batch: usize,
}

#[derive(Debug, Args)]
pub struct TrackBench {
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Length of the test clip in frames (25 fps).
    #[arg(long, default_value_t = 250)]
    frames: usize,
    /// Timed runs of the whole clip, and of the photo (the medians are reported).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// The photo (default: assets/demo/astronaut.jpg).
    #[arg(long)]
    photo: Option<std::path::PathBuf>,
    /// FLAME asset.
    #[arg(long, default_value = crate::cmd_model::SYNTHETIC_FLAME)]
    flame: std::path::PathBuf,
}

#[derive(Debug, Args)]
pub struct VideoBench {
    /// ffmpeg decoder threads.
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Timed runs per clip (the median is reported).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Length of the test clips in frames (30 fps).
    #[arg(long, default_value_t = 300)]
    frames: usize,
    /// Folder for the test clips (default: a temporary folder, removed afterwards).
    #[arg(long)]
    dir: Option<std::path::PathBuf>,
}

#[derive(Debug, Args)]
pub struct FaceBench {
    /// A folder of frames (sorted by name) or image files.
    #[arg(required = true)]
    frames: Vec<std::path::PathBuf>,
    /// Passes over the frames (the first is a warm-up); medians over all timed frames.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Use at most this many frames.
    #[arg(long, default_value_t = 120)]
    max_frames: usize,
}

#[derive(Debug, Args)]
pub struct ModelBench {
    /// Architecture: release, small or tiny.
    #[arg(long, default_value = "release")]
    preset: String,
    /// Weights to use instead of seeded random ones.
    #[arg(long)]
    ckpt: Option<std::path::PathBuf>,
    /// Timed runs (after one warm-up); the median is reported.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Arithmetic of the products: f32 (the release's) or bf16 (AVX512-BF16 CPUs). With bf16
    /// the run ends with the quality cost: the fine image of bf16 against f32 (max abs, PSNR).
    #[arg(long, default_value = "f32")]
    precision: gagavatar_ops::Precision,
    /// Source image (resized to the preset's size) instead of uniform noise: a real face gives
    /// the quality comparison realistic activations.
    #[arg(long)]
    image: Option<std::path::PathBuf>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum RegimeArg {
    Small,
    Large,
    Both,
}

#[derive(Debug, Args)]
pub struct SplatBench {
    /// Scale regime: small (world scales ~0.005) or large (~0.025, ~30 px radius).
    #[arg(long, value_enum, default_value = "both")]
    regime: RegimeArg,
    /// Timed runs per measurement (after one warm-up); the median is reported.
    #[arg(long, default_value_t = 10)]
    runs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Feature channels.
    #[arg(long, default_value_t = 32)]
    channels: usize,
    /// Points per side of each lifted plane.
    #[arg(long, default_value_t = 296)]
    plane: usize,
    #[command(flatten)]
    device: crate::device_args::DeviceArgs,
}

pub fn run(cmd: BenchCmd) -> Result<()> {
    match cmd {
        BenchCmd::Splat(args) => bench_splat(args),
        BenchCmd::Model(args) => bench_model(args),
        BenchCmd::Video(args) => bench_video(args),
        BenchCmd::Drive(args) => crate::cmd_bench_drive::bench_drive(args),
        BenchCmd::Reconstruct(args) => crate::cmd_bench_reconstruct::bench_reconstruct(args),
        BenchCmd::RendererGrad(args) => crate::cmd_bench_renderer_grad::bench_renderer_grad(args),
        BenchCmd::DptGrad(args) => crate::cmd_bench_dpt_grad::bench_dpt_grad(args),
        BenchCmd::Face(args) => bench_face(args),
        BenchCmd::Eval(args) => bench_eval(args),
        BenchCmd::Track(args) => bench_track(args),
        BenchCmd::Serve(args) => crate::cmd_bench_serve::bench_serve(args),
    }
}

use crate::bench_stats::median;
pub use crate::procstat::peak_rss_mib;

fn bench_splat(args: SplatBench) -> Result<()> {
    let threads = args.threads.unwrap_or_else(num_cpus);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("building the thread pool")?;
    let regimes: &[Regime] = match args.regime {
        RegimeArg::Small => &[Regime::Small],
        RegimeArg::Large => &[Regime::Large],
        RegimeArg::Both => &[Regime::Small, Regime::Large],
    };
    let runs = args.runs.max(1);
    // The splatting's training kernels are f32 whatever the adapter offers.
    let gpu = args
        .device
        .open_for_training("splatting forward + backward")?;
    for &regime in regimes {
        let (scene, cam) = avatar_scene(args.plane, 5023, args.channels, regime, 1);
        if let Some(gpu) = &gpu {
            let tuning = args.device.tuning(gpu)?;
            let bg = vec![0f32; args.channels];
            let t = crate::cmd_bench_splat_gpu::time(gpu, &tuning, &scene, &bg, &cam, runs)?;
            println!(
                "splat {regime:?} on the GPU ({}{}): {} Gaussians, {}x{}, {} channels: training \
                 forward median {:.2} ms, backward median {:.2} ms, tile pairs {}, GPU buffers {:.0} MiB",
                gpu.describe(),
                if gpu.is_cpu() { ", CPU-EMULATED: says nothing about a real GPU" } else { "" },
                scene.len(),
                cam.width,
                cam.height,
                args.channels,
                t.forward,
                t.backward,
                t.pairs,
                t.mib
            );
            continue;
        }
        let dev = Device::Cpu;
        let tensors = scene.to_tensors(&dev)?;
        let bg = Tensor::zeros(args.channels, candle_core::DType::F32, &dev)?;
        let pb = ProgressBar::new(2 * (runs as u64 + 1));
        pb.set_style(ProgressStyle::with_template(
            "{msg} [{bar:30}] {pos}/{len} ETA {eta}",
        )?);
        pb.set_message(format!("{regime:?}"));
        let mut fwd = Vec::new();
        let mut bwd = Vec::new();
        let mut pairs = 0;
        let mut visible = 0;
        pool.install(|| -> Result<()> {
            for i in 0..=runs {
                let t0 = Instant::now();
                let out = splat(
                    &Gaussians::from_tensors(&tensors),
                    &bg,
                    std::slice::from_ref(&cam),
                )?;
                let dt = t0.elapsed().as_secs_f64();
                pairs = out.tile_pairs[0];
                let radii: Vec<u32> = out.radii.flatten_all()?.to_vec1()?;
                visible = radii.iter().filter(|&&r| r > 0).count();
                if i > 0 {
                    fwd.push(dt * 1e3);
                }
                pb.inc(1);
            }
            let vars = tensors
                .iter()
                .map(Var::from_tensor)
                .collect::<candle_core::Result<Vec<_>>>()?;
            let var_tensors: [Tensor; 5] = std::array::from_fn(|i| vars[i].as_tensor().clone());
            for i in 0..=runs {
                let out = splat(
                    &Gaussians::from_tensors(&var_tensors),
                    &bg,
                    std::slice::from_ref(&cam),
                )?;
                let loss = out.image.mean_all()?;
                let t0 = Instant::now();
                let grads = loss.backward()?;
                let dt = t0.elapsed().as_secs_f64();
                anyhow::ensure!(grads.get(vars[0].as_tensor()).is_some(), "no gradient");
                if i > 0 {
                    bwd.push(dt * 1e3);
                }
                pb.inc(1);
            }
            Ok(())
        })?;
        pb.finish_and_clear();
        println!(
            "splat {regime:?}: {} Gaussians ({visible} visible), {}x{}, {} channels, {threads} threads: \
             forward median {:.1} ms (min {:.1}), backward median {:.1} ms (min {:.1}), tile pairs {pairs}, \
             peak RSS {:.0} MiB",
            scene.len(),
            cam.width,
            cam.height,
            args.channels,
            median(&mut fwd),
            fwd[0],
            median(&mut bwd),
            bwd[0],
            peak_rss_mib().unwrap_or(f64::NAN)
        );
    }
    Ok(())
}

fn num_cpus() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
}

fn bench_model(args: ModelBench) -> Result<()> {
    use gagavatar_net::checkpoint::{init_weights, load_model};
    use gagavatar_net::model::GagAvatar;
    use gagavatar_net::style_unet::Noise;
    use gagavatar_net::ModelConfig;

    let threads = args.threads.unwrap_or_else(num_cpus);
    // candle's matmul reads the thread count from the environment.
    std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("building the thread pool")?;
    let cfg = ModelConfig::preset(&args.preset)
        .with_context(|| format!("unknown preset `{}`", args.preset))?;
    let dev = Device::Cpu;
    let mut model = match &args.ckpt {
        Some(p) => load_model(p, Some(&cfg), &dev)?,
        None => {
            let w = init_weights(&cfg, 0)?;
            let mut map = std::collections::HashMap::new();
            for (k, (s, v)) in w {
                map.insert(k, Tensor::from_vec(v, s, &dev)?);
            }
            gagavatar_net::checkpoint::build_model(&cfg, map, &dev)?
        }
    };
    model.set_precision(args.precision)?;
    let rss_after_load = peak_rss_mib();
    let size = cfg.image_size;
    let image = match &args.image {
        // The pipeline's own reading and resizing of a source photo.
        Some(p) => {
            gagavatar_avatar::image_tensor(&gagavatar_data::images::read_image_file(p)?, size)?
        }
        None => Tensor::rand(0f32, 1f32, (1, 3, size, size), &dev)?,
    };
    // The release's frontal camera is yaw = pi (R = diag(-1, 1, -1)); slightly off-axis.
    let tm = gagavatar_splat::Camera::look_at_origin_matrix(9.0, std::f64::consts::PI + 0.1, 0.05);
    let tm: Vec<f32> = tm.iter().flatten().map(|&x| x as f32).collect();
    let tm = Tensor::from_vec(tm, (1, 3, 4), &dev)?;
    let verts = Tensor::randn(0f32, 0.4, (1, cfg.n_vertices, 3), &dev)?;
    let mut names: Vec<&str> = GagAvatar::STAGES.to_vec();
    names.extend(["reconstruct (total)", "splat", "renderer", "drive (total)"]);
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    let runs = args.runs.max(1);
    let bar = ProgressBar::new((runs + 1) as u64);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} ETA {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(format!("model {} x{threads}", cfg.name));
    pool.install(|| -> Result<()> {
        for run in 0..=runs {
            let mut t = Vec::with_capacity(names.len());
            let start = Instant::now();
            let mut lap = start;
            let (avatar, _) = model.reconstruct_staged(&image, &tm, &mut |_| {
                t.push(lap.elapsed().as_secs_f64());
                lap = Instant::now();
            })?;
            t.push(start.elapsed().as_secs_f64());
            let d0 = Instant::now();
            let coarse = model.splat_coarse(&avatar, &verts, &tm)?;
            t.push(d0.elapsed().as_secs_f64());
            let r0 = Instant::now();
            model.render(&coarse, Noise::Fixed)?;
            t.push(r0.elapsed().as_secs_f64());
            t.push(d0.elapsed().as_secs_f64());
            if run > 0 {
                for (k, v) in t.into_iter().enumerate() {
                    times[k].push(v);
                }
            }
            bar.inc(1);
        }
        Ok(())
    })?;
    bar.finish_and_clear();
    println!(
        "model {} {} ({threads} threads, median of {runs} runs after a warm-up)",
        cfg.name,
        args.precision.name()
    );
    for (k, name) in names.iter().enumerate() {
        println!("  {name:<22} {:>9.1} ms", 1e3 * median(&mut times[k]));
    }
    if let Some(mib) = rss_after_load {
        println!("  peak RSS after loading {mib:>9.0} MiB");
    }
    if let Some(mib) = peak_rss_mib() {
        println!("  peak RSS               {mib:>9.0} MiB");
    }
    if args.precision != gagavatar_ops::Precision::F32 {
        // The fine image end to end, and the renderer alone on a fixed pattern (the input
        // `tools/reference/bench_torch.py --weights` gives PyTorch, so the two compare).
        let pattern = render_pattern(cfg.color_dim, size, &dev)?;
        let outputs = |model: &GagAvatar| -> Result<[Vec<f32>; 2]> {
            pool.install(|| {
                let avatar = model.reconstruct(&image, &tm)?;
                let coarse = model.splat_coarse(&avatar, &verts, &tm)?;
                let fine = model.render(&coarse, Noise::Fixed)?;
                let alone = model.render(&pattern, Noise::Fixed)?;
                Ok([
                    fine.flatten_all()?.to_vec1()?,
                    alone.flatten_all()?.to_vec1()?,
                ])
            })
        };
        let low = outputs(&model)?;
        model.set_precision(gagavatar_ops::Precision::F32)?;
        let full = outputs(&model)?;
        let p = args.precision.name();
        for (what, (a, b)) in ["fine image (end to end)", "renderer alone (pattern)"]
            .iter()
            .zip(low.iter().zip(&full))
        {
            let (max_abs, psnr) = image_difference(a, b);
            println!("  {what}, {p} against f32: max abs {max_abs:.2e}, PSNR {psnr:.1} dB");
        }
    }
    Ok(())
}

/// The renderer input of the precision comparison: `0.5 + 0.5 sin(0.05 (c + 1) x + 0.07 y +
/// 0.3 c)` in channel c, row y, column x (`bench_torch.py` builds the same).
fn render_pattern(channels: usize, size: usize, dev: &Device) -> Result<Tensor> {
    let mut v = Vec::with_capacity(channels * size * size);
    for c in 0..channels {
        for y in 0..size {
            for x in 0..size {
                let a = 0.05 * (c + 1) as f64 * x as f64 + 0.07 * y as f64 + 0.3 * c as f64;
                v.push((0.5 + 0.5 * a.sin()) as f32);
            }
        }
    }
    Ok(Tensor::from_vec(v, (1, channels, size, size), dev)?)
}

/// Largest absolute difference (NaN when any value is) and PSNR (peak 1) of two images in
/// [0, 1].
fn image_difference(a: &[f32], b: &[f32]) -> (f64, f64) {
    let mut max_abs = 0f64;
    let mut sq = 0f64;
    for (&x, &y) in a.iter().zip(b) {
        let d = (x as f64 - y as f64).abs();
        // `f64::max` would drop a NaN; a NaN anywhere stays the answer.
        if d.is_nan() || d > max_abs {
            max_abs = d;
        }
        sq += d * d;
    }
    let mse = sq / a.len().max(1) as f64;
    (max_abs, 10.0 * (1.0 / mse).log10())
}

/// Peak resident memory of another process (Linux `VmHWM`), in MiB.
fn peak_rss_of_mib(pid: u32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

fn bench_video(args: VideoBench) -> Result<()> {
    use gagavatar_video::read::{find_ffmpeg, DecoderChoice, ReadOptions, VideoReader};
    use std::process::Command;

    let tools = find_ffmpeg(None)
        .context("bench video makes its clips with ffmpeg, which is not on PATH")?;
    let (dir, _cleanup) = match &args.dir {
        Some(d) => {
            std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
            (d.clone(), None)
        }
        None => {
            let d =
                std::env::temp_dir().join(format!("gagavatar-bench-video-{}", std::process::id()));
            std::fs::create_dir_all(&d)?;
            (d.clone(), Some(RemoveDir(d)))
        }
    };
    let n = args.frames.max(1);
    let make = |name: &str, size: &str, extra: &[&str]| -> Result<std::path::PathBuf> {
        let out = dir.join(name);
        if out.exists() {
            return Ok(out);
        }
        eprintln!("making {} ({size}, {n} frames) with ffmpeg", out.display());
        let st = Command::new(&tools.ffmpeg)
            .args([
                "-hide_banner",
                "-loglevel",
                "error",
                "-y",
                "-f",
                "lavfi",
                "-i",
            ])
            // Temporal noise stands in for camera grain, so the bitrate is a camera's, not a
            // test pattern's.
            .arg(format!("testsrc2=size={size}:rate=30,noise=alls=8:allf=t"))
            .args(["-frames:v", &n.to_string()])
            .args(extra)
            .arg(&out)
            .status()?;
        anyhow::ensure!(st.success(), "ffmpeg could not make {}", out.display());
        Ok(out)
    };
    // Phone-like bitrates: 16 Mbit/s at 1080p30, 2 Mbit/s (about the same bits per pixel) at
    // 512x512.
    let x264 = |profile: &'static str, rate: &'static str| {
        [
            "-c:v",
            "libx264",
            "-preset",
            "veryfast",
            "-profile:v",
            profile,
            "-b:v",
            rate,
            "-maxrate",
            rate,
            "-bufsize",
            rate,
            "-pix_fmt",
            "yuv420p",
        ]
    };
    let clips = [
        (
            "512x512 H.264 High, ffmpeg",
            make("high_512.mp4", "512x512", &x264("high", "2M"))?,
            DecoderChoice::Ffmpeg,
        ),
        (
            "1920x1080 H.264 High, ffmpeg",
            make("high_1080.mp4", "1920x1080", &x264("high", "16M"))?,
            DecoderChoice::Ffmpeg,
        ),
        (
            "512x512 H.264 Baseline, OpenH264",
            make("base_512.mp4", "512x512", &x264("baseline", "2M"))?,
            DecoderChoice::OpenH264,
        ),
        (
            "1920x1080 H.264 Baseline, OpenH264",
            make("base_1080.mp4", "1920x1080", &x264("baseline", "16M"))?,
            DecoderChoice::OpenH264,
        ),
    ];
    println!(
        "peak RSS of this process before reading: {:.0} MiB",
        peak_rss_mib().unwrap_or(f64::NAN)
    );
    println!(
        "video decoding, {} threads for ffmpeg ({} {}.{}), {n} frames per clip, median of {} runs:",
        args.threads,
        tools.ffmpeg.display(),
        tools.version.0,
        tools.version.1,
        args.runs.max(1)
    );
    for (label, path, decoder) in &clips {
        let bytes = std::fs::metadata(path)?.len();
        let opts = ReadOptions {
            threads: Some(args.threads),
            decoder: *decoder,
            ..ReadOptions::default()
        };
        let mut rates = Vec::new();
        let mut cpu_self = Vec::new();
        let mut cpu_child = Vec::new();
        let mut child_peak = 0f64;
        for _ in 0..args.runs.max(1) {
            let (s0, c0) = (cpu_seconds(false), cpu_seconds(true));
            let t0 = Instant::now();
            let mut reader = VideoReader::open(path, &opts)?;
            let mut count = 0usize;
            let mut checksum = 0u64;
            while let Some(frame) = reader.next() {
                let frame = frame?;
                // Touch the pixels so nothing is optimised away.
                checksum = checksum.wrapping_add(u64::from(frame.rgb.as_raw()[count % 97]));
                count += 1;
                if let Some(pid) = reader.ffmpeg_pid() {
                    if let Some(mib) = peak_rss_of_mib(pid) {
                        child_peak = child_peak.max(mib);
                    }
                }
            }
            drop(reader);
            let dt = t0.elapsed().as_secs_f64();
            anyhow::ensure!(count == n, "{label}: read {count} of {n} frames");
            cpu_self.push(1e3 * (cpu_seconds(false) - s0) / count as f64);
            cpu_child.push(1e3 * (cpu_seconds(true) - c0) / count as f64);
            std::hint::black_box(checksum);
            rates.push(count as f64 / dt);
        }
        let mbps = bytes as f64 * 8.0 / (n as f64 / 30.0) / 1e6;
        let ours = peak_rss_mib().unwrap_or(f64::NAN);
        let child = if child_peak > 0.0 {
            format!(
                "; peak RSS: ffmpeg {child_peak:.0} MiB + this process {ours:.0} MiB = {:.0} MiB",
                child_peak + ours
            )
        } else {
            format!("; peak RSS (this process) {ours:.0} MiB")
        };
        let cpu = median(&mut cpu_self) + median(&mut cpu_child);
        println!(
            "  {label:<36} {:>7.1} frames/s (min {:.1}, max {:.1}), {mbps:.1} Mbit/s; CPU per frame \
             {cpu:.2} ms (reader {:.2} ms, ffmpeg {:.2} ms){child}",
            median(&mut rates.clone()),
            rates.iter().cloned().fold(f64::INFINITY, f64::min),
            rates.iter().cloned().fold(0.0, f64::max),
            median(&mut cpu_self),
            median(&mut cpu_child),
        );
    }
    println!(
        "  load average {} on {} cores (other work slows the wall-clock rates, not the CPU per frame)",
        load_average(),
        num_cpus()
    );
    Ok(())
}

/// User + system CPU seconds of this process, or of its finished (waited-for) children.
fn cpu_seconds(children: bool) -> f64 {
    #[cfg(unix)]
    {
        // SAFETY: getrusage only writes the struct it is given.
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        let who = if children {
            libc::RUSAGE_CHILDREN
        } else {
            libc::RUSAGE_SELF
        };
        if unsafe { libc::getrusage(who, &mut ru) } == 0 {
            let t = |tv: libc::timeval| tv.tv_sec as f64 + tv.tv_usec as f64 * 1e-6;
            return t(ru.ru_utime) + t(ru.ru_stime);
        }
    }
    let _ = children;
    0.0
}

/// Removes a folder when dropped.
struct RemoveDir(std::path::PathBuf);

impl Drop for RemoveDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn face_frames(args: &FaceBench) -> Result<Vec<image::RgbImage>> {
    let mut paths = Vec::new();
    for p in &args.frames {
        if p.is_dir() {
            let mut v: Vec<_> = std::fs::read_dir(p)
                .with_context(|| format!("reading {}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_file())
                .collect();
            v.sort();
            paths.extend(v);
        } else {
            paths.push(p.clone());
        }
    }
    paths.truncate(args.max_frames);
    anyhow::ensure!(!paths.is_empty(), "no frames given");
    let opts = gagavatar_formats::image::DecodeOptions::default();
    paths
        .iter()
        .map(|p| Ok(gagavatar_formats::image::read_image(p, &opts)?.rgb))
        .collect()
}

/// Median and minimum of per-frame times, in ms.
fn stats(v: &mut [f64]) -> (f64, f64) {
    let m = median(v);
    (m, v[0])
}

fn bench_face(args: FaceBench) -> Result<()> {
    use gagavatar_face::detection::{DetectorModel, FaceDetector};
    use gagavatar_face::face_mesh::{FaceMesh, FaceTracker};
    use gagavatar_face::matte::SelfieSegmenter;

    let threads = args.threads.unwrap_or_else(num_cpus);
    gagavatar_face::pool::set_threads(threads);
    let frames = face_frames(&args)?;
    let runs = args.runs.max(2);
    let (fw, fh) = (frames[0].width(), frames[0].height());
    let mesh = FaceMesh::new()?;
    let full = FaceDetector::new(DetectorModel::FullRange)?;
    let seg = SelfieSegmenter::new()?;
    let total = (runs * frames.len() * 6) as u64;
    let pb = ProgressBar::new(total);
    pb.set_style(ProgressStyle::with_template(
        "{msg} [{bar:30}] {pos}/{len} ETA {eta}",
    )?);

    // Each measurement: `runs` passes over the frames, the first one untimed.
    let measure =
        |name: &str, f: &mut dyn FnMut(&image::RgbImage) -> Result<()>| -> Result<Vec<f64>> {
            pb.set_message(name.to_owned());
            let mut times = Vec::new();
            for run in 0..runs {
                for frame in &frames {
                    let frame = frame.clone();
                    let t0 = Instant::now();
                    f(&frame)?;
                    let dt = t0.elapsed().as_secs_f64() * 1e3;
                    if run > 0 {
                        times.push(dt);
                    }
                    pb.inc(1);
                }
            }
            Ok(times)
        };

    let mut tracker = FaceTracker::with_models(mesh.clone());
    let mut detected = 0usize;
    let mut found = 0usize;
    let mut tracking = measure("tracking", &mut |f| {
        let was = tracker.is_tracking();
        let face = tracker.process(f)?;
        detected += !was as usize;
        found += face.is_some() as usize;
        Ok(())
    })?;
    let mut short = measure("short range", &mut |f| {
        mesh.detector.detect(f)?;
        Ok(())
    })?;
    let mut full_t = measure("full range", &mut |f| {
        full.detect(f)?;
        Ok(())
    })?;
    let mut stat = measure("static mesh", &mut |f| {
        mesh.process(f, 1)?;
        Ok(())
    })?;
    let mut matte = measure("matte 256", &mut |f| {
        seg.mask256(f)?;
        Ok(())
    })?;
    let mut matte_full = measure("matte", &mut |f| {
        seg.matte(f)?;
        Ok(())
    })?;
    pb.finish_and_clear();
    let rows = [
        (
            "tracking frame (478 landmarks, detector skipped while tracked)",
            &mut tracking,
        ),
        ("detection, short range (128)", &mut short),
        ("detection, full range (192)", &mut full_t),
        ("photo: short-range detection + 478 landmarks", &mut stat),
        ("matte 256x256 (sampling + network)", &mut matte),
        ("matte at frame size (+ resize back)", &mut matte_full),
    ];
    println!(
        "face, {} frames of {fw}x{fh}, {threads} threads, {} timed passes:",
        frames.len(),
        runs - 1
    );
    for (name, v) in rows {
        let (m, lo) = stats(v);
        println!("  {name}: median {m:.2} ms (min {lo:.2})");
    }
    println!(
        "  tracking: face in {found} of {} frames, detector ran on {detected}",
        runs * frames.len()
    );
    Ok(())
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
}

fn bench_eval(a: EvalBench) -> Result<()> {
    let out = std::env::temp_dir().join(format!("gagavatar-bench-eval-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let args = crate::cmd_eval::EvalArgs {
        ground_truth_as_result: a.ckpt.is_none(),
        source_as_result: false,
        ckpt: a.ckpt,
        data: a.data,
        split: a.split,
        preset: None,
        flame: a.flame,
        mode: Some("self".into()),
        out: Some(out.clone()),
        pairs: Some(a.pairs),
        seed: 0,
        batch: a.batch,
        limit: None,
        json: None,
        grid: None,
        lpips: a.lpips,
        arcface: None,
        threads: Some(a.threads),
    };
    let load_before = load_average();
    let cpu0 = cpu_seconds(false);
    let result = crate::cmd_eval::run_protocol(&args, &out);
    let cpu = cpu_seconds(false) - cpu0;
    let load_after = load_average();
    let _ = std::fs::remove_dir_all(&out);
    let o = result?;
    println!(
        "eval protocol, {} self pairs, {} threads{}: metrics {:.1} ms a pair wall ({:.2} s in \
         all), rendering {:.2} s; CPU time of the whole run {:.1} ms a pair (all threads, loading \
         included); load average before {load_before}, after {load_after}",
        o.scored,
        a.threads,
        if args.lpips.is_some() {
            ", with LPIPS"
        } else {
            ", no LPIPS"
        },
        o.metrics_ms_per_pair(),
        o.metrics.as_secs_f64(),
        o.render.as_secs_f64(),
        cpu * 1e3 / o.scored.max(1) as f64,
    );
    Ok(())
}

/// Frame `i` of `n` of the bench clip: `photo` through a window that zooms between 70% and 90%
/// of its side and drifts around its centre, resized to 512x512.
fn bench_clip_frame(photo: &image::RgbImage, i: usize, n: usize) -> image::RgbImage {
    let t = i as f64 / n.max(1) as f64;
    let tau = std::f64::consts::TAU;
    let side = photo.width().min(photo.height()) as f64;
    let s = side * (0.8 + 0.1 * (tau * t).sin());
    let cx = photo.width() as f64 / 2.0 + 0.08 * side * (tau * t).cos();
    let cy = photo.height() as f64 / 2.0 + 0.05 * side * (2.0 * tau * t).sin();
    let x0 = (cx - s / 2.0).clamp(0.0, photo.width() as f64 - s).round() as u32;
    let y0 = (cy - s / 2.0).clamp(0.0, photo.height() as f64 - s).round() as u32;
    let view = image::imageops::crop_imm(photo, x0, y0, s as u32, s as u32).to_image();
    image::imageops::resize(&view, 512, 512, image::imageops::FilterType::Triangle)
}

fn bench_track(args: TrackBench) -> Result<()> {
    use crate::tracking::{median as med, tracker_for, Bars};
    use gagavatar_video::{VideoOptions, VideoWriter};
    if args.runs == 0 || args.frames == 0 || args.threads == 0 {
        anyhow::bail!("--runs, --frames and --threads must be at least 1");
    }
    crate::cmd_track::set_threads(Some(args.threads));
    let photo_path = match &args.photo {
        Some(p) => p.clone(),
        None => crate::cmd_demo::find_assets(None)?.join("astronaut.jpg"),
    };
    let opts = gagavatar_formats::image::DecodeOptions {
        min_side: 16,
        fit_within: Some(4096),
    };
    let photo = gagavatar_formats::image::read_image(&photo_path, &opts)?.rgb;
    let tmp = std::env::temp_dir().join(format!("gagavatar_bench_track_{}", std::process::id()));
    std::fs::create_dir_all(&tmp)?;
    let _cleanup = RemoveDir(tmp.clone());
    let clip = tmp.join("clip.mp4");
    let vopts = VideoOptions {
        fps: 25.0,
        watermark: false,
    };
    let mut w = VideoWriter::create(&clip, 512, 512, vopts)?;
    for i in 0..args.frames {
        w.push_rgb(bench_clip_frame(&photo, i, args.frames).as_raw())?;
    }
    w.finish()?;

    let t0 = Instant::now();
    let tracker = tracker_for(&args.flame)?;
    let load = t0.elapsed().as_secs_f64();
    println!(
        "track bench: {} threads, {} frames 512x512 H.264 from {}, models loaded in {:.0} ms",
        args.threads,
        args.frames,
        photo_path.display(),
        1e3 * load
    );
    let mut fps = Vec::new();
    let mut stages: Vec<[f64; 2]> = Vec::new();
    for r in 0..args.runs {
        let out = tmp.join(format!("video_{r}"));
        let t = Instant::now();
        let c0 = cpu_seconds(false) + cpu_seconds(true);
        let s = tracker.track_video_file(&clip, &out, None, &Bars::default())?;
        let secs = t.elapsed().as_secs_f64();
        let cpu = cpu_seconds(false) + cpu_seconds(true) - c0;
        fps.push(s.frames as f64 / secs);
        stages.push(s.seconds.map(|x| 1e3 * x / s.frames as f64));
        println!(
            "  video run {r}: {:.1} frames/s ({:.1} ms/frame: decode + landmarks {:.1}, fit while \
             decoding again + cropping + matting + JPEG + writing {:.1}); CPU {:.1} ms/frame in \
             all, {:.1} of it the fit's thread; {} frames without a face",
            s.frames as f64 / secs,
            1e3 * secs / s.frames as f64,
            stages[r][0],
            stages[r][1],
            1e3 * cpu / s.frames as f64,
            1e3 * s.fit_cpu_seconds / s.frames as f64,
            s.no_face
        );
        let _ = std::fs::remove_dir_all(&out);
    }
    let mut photo_ms = Vec::new();
    for r in 0..args.runs + 1 {
        let out = tmp.join(format!("photo_{r}"));
        let t = Instant::now();
        tracker.track_photo_file(&photo_path, &out, None)?;
        let ms = 1e3 * t.elapsed().as_secs_f64();
        // The first run warms caches and thread pools; it is reported but not in the median.
        if r > 0 {
            photo_ms.push(ms);
        }
        println!("  photo run {r}: {ms:.0} ms");
        let _ = std::fs::remove_dir_all(&out);
    }
    println!(
        "video tracking: {:.1} frames/s (median of {}), photo: {:.0} ms (median of {}), {} threads; \
         load average {}",
        med(&fps),
        fps.len(),
        med(&photo_ms),
        photo_ms.len(),
        args.threads,
        load_average()
    );
    Ok(())
}
