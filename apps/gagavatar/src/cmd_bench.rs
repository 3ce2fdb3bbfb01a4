//! `gagavatar bench ...`: timings of the hot paths on this machine.

use anyhow::{Context, Result};
use candle_core::{Device, Tensor, Var};
use clap::{Args, Subcommand, ValueEnum};
use gagavatar_splat::testscene::{avatar_scene, Regime};
use gagavatar_splat::{splat, Gaussians};
use indicatif::{ProgressBar, ProgressStyle};
use std::time::Instant;

#[derive(Debug, Subcommand)]
pub enum BenchCmd {
    /// Splatting forward and backward on the avatar-like scene (2 lifted 296x296 planes + 5023
    /// head points, camera at distance 9, focal 12, 512x512, 32 channels).
    #[command(
        after_help = "Example:\n  gagavatar bench splat --regime small --runs 20 --threads 2"
    )]
    Splat(SplatBench),
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
}

pub fn run(cmd: BenchCmd) -> Result<()> {
    match cmd {
        BenchCmd::Splat(args) => bench_splat(args),
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Peak resident memory of this process (Linux `VmHWM`), in MiB.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

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
    for &regime in regimes {
        let (scene, cam) = avatar_scene(args.plane, 5023, args.channels, regime, 1);
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
             forward median {:.1} ms, backward median {:.1} ms, tile pairs {pairs}, peak RSS {:.0} MiB",
            scene.len(),
            cam.width,
            cam.height,
            args.channels,
            median(&mut fwd),
            median(&mut bwd),
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
