//! `gagavatar serve`: one process serving a web page and a versioned HTTP API over the pipeline
//! library (`gagavatar-avatar`); no second copy of the pipeline.
//!
//! * [`api`]: the routes (`/v1/...`, `/metrics`, the page);
//! * [`batcher`]: concurrent render requests gathered into batched renderer calls;
//! * [`store`]: avatars in memory under a byte budget, least recently used dropped first;
//! * [`jobs`]: reenact jobs (track an uploaded video, render every frame, mp4 out);
//! * [`metrics`]: the Prometheus text; [`page`]: the page, built into the binary.
//!
//! Compute runs on blocking threads (tracking, reconstruction) and on the batcher's render
//! thread; the async side only moves bytes. Nothing a client sends is used as a path: uploads
//! are stored under names the server makes (content hashes, random job ids).

pub mod api;
pub mod batcher;
pub mod client;
pub mod error;
pub mod jobs;
pub mod loadtest;
pub mod metrics;
pub mod page;
pub mod store;

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicUsize;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use gagavatar_avatar::Engine;

pub use api::router;
pub use batcher::BatchConfig;
pub use error::ApiError;

/// What the server allows and how it batches.
#[derive(Debug, Clone)]
pub struct ServeConfig {
    /// A bearer token every API call must carry (`Authorization: Bearer T`, or `?token=T` on
    /// download links); `None`: no token.
    pub token: Option<String>,
    pub batch: BatchConfig,
    /// Bytes of avatars kept in memory; beyond it the least recently used go.
    pub avatar_budget: usize,
    /// Largest photo upload, bytes.
    pub max_photo_bytes: usize,
    /// Largest video upload, bytes.
    pub max_video_bytes: usize,
    /// Largest photo, width x height.
    pub max_pixels: u64,
    /// Longest video a reenact job takes, frames.
    pub max_video_frames: usize,
    /// Reenact jobs running at once; more get 429.
    pub max_jobs: usize,
    /// Photos being tracked or waiting for it; more get 503.
    pub max_pending_avatars: usize,
    /// Live (webcam) sessions at once; more get 429.
    pub max_live: usize,
    /// What the health answer says about where frames are rendered.
    pub device: String,
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            token: None,
            batch: BatchConfig {
                max_batch: 8,
                window: Duration::from_millis(4),
                max_queue: 64,
            },
            avatar_budget: 1 << 30,
            max_photo_bytes: 20 << 20,
            max_video_bytes: 200 << 20,
            max_pixels: 40_000_000,
            max_video_frames: 1800,
            max_jobs: 2,
            max_pending_avatars: 4,
            max_live: 4,
            device: "cpu".into(),
        }
    }
}

/// Everything the handlers share.
pub struct AppState {
    pub engine: Arc<Engine>,
    pub cfg: ServeConfig,
    pub store: store::AvatarStore,
    pub batcher: Arc<batcher::Batcher>,
    pub metrics: Arc<metrics::Metrics>,
    pub jobs: Mutex<HashMap<String, Arc<jobs::Job>>>,
    /// Photos being tracked or waiting to be.
    pub pending_avatars: AtomicUsize,
    /// Live sessions open.
    pub live_sessions: AtomicUsize,
    /// One reconstruction at a time (they use every core).
    pub compute: tokio::sync::Semaphore,
    /// Uploads, job results and exports, removed with the state.
    pub scratch: PathBuf,
}

impl AppState {
    /// Starts the batcher and makes the scratch folder.
    pub fn new(engine: Arc<Engine>, cfg: ServeConfig) -> std::io::Result<Arc<Self>> {
        let metrics = Arc::new(metrics::Metrics::default());
        let scratch = std::env::temp_dir().join(format!(
            "gagavatar-serve-{}-{:08x}",
            std::process::id(),
            api::random_u64() as u32
        ));
        std::fs::create_dir_all(scratch.join("uploads"))?;
        std::fs::create_dir_all(scratch.join("jobs"))?;
        std::fs::create_dir_all(scratch.join("exports"))?;
        Ok(Arc::new(AppState {
            batcher: Arc::new(batcher::Batcher::start(cfg.batch, metrics.clone())),
            store: store::AvatarStore::new(cfg.avatar_budget),
            engine,
            cfg,
            metrics,
            jobs: Mutex::new(HashMap::new()),
            pending_avatars: AtomicUsize::new(0),
            live_sessions: AtomicUsize::new(0),
            compute: tokio::sync::Semaphore::new(1),
            scratch,
        }))
    }
}

impl Drop for AppState {
    fn drop(&mut self) {
        for j in self.jobs.lock().unwrap_or_else(|p| p.into_inner()).values() {
            j.cancel.cancel();
        }
        let _ = std::fs::remove_dir_all(&self.scratch);
    }
}

/// Serves `state` on `listener` until `shutdown` completes.
pub async fn serve(
    listener: tokio::net::TcpListener,
    state: Arc<AppState>,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    axum::serve(listener, router(state))
        .with_graceful_shutdown(shutdown)
        .await
}

/// A server on a loopback port in its own thread and runtime (tests, the load benchmark);
/// stopped and joined when dropped.
pub struct LocalServer {
    pub addr: std::net::SocketAddr,
    pub state: Arc<AppState>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<std::io::Result<()>>>,
}

impl LocalServer {
    pub fn start(state: Arc<AppState>) -> std::io::Result<LocalServer> {
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let (atx, arx) = std::sync::mpsc::channel();
        let st = state.clone();
        let thread = std::thread::spawn(move || -> std::io::Result<()> {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()?;
            rt.block_on(async move {
                let l = match tokio::net::TcpListener::bind("127.0.0.1:0").await {
                    Ok(l) => l,
                    Err(e) => {
                        let _ = atx.send(Err(e));
                        return Ok(());
                    }
                };
                let _ = atx.send(l.local_addr());
                serve(l, st, async {
                    let _ = rx.await;
                })
                .await
            })
        });
        let addr = arx
            .recv()
            .map_err(|_| std::io::Error::other("the server thread stopped before it listened"))??;
        Ok(LocalServer {
            addr,
            state,
            stop: Some(tx),
            thread: Some(thread),
        })
    }
}

impl Drop for LocalServer {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
