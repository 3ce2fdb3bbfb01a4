//! `gagavatar serve`: the web app and the HTTP API (`crates/serve`) over one loaded engine.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use gagavatar_avatar::{Engine, EngineConfig, FlameSource};
use gagavatar_serve::{AppState, BatchConfig, ServeConfig};

#[derive(Debug, Args)]
#[command(
    after_help = "Serves a page (drop a photo, see the avatar, drag to orbit, move the \
expression, jaw and eye sliders, reenact an uploaded video, download the .ply) and the versioned \
HTTP API it uses (README: \"Serving\"). Binds to loopback unless --host says otherwise; with \
--token every API call needs `Authorization: Bearer TOKEN` (the printed URL carries it for the \
page).\n\n\
Examples:\n  gagavatar serve                      # the shipped demo model on http://127.0.0.1:8000/\n  \
gagavatar serve --ckpt GAGAvatar.pt --flame FLAME_with_eye.pt --port 8080 --token s3cret"
)]
pub struct ServeArgs {
    /// Port to listen on (0: any free port).
    #[arg(long, default_value_t = 8000)]
    pub port: u16,
    /// Address to bind; 0.0.0.0 makes the server reachable from other machines.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: String,
    /// Weights (`GAGAvatar.pt` or safetensors); default: the shipped demo model.
    #[arg(long)]
    pub ckpt: Option<PathBuf>,
    /// FLAME asset; default: the one the weights name (`synthetic` for the demo model).
    #[arg(long)]
    pub flame: Option<PathBuf>,
    /// A token API calls must carry (`Authorization: Bearer TOKEN`).
    #[arg(long)]
    pub token: Option<String>,
    /// Frames gathered into one renderer call at most (1: no batching).
    #[arg(long, default_value_t = 8)]
    pub max_batch: usize,
    /// How long a render request waits for others to batch with, in milliseconds.
    #[arg(long, default_value_t = 4)]
    pub batch_window_ms: u64,
    /// Render requests waiting at most; more are answered 503 with Retry-After.
    #[arg(long, default_value_t = 64)]
    pub max_queue: usize,
    /// Memory for avatars kept between requests, in MB (least recently used dropped first).
    #[arg(long, default_value_t = 1024)]
    pub avatar_memory_mb: usize,
    /// Largest photo upload in MB.
    #[arg(long, default_value_t = 20)]
    pub max_photo_mb: usize,
    /// Largest video upload in MB.
    #[arg(long, default_value_t = 200)]
    pub max_video_mb: usize,
    /// Longest video a reenact job takes, in frames.
    #[arg(long, default_value_t = 1800)]
    pub max_video_frames: usize,
    /// Worker threads for tracking and rendering (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Arithmetic of the model's products: f32 (the release's) or bf16 (AVX512-BF16 CPUs).
    #[arg(long, default_value = "f32")]
    pub precision: gagavatar_ops::Precision,
}

pub fn run(a: ServeArgs) -> Result<()> {
    if a.max_batch == 0 || a.max_queue == 0 {
        bail!("--max-batch and --max-queue must be at least 1");
    }
    crate::cmd_track::set_threads(a.threads);
    let weights = match &a.ckpt {
        Some(p) => p.clone(),
        None => crate::cmd_demo::find_assets(None)?.join("weights.safetensors"),
    };
    let mut cfg = EngineConfig::new(&weights);
    if let Some(f) = &a.flame {
        cfg.flame = FlameSource::from_arg(f);
    }
    cfg.precision = a.precision;
    let engine = Engine::open(&cfg).map_err(crate::cmd_model::with_flag_hints)?;
    for w in engine.warnings() {
        eprintln!("warning: {w}");
    }
    let serve_cfg = ServeConfig {
        token: a.token.clone(),
        batch: BatchConfig {
            max_batch: a.max_batch,
            window: Duration::from_millis(a.batch_window_ms),
            max_queue: a.max_queue,
        },
        avatar_budget: a.avatar_memory_mb << 20,
        max_photo_bytes: a.max_photo_mb << 20,
        max_video_bytes: a.max_video_mb << 20,
        max_video_frames: a.max_video_frames,
        ..ServeConfig::default()
    };
    let state = AppState::new(Arc::new(engine), serve_cfg).context("starting the server")?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the server's runtime")?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind((a.host.as_str(), a.port))
            .await
            .with_context(|| format!("cannot listen on {}:{}", a.host, a.port))?;
        let addr = listener.local_addr()?;
        let host = if addr.ip().is_unspecified() {
            "127.0.0.1".to_string()
        } else {
            addr.ip().to_string()
        };
        let fragment = a
            .token
            .as_ref()
            .map(|t| format!("#token={t}"))
            .unwrap_or_default();
        eprintln!(
            "serving {} on http://{host}:{}/{fragment} (Ctrl-C to stop)",
            weights.display(),
            addr.port()
        );
        // The CLI's Ctrl-C handler sets a flag; the server stops when it is set.
        let shutdown = async {
            while !crate::interrupted() {
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        };
        gagavatar_serve::serve(listener, state, shutdown)
            .await
            .context("serving")
    })
}
