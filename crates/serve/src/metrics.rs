//! Counters for `/metrics` (Prometheus text format): queue depth, batch sizes, render latency
//! quantiles, cached avatars, jobs, answers by status class.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Duration;

/// Latencies kept for the quantiles (the most recent ones).
const LATENCY_WINDOW: usize = 4096;
/// Batch-size histogram buckets (upper bounds).
const BATCH_BUCKETS: [usize; 6] = [1, 2, 4, 8, 16, 32];

#[derive(Default)]
pub struct Metrics {
    queue_depth: AtomicU64,
    batches: AtomicU64,
    frames: AtomicU64,
    cancelled: AtomicU64,
    batch_buckets: [AtomicU64; BATCH_BUCKETS.len()],
    render_seconds_micros: AtomicU64,
    latencies: Mutex<VecDeque<f64>>,
    answers: [AtomicU64; 5],
    avatars_created: AtomicU64,
    avatars_evicted: AtomicU64,
}

impl Metrics {
    pub fn set_queue_depth(&self, n: usize) {
        self.queue_depth.store(n as u64, Ordering::Relaxed);
    }
    pub fn add_batch(&self, frames: usize, took: Duration) {
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.frames.fetch_add(frames as u64, Ordering::Relaxed);
        self.render_seconds_micros
            .fetch_add(took.as_micros() as u64, Ordering::Relaxed);
        for (b, bound) in self.batch_buckets.iter().zip(BATCH_BUCKETS) {
            if frames <= bound {
                b.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
    pub fn add_cancelled(&self, n: usize) {
        self.cancelled.fetch_add(n as u64, Ordering::Relaxed);
    }
    pub fn add_latency(&self, d: Duration) {
        let mut l = self.latencies.lock().unwrap_or_else(|p| p.into_inner());
        if l.len() == LATENCY_WINDOW {
            l.pop_front();
        }
        l.push_back(d.as_secs_f64());
    }
    pub fn add_answer(&self, status: u16) {
        let class = (status / 100).clamp(1, 5) as usize - 1;
        self.answers[class].fetch_add(1, Ordering::Relaxed);
    }
    pub fn avatar_created(&self) {
        self.avatars_created.fetch_add(1, Ordering::Relaxed);
    }
    pub fn avatars_evicted(&self, n: usize) {
        self.avatars_evicted.fetch_add(n as u64, Ordering::Relaxed);
    }
    pub fn frames(&self) -> u64 {
        self.frames.load(Ordering::Relaxed)
    }
    pub fn batches(&self) -> u64 {
        self.batches.load(Ordering::Relaxed)
    }

    /// Render latency (queued to rendered) quantile `q` in seconds over the recent window.
    pub fn latency_quantile(&self, q: f64) -> Option<f64> {
        let l = self.latencies.lock().unwrap_or_else(|p| p.into_inner());
        if l.is_empty() {
            return None;
        }
        let mut v: Vec<f64> = l.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
        Some(v[i])
    }

    /// The Prometheus text exposition; `avatars` and `avatar_bytes` describe the store now,
    /// `jobs` the reenact jobs running.
    pub fn render_text(&self, avatars: usize, avatar_bytes: usize, jobs: usize) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let g = |s: &mut String, name: &str, help: &str, kind: &str, v: f64| {
            let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {v}");
        };
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed) as f64;
        g(
            &mut s,
            "gagavatar_queue_depth",
            "Render requests waiting.",
            "gauge",
            load(&self.queue_depth),
        );
        g(
            &mut s,
            "gagavatar_render_frames_total",
            "Frames rendered.",
            "counter",
            load(&self.frames),
        );
        g(
            &mut s,
            "gagavatar_render_cancelled_total",
            "Frames dropped because their client went away.",
            "counter",
            load(&self.cancelled),
        );
        g(
            &mut s,
            "gagavatar_render_seconds_total",
            "Seconds spent in renderer calls.",
            "counter",
            load(&self.render_seconds_micros) * 1e-6,
        );
        let _ = writeln!(
            s,
            "# HELP gagavatar_batch_size Frames per renderer call.\n# TYPE gagavatar_batch_size histogram"
        );
        for (b, bound) in self.batch_buckets.iter().zip(BATCH_BUCKETS) {
            let _ = writeln!(
                s,
                "gagavatar_batch_size_bucket{{le=\"{bound}\"}} {}",
                load(b)
            );
        }
        let _ = writeln!(
            s,
            "gagavatar_batch_size_bucket{{le=\"+Inf\"}} {}\ngagavatar_batch_size_sum {}\ngagavatar_batch_size_count {}",
            load(&self.batches),
            load(&self.frames),
            load(&self.batches)
        );
        let _ = writeln!(
            s,
            "# HELP gagavatar_render_latency_seconds Queued-to-rendered time of recent frames.\n# TYPE gagavatar_render_latency_seconds summary"
        );
        for q in [0.5, 0.99] {
            if let Some(v) = self.latency_quantile(q) {
                let _ = writeln!(
                    s,
                    "gagavatar_render_latency_seconds{{quantile=\"{q}\"}} {v}"
                );
            }
        }
        g(
            &mut s,
            "gagavatar_avatars",
            "Avatars in memory.",
            "gauge",
            avatars as f64,
        );
        g(
            &mut s,
            "gagavatar_avatar_bytes",
            "Bytes the avatars in memory hold.",
            "gauge",
            avatar_bytes as f64,
        );
        g(
            &mut s,
            "gagavatar_avatars_created_total",
            "Avatars reconstructed.",
            "counter",
            load(&self.avatars_created),
        );
        g(
            &mut s,
            "gagavatar_avatars_evicted_total",
            "Avatars dropped to stay within the memory budget.",
            "counter",
            load(&self.avatars_evicted),
        );
        g(
            &mut s,
            "gagavatar_jobs_running",
            "Reenact jobs not finished.",
            "gauge",
            jobs as f64,
        );
        let _ = writeln!(
            s,
            "# HELP gagavatar_http_answers_total Answers by status class.\n# TYPE gagavatar_http_answers_total counter"
        );
        for (i, a) in self.answers.iter().enumerate() {
            let _ = writeln!(
                s,
                "gagavatar_http_answers_total{{class=\"{}xx\"}} {}",
                i + 1,
                load(a)
            );
        }
        s
    }
}
