//! A bounded load test on loopback (`gagavatar bench serve`): N concurrent clients, each sending
//! render requests for one of several avatars, every answer checked (200, a PNG of the model's
//! size); throughput and client-side latency, with the server's batch sizes.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Instant;

use gagavatar_avatar::Engine;

use crate::client::request;
use crate::{AppState, BatchConfig, LocalServer, ServeConfig};

#[derive(Debug, Clone)]
pub struct LoadConfig {
    pub clients: usize,
    pub requests_per_client: usize,
    pub batch: BatchConfig,
}

#[derive(Debug, Clone)]
pub struct LoadReport {
    pub frames: usize,
    pub seconds: f64,
    pub frames_per_second: f64,
    pub p50_ms: f64,
    pub p99_ms: f64,
    /// Answers that were not a 200 with a PNG of the right size.
    pub wrong: usize,
    pub batches: u64,
    /// Upload to first frame, for the first photo (tracking through a cold cache).
    pub first_frame_ms: f64,
    /// Bytes the avatar store holds per avatar.
    pub bytes_per_avatar: usize,
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
    v[i]
}

/// Starts a server with `cfg.batch`, makes an avatar of each photo, then runs the clients.
pub fn run(
    engine: Arc<Engine>,
    photos: &[Vec<u8>],
    cfg: &LoadConfig,
) -> std::io::Result<LoadReport> {
    let serve_cfg = ServeConfig {
        batch: BatchConfig {
            max_queue: cfg.batch.max_queue.max(cfg.clients * 2),
            ..cfg.batch
        },
        ..ServeConfig::default()
    };
    let size = engine.image_size() as u32;
    let server = LocalServer::start(AppState::new(engine, serve_cfg)?)?;
    let addr = server.addr;
    let mut ids = Vec::new();
    let mut first_frame_ms = f64::NAN;
    for (i, p) in photos.iter().enumerate() {
        let t0 = Instant::now();
        let a = request(addr, "POST", "/v1/avatars", &[], p)?;
        if a.status / 100 != 2 {
            return Err(std::io::Error::other(format!(
                "photo {i}: {} {}",
                a.status,
                a.text()
            )));
        }
        let id = a.json()["id"].as_str().unwrap_or_default().to_string();
        let f = request(
            addr,
            "POST",
            &format!("/v1/avatars/{id}/render"),
            &[],
            b"{}",
        )?;
        if i == 0 && f.status == 200 {
            first_frame_ms = 1e3 * t0.elapsed().as_secs_f64();
        }
        ids.push(id);
    }
    let (avatars, bytes) = server.state.store.usage();
    let batches0 = server.state.metrics.batches();
    let t0 = Instant::now();
    let threads: Vec<_> = (0..cfg.clients)
        .map(|c| {
            let id = ids[c % ids.len()].clone();
            let n = cfg.requests_per_client;
            std::thread::spawn(move || client(addr, &id, c, n, size))
        })
        .collect();
    let mut latencies = Vec::new();
    let mut wrong = 0;
    for t in threads {
        let (l, w) = t
            .join()
            .map_err(|_| std::io::Error::other("a client thread panicked"))?;
        latencies.extend(l);
        wrong += w;
    }
    let seconds = t0.elapsed().as_secs_f64();
    let frames = cfg.clients * cfg.requests_per_client;
    Ok(LoadReport {
        frames,
        seconds,
        frames_per_second: frames as f64 / seconds,
        p50_ms: quantile(&mut latencies, 0.5),
        p99_ms: quantile(&mut latencies, 0.99),
        wrong,
        batches: server.state.metrics.batches() - batches0,
        first_frame_ms,
        bytes_per_avatar: bytes / avatars.max(1),
    })
}

fn client(addr: SocketAddr, id: &str, c: usize, n: usize, size: u32) -> (Vec<f64>, usize) {
    let mut lat = Vec::with_capacity(n);
    let mut wrong = 0;
    for r in 0..n {
        let yaw = ((c * 7 + r * 3) % 41) as f64 - 20.0;
        let body = format!(
            "{{\"yaw\": {yaw}, \"jaw\": [{}, 0, 0]}}",
            0.01 * (r % 20) as f64
        );
        let t = Instant::now();
        let ok = match request(
            addr,
            "POST",
            &format!("/v1/avatars/{id}/render"),
            &[],
            body.as_bytes(),
        ) {
            Ok(a) if a.status == 200 => image::load_from_memory(&a.body)
                .map(|img| img.width() == size && img.height() == size)
                .unwrap_or(false),
            _ => false,
        };
        lat.push(1e3 * t.elapsed().as_secs_f64());
        if !ok {
            wrong += 1;
        }
    }
    (lat, wrong)
}
