//! Gathering concurrent render requests into batched renderer calls: a worker thread takes the
//! first waiting request, waits a short, bounded time for more (for any avatar of the engine),
//! and renders them all with one `render_many` call. Requests whose client has gone (their
//! answer channel closed) are dropped before rendering.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use gagavatar_avatar::{render_many, Avatar, Camera, FrameCodes};
use tokio::sync::oneshot;

use crate::metrics::Metrics;

/// One frame to render, and where its RGB bytes (or the error's line) go.
pub struct RenderJob {
    pub avatar: Arc<Avatar>,
    pub codes: FrameCodes,
    pub camera: Camera,
    pub reply: oneshot::Sender<Result<Vec<u8>, String>>,
    pub queued: Instant,
}

/// How requests are gathered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchConfig {
    /// Frames in one renderer call at most (1: no batching).
    pub max_batch: usize,
    /// How long the first request of a batch waits for company.
    pub window: Duration,
    /// Waiting requests at most; more are refused (503) rather than queued.
    pub max_queue: usize,
}

struct Queue {
    jobs: VecDeque<RenderJob>,
    stop: bool,
}

/// The queue and its worker thread (stopped and joined on drop).
pub struct Batcher {
    shared: Arc<(Mutex<Queue>, Condvar)>,
    cfg: BatchConfig,
    metrics: Arc<Metrics>,
    worker: Option<std::thread::JoinHandle<()>>,
}

/// The queue is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueFull;

impl Batcher {
    pub fn start(cfg: BatchConfig, metrics: Arc<Metrics>) -> Self {
        let shared = Arc::new((
            Mutex::new(Queue {
                jobs: VecDeque::new(),
                stop: false,
            }),
            Condvar::new(),
        ));
        let worker = {
            let shared = shared.clone();
            let metrics = metrics.clone();
            std::thread::Builder::new()
                .name("gagavatar-render".into())
                .spawn(move || work(&shared, cfg, &metrics))
                .ok()
        };
        Batcher {
            shared,
            cfg,
            metrics,
            worker,
        }
    }

    /// Queues a frame; `bypass_limit` for a reenact job's own frames (bounded by the job).
    pub fn submit(&self, job: RenderJob, bypass_limit: bool) -> Result<(), QueueFull> {
        let (lock, cv) = &*self.shared;
        let mut q = lock.lock().unwrap_or_else(|p| p.into_inner());
        if !bypass_limit && q.jobs.len() >= self.cfg.max_queue {
            return Err(QueueFull);
        }
        q.jobs.push_back(job);
        self.metrics.set_queue_depth(q.jobs.len());
        cv.notify_one();
        Ok(())
    }

    pub fn queue_depth(&self) -> usize {
        let (lock, _) = &*self.shared;
        lock.lock().unwrap_or_else(|p| p.into_inner()).jobs.len()
    }

    pub fn config(&self) -> BatchConfig {
        self.cfg
    }
}

impl Drop for Batcher {
    fn drop(&mut self) {
        let (lock, cv) = &*self.shared;
        lock.lock().unwrap_or_else(|p| p.into_inner()).stop = true;
        cv.notify_all();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

fn work(shared: &(Mutex<Queue>, Condvar), cfg: BatchConfig, metrics: &Metrics) {
    let (lock, cv) = shared;
    loop {
        let batch: Vec<RenderJob> = {
            let mut q = lock.lock().unwrap_or_else(|p| p.into_inner());
            while q.jobs.is_empty() && !q.stop {
                q = cv.wait(q).unwrap_or_else(|p| p.into_inner());
            }
            if q.stop {
                return;
            }
            // The first request waits at most `window` for others to join it.
            let deadline = Instant::now() + cfg.window;
            while q.jobs.len() < cfg.max_batch && !q.stop {
                let now = Instant::now();
                if now >= deadline {
                    break;
                }
                let (g, _) = cv
                    .wait_timeout(q, deadline - now)
                    .unwrap_or_else(|p| p.into_inner());
                q = g;
            }
            let n = q.jobs.len().min(cfg.max_batch.max(1));
            let batch = q.jobs.drain(..n).collect();
            metrics.set_queue_depth(q.jobs.len());
            batch
        };
        // A client that went away cancels its frame.
        let (live, gone): (Vec<RenderJob>, Vec<RenderJob>) =
            batch.into_iter().partition(|j| !j.reply.is_closed());
        metrics.add_cancelled(gone.len());
        if live.is_empty() {
            continue;
        }
        render(live, metrics);
    }
}

fn render(jobs: Vec<RenderJob>, metrics: &Metrics) {
    let t0 = Instant::now();
    // One entry per distinct avatar, frames pointing at them.
    let mut avatars: Vec<&Arc<Avatar>> = Vec::new();
    let mut frames = Vec::with_capacity(jobs.len());
    for j in &jobs {
        let k = match avatars.iter().position(|a| Arc::ptr_eq(a, &j.avatar)) {
            Some(k) => k,
            None => {
                avatars.push(&j.avatar);
                avatars.len() - 1
            }
        };
        frames.push((k, j.codes.clone(), j.camera));
    }
    let refs: Vec<&Avatar> = avatars.iter().map(|a| a.as_ref()).collect();
    let result = render_many(&refs, &frames);
    let n = jobs.len();
    metrics.add_batch(n, t0.elapsed());
    match result {
        Ok(rgb) => {
            for (j, frame) in jobs.into_iter().zip(rgb) {
                metrics.add_latency(j.queued.elapsed());
                let _ = j.reply.send(Ok(frame));
            }
        }
        Err(e) => {
            let line = crate::error::one_line(&e);
            for j in jobs {
                let _ = j.reply.send(Err(line.clone()));
            }
        }
    }
}
