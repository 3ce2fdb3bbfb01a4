//! `gagavatar bench serve`: the server's load test (`gagavatar_serve::loadtest`), batched and
//! one request at a time, in one run.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Result};
use clap::Args;
use gagavatar_avatar::{Engine, EngineConfig, FlameSource};
use gagavatar_serve::loadtest::{run, LoadConfig};
use gagavatar_serve::BatchConfig;

#[derive(Debug, Args)]
pub struct ServeBench {
    /// Weights (default: the shipped demo model).
    #[arg(long)]
    pub ckpt: Option<PathBuf>,
    /// FLAME asset (default: the one the weights name).
    #[arg(long)]
    pub flame: Option<PathBuf>,
    #[arg(long, default_value_t = 32)]
    pub clients: usize,
    /// Render requests per client.
    #[arg(long, default_value_t = 8)]
    pub requests: usize,
    /// The batch limits to compare (1: one request at a time).
    #[arg(long, value_delimiter = ',', default_value = "1,8")]
    pub max_batch: Vec<usize>,
    /// How long a batch waits for company, in milliseconds.
    #[arg(long, default_value_t = 4)]
    pub window_ms: u64,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

pub fn bench_serve(a: ServeBench) -> Result<()> {
    if a.clients == 0 || a.requests == 0 || a.max_batch.contains(&0) {
        bail!("--clients, --requests and every --max-batch must be at least 1");
    }
    crate::cmd_track::set_threads(Some(a.threads));
    let assets = crate::cmd_demo::find_assets(None)?;
    let weights = a
        .ckpt
        .clone()
        .unwrap_or_else(|| assets.join("weights.safetensors"));
    let mut cfg = EngineConfig::new(&weights);
    if let Some(f) = &a.flame {
        cfg.flame = FlameSource::from_arg(f);
    }
    let engine = Arc::new(Engine::open(&cfg).map_err(crate::cmd_model::with_flag_hints)?);
    let photo = std::fs::read(assets.join("astronaut.jpg"))?;
    let mirrored = {
        let img = image::load_from_memory(&photo)?.to_rgb8();
        let mut b = Vec::new();
        image::imageops::flip_horizontal(&img)
            .write_to(&mut std::io::Cursor::new(&mut b), image::ImageFormat::Png)?;
        b
    };
    println!(
        "serve bench: {} ({} px), {} threads, {} clients x {} render requests, 2 avatars, loopback",
        weights.display(),
        engine.image_size(),
        a.threads,
        a.clients,
        a.requests
    );
    for &max_batch in &a.max_batch {
        let load = LoadConfig {
            clients: a.clients,
            requests_per_client: a.requests,
            batch: BatchConfig {
                max_batch,
                window: Duration::from_millis(if max_batch == 1 { 0 } else { a.window_ms }),
                max_queue: 1024,
            },
        };
        let r = run(engine.clone(), &[photo.clone(), mirrored.clone()], &load)?;
        println!(
            "  max batch {max_batch:>2}: {:.1} frames/s, p50 {:.0} ms, p99 {:.0} ms, {} frames in {} renderer \
             calls ({:.1} a call), {} wrong answers; upload to first frame {:.0} ms; {:.1} MB per cached avatar",
            r.frames_per_second,
            r.p50_ms,
            r.p99_ms,
            r.frames,
            r.batches,
            r.frames as f64 / r.batches.max(1) as f64,
            r.wrong,
            r.first_frame_ms,
            r.bytes_per_avatar as f64 / (1 << 20) as f64
        );
        if r.wrong > 0 {
            bail!("{} of {} answers were wrong", r.wrong, r.frames);
        }
    }
    println!(
        "peak memory {:.0} MiB",
        crate::procstat::peak_rss_mib().unwrap_or(f64::NAN)
    );
    Ok(())
}
