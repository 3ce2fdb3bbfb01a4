//! The HTTP API over real loopback sockets, with the shipped demo model and the public-domain
//! photo the repository ships: what each route answers, the limits and their status codes, the
//! token, batching, LRU eviction, a disconnecting client, and a reenact job end to end.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use gagavatar_avatar::{Drive, Engine, EngineConfig};
use gagavatar_serve::client::{request, Answer};
use gagavatar_serve::{AppState, BatchConfig, LocalServer, ServeConfig};

/// Batched renderer calls may sum in another order than a single frame: one 8-bit level.
const BATCH_LEVELS: i32 = 1;

fn demo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo")
}

fn engine() -> Arc<Engine> {
    Arc::new(Engine::open(&EngineConfig::new(demo().join("weights.safetensors"))).unwrap())
}

fn astronaut() -> Vec<u8> {
    std::fs::read(demo().join("astronaut.jpg")).unwrap()
}

/// A server on a free loopback port, stopped when dropped.
struct Server(LocalServer);

impl std::ops::Deref for Server {
    type Target = LocalServer;
    fn deref(&self) -> &LocalServer {
        &self.0
    }
}

impl Server {
    fn start(cfg: ServeConfig) -> Server {
        Self::with_engine(engine(), cfg)
    }
    fn with_engine(engine: Arc<Engine>, cfg: ServeConfig) -> Server {
        Server(LocalServer::start(AppState::new(engine, cfg).unwrap()).unwrap())
    }
    fn get(&self, path: &str) -> Answer {
        request(self.addr, "GET", path, &[], &[]).unwrap()
    }
    fn post(&self, path: &str, body: &[u8]) -> Answer {
        request(self.addr, "POST", path, &[], body).unwrap()
    }
    fn json(&self, path: &str, v: serde_json::Value) -> Answer {
        self.post(path, v.to_string().as_bytes())
    }
    fn metric(&self, name: &str) -> f64 {
        let text = self.get("/metrics").text();
        text.lines()
            .find_map(|l| l.strip_prefix(name).and_then(|r| r.strip_prefix(' ')))
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no metric {name} in\n{text}"))
    }
    fn create(&self, photo: &[u8]) -> String {
        let a = self.post("/v1/avatars", photo);
        assert!(
            a.status == 201 || a.status == 200,
            "{} {}",
            a.status,
            a.text()
        );
        a.json()["id"].as_str().unwrap().to_string()
    }
}

fn set_cache() {
    let dir =
        std::env::temp_dir().join(format!("gagavatar_serve_test_cache_{}", std::process::id()));
    std::env::set_var("GAGAVATAR_CACHE", dir);
}

fn decode(a: &Answer) -> image::RgbImage {
    image::load_from_memory(&a.body)
        .unwrap_or_else(|e| panic!("{e}: {} {}", a.status, a.text()))
        .to_rgb8()
}

fn assert_error(a: &Answer, status: u16, needle: &str) {
    assert_eq!(a.status, status, "{}", a.text());
    let msg = a.json()["error"].as_str().map(str::to_string);
    let msg = msg.unwrap_or_else(|| panic!("not a JSON error: {}", a.text()));
    assert!(msg.contains(needle), "`{msg}` does not say `{needle}`");
    assert!(!msg.contains('\n'), "not one line: {msg}");
}

#[test]
fn a_photo_becomes_an_avatar_that_renders_as_the_library_does() {
    set_cache();
    let e = engine();
    let s = Server::with_engine(e.clone(), ServeConfig::default());
    let h = s.get("/v1/health").json();
    assert_eq!(
        (h["status"].as_str(), h["image_size"].as_u64()),
        (Some("ok"), Some(64))
    );
    let page = s.get("/");
    assert!(
        page.status == 200 && page.text().contains("Drop a photo"),
        "{}",
        page.text()
    );
    assert!(s.get("/app.js").text().contains("/v1/avatars"));

    let first = s.post("/v1/avatars", &astronaut());
    assert_eq!(first.status, 201, "{}", first.text());
    let id = first.json()["id"].as_str().unwrap().to_string();
    // The same photo again: the avatar in memory, no work.
    let again = s.post("/v1/avatars", &astronaut());
    assert_eq!(
        (again.status, again.json()["cached"].as_bool()),
        (200, Some(true))
    );
    assert_eq!(again.json()["id"].as_str(), Some(id.as_str()));

    let crop = decode(&s.get(&format!("/v1/avatars/{id}/crop.png")));
    assert_eq!(crop.dimensions(), (512, 512));
    let info = s.get(&format!("/v1/avatars/{id}")).json();
    let record: gagavatar_flame::TrackedFrame =
        gagavatar_flame::TrackedFrame::from_json_str(&info["record"].to_string()).unwrap();

    // A frame through the server equals the library's own drive of the same avatar and codes.
    let body = serde_json::json!({"expression": [1.5, -1.0], "jaw": [0.25, 0.0, 0.0], "yaw": 15.0, "watermark": false});
    let served = decode(&s.json(&format!("/v1/avatars/{id}/render"), body));
    assert_eq!(served.dimensions(), (64, 64));
    let avatar = e.avatar(&crop, &record).unwrap();
    let mut codes = avatar.codes(&record, "record").unwrap();
    codes.expression.iter_mut().for_each(|v| *v = 0.0);
    codes.expression[0] = 1.5;
    codes.expression[1] = -1.0;
    codes.pose[3] = 0.25;
    codes.pose[4] = 0.0;
    codes.pose[5] = 0.0;
    let cam = gagavatar_avatar::orbit::orbit_transform(
        &avatar.source_camera().unwrap(),
        15f64.to_radians(),
        0.0,
    );
    let own = avatar.cpu_drive().render(&codes, &cam).unwrap();
    let worst = own
        .iter()
        .zip(served.as_raw())
        .map(|(a, b)| (*a as i32 - *b as i32).abs())
        .max()
        .unwrap();
    assert!(
        worst <= BATCH_LEVELS,
        "{worst} levels from the library's frame"
    );

    // The sliders move the frame; the label is on by default; JPEG on request.
    let neutral = decode(&s.json(
        &format!("/v1/avatars/{id}/render"),
        serde_json::json!({"watermark": false}),
    ));
    assert_ne!(
        neutral.as_raw(),
        served.as_raw(),
        "codes and camera changed nothing"
    );
    let labelled = decode(&s.json(&format!("/v1/avatars/{id}/render"), serde_json::json!({})));
    assert_ne!(
        labelled.as_raw(),
        neutral.as_raw(),
        "no visible label by default"
    );
    let jpeg = s.json(
        &format!("/v1/avatars/{id}/render"),
        serde_json::json!({"format": "jpeg"}),
    );
    assert_eq!(jpeg.header("content-type"), Some("image/jpeg"));
    decode(&jpeg);

    let ply = s.get(&format!("/v1/avatars/{id}/avatar.ply"));
    assert_eq!(ply.status, 200);
    assert!(ply.body.starts_with(b"ply\n"), "not a .ply");
    assert!(s
        .get("/metrics")
        .text()
        .contains("gagavatar_render_frames_total"));

    // Deleting it frees it.
    let d = request(s.addr, "DELETE", &format!("/v1/avatars/{id}"), &[], &[]).unwrap();
    assert_eq!(d.status, 204);
    assert_error(&s.get(&format!("/v1/avatars/{id}")), 404, "no avatar");
}

#[test]
fn bad_requests_get_one_clear_line_and_the_server_keeps_serving() {
    set_cache();
    let cfg = ServeConfig {
        max_photo_bytes: 200_000,
        max_pixels: 300_000,
        ..ServeConfig::default()
    };
    let s = Server::start(cfg);
    assert_error(&s.post("/v1/avatars", b""), 400, "empty");
    assert_error(
        &s.post("/v1/avatars", b"hello, not a photo"),
        415,
        "not a photo",
    );
    // Too many bytes (the astronaut JPEG is larger than 200 kB), too many pixels.
    assert_error(
        &s.post("/v1/avatars", &vec![0u8; 300_000]),
        413,
        "larger than",
    );
    let mut big = Vec::new();
    image::RgbImage::new(1000, 1000)
        .write_to(&mut std::io::Cursor::new(&mut big), image::ImageFormat::Png)
        .unwrap();
    assert_error(&s.post("/v1/avatars", &big), 413, "megapixels");
    // A wall is not a face.
    let mut wall = Vec::new();
    image::RgbImage::from_pixel(200, 160, image::Rgb([120, 130, 140]))
        .write_to(
            &mut std::io::Cursor::new(&mut wall),
            image::ImageFormat::Png,
        )
        .unwrap();
    assert_error(
        &s.post("/v1/avatars", &wall),
        422,
        "no face found in the photo",
    );
    // Unknown avatars and routes; ids that are not ids never reach a path.
    assert_error(&s.get("/v1/avatars/0123456789abcdef"), 404, "no avatar");
    assert_error(
        &s.get("/v1/avatars/..%2F..%2Fetc%2Fpasswd/crop.png"),
        404,
        "no avatar",
    );
    assert_error(&s.get("/v1/jobs/zzzz"), 404, "no job");
    assert_error(&s.get("/v2/anything"), 404, "no such");
    // The server still works.
    let small = {
        let img = image::open(demo().join("astronaut.jpg")).unwrap().to_rgb8();
        let img = image::imageops::resize(&img, 400, 400, image::imageops::FilterType::Triangle);
        let mut b = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut b), image::ImageFormat::Jpeg)
            .unwrap();
        b
    };
    let id = s.create(&small);
    let render = |body: &str| s.post(&format!("/v1/avatars/{id}/render"), body.as_bytes());
    assert_error(&render("{\"bogus\": 1}"), 400, "unknown field `bogus`");
    assert_error(&render("{not json"), 400, "bad render request");
    assert_error(&render("{\"yaw\": 500}"), 400, "yaw must be within");
    assert_error(
        &render("{\"expression\": [1e39]}"),
        400,
        "expression[0] is not a finite number",
    );
    assert_error(
        &render(&format!(
            "{{\"expression\": [{}]}}",
            vec!["0.1"; 200].join(",")
        )),
        400,
        "expression has 200 values",
    );
    assert_error(&render("{\"format\": \"gif\"}"), 400, "png or jpeg");
    assert_error(
        &render("{\"camera\": [[1,0,0,0],[0,1,0,0],[0,0,1,5]], \"yaw\": 3}"),
        400,
        "not both",
    );
    assert_eq!(render("{}").status, 200);
    assert!(s.metric("gagavatar_http_answers_total{class=\"4xx\"}") >= 10.0);
}

#[test]
fn a_token_guards_the_api_but_not_the_page() {
    set_cache();
    let s = Server::start(ServeConfig {
        token: Some("s3cret".into()),
        ..ServeConfig::default()
    });
    assert_eq!(s.get("/").status, 200);
    assert_error(&s.get("/v1/health"), 401, "token");
    assert_error(&s.get("/metrics"), 401, "token");
    let wrong = request(
        s.addr,
        "GET",
        "/v1/health",
        &[("Authorization", "Bearer nope")],
        &[],
    )
    .unwrap();
    assert_eq!(wrong.status, 401);
    let ok = request(
        s.addr,
        "GET",
        "/v1/health",
        &[("Authorization", "Bearer s3cret")],
        &[],
    )
    .unwrap();
    assert_eq!(ok.status, 200);
    assert_eq!(s.get("/v1/health?token=s3cret").status, 200);
}

#[test]
fn concurrent_renders_are_batched_and_a_full_queue_answers_503() {
    set_cache();
    // A long window: the first request waits for the others, so they share renderer calls.
    let s = Arc::new(Server::start(ServeConfig {
        batch: BatchConfig {
            max_batch: 8,
            window: Duration::from_millis(300),
            max_queue: 64,
        },
        ..ServeConfig::default()
    }));
    let id = s.create(&astronaut());
    let threads: Vec<_> = (0..16)
        .map(|i| {
            let s = s.clone();
            let id = id.clone();
            std::thread::spawn(move || {
                let body = serde_json::json!({"yaw": i as f64, "watermark": false});
                s.json(&format!("/v1/avatars/{id}/render"), body)
            })
        })
        .collect();
    for t in threads {
        let a = t.join().unwrap();
        assert_eq!(a.status, 200, "{}", a.text());
    }
    let (frames, batches) = (s.state.metrics.frames(), s.state.metrics.batches());
    assert_eq!(frames, 16);
    assert!(
        batches <= 4,
        "16 concurrent frames took {batches} renderer calls"
    );

    // A queue of two that the worker is not draining yet (it waits 2 s for company): the third
    // request is refused at once with Retry-After, and the first two are still answered.
    let s = Arc::new(Server::start(ServeConfig {
        batch: BatchConfig {
            max_batch: 100,
            window: Duration::from_millis(2000),
            max_queue: 2,
        },
        ..ServeConfig::default()
    }));
    let id = s.create(&astronaut());
    let waiting: Vec<_> = (0..2)
        .map(|_| {
            let s = s.clone();
            let id = id.clone();
            std::thread::spawn(move || {
                s.json(&format!("/v1/avatars/{id}/render"), serde_json::json!({}))
            })
        })
        .collect();
    while s.state.batcher.queue_depth() < 2 {
        std::thread::sleep(Duration::from_millis(10));
    }
    let refused = s.json(&format!("/v1/avatars/{id}/render"), serde_json::json!({}));
    assert_error(&refused, 503, "queue is full");
    assert_eq!(refused.header("retry-after"), Some("1"));
    for t in waiting {
        assert_eq!(t.join().unwrap().status, 200);
    }
}

#[test]
fn a_client_that_disconnects_cancels_its_frame() {
    set_cache();
    let s = Server::start(ServeConfig {
        batch: BatchConfig {
            max_batch: 100,
            window: Duration::from_millis(1500),
            max_queue: 8,
        },
        ..ServeConfig::default()
    });
    let id = s.create(&astronaut());
    {
        use std::io::Write;
        let mut c = std::net::TcpStream::connect(s.addr).unwrap();
        let body = "{}";
        write!(
            c,
            "POST /v1/avatars/{id}/render HTTP/1.1\r\nHost: x\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        )
        .unwrap();
        while s.state.batcher.queue_depth() < 1 {
            std::thread::sleep(Duration::from_millis(10));
        }
        // The connection closes here, before the batch is rendered.
    }
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while s.metric("gagavatar_render_cancelled_total") < 1.0 {
        assert!(
            std::time::Instant::now() < deadline,
            "the frame was not cancelled"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        s.state.metrics.frames(),
        0,
        "the gone client's frame was rendered"
    );
}

#[test]
fn the_least_recently_used_avatar_goes_when_memory_runs_out() {
    set_cache();
    let s = Server::start(ServeConfig::default());
    let a = s.create(&astronaut());
    let per_avatar = s.get("/v1/health").json()["avatar_bytes"].as_u64().unwrap() as usize;
    assert!(per_avatar > 0);
    drop(s);
    // Room for one avatar and a half: a second one pushes the first out.
    let s = Server::start(ServeConfig {
        avatar_budget: per_avatar * 3 / 2,
        ..ServeConfig::default()
    });
    assert_eq!(s.create(&astronaut()), a);
    let mirrored = {
        let img = image::open(demo().join("astronaut.jpg")).unwrap().to_rgb8();
        let img = image::imageops::flip_horizontal(&img);
        let mut b = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut b), image::ImageFormat::Png)
            .unwrap();
        b
    };
    let b = s.create(&mirrored);
    assert_ne!(a, b);
    assert_error(
        &s.get(&format!("/v1/avatars/{a}")),
        404,
        "dropped to free memory",
    );
    assert_eq!(s.get(&format!("/v1/avatars/{b}")).status, 200);
    assert_eq!(s.metric("gagavatar_avatars_evicted_total"), 1.0);
    assert_eq!(s.metric("gagavatar_avatars"), 1.0);
}

/// Six 128x128 frames of the astronaut through a drifting window, as H.264 mp4 (the built-in
/// encoder and decoder: no ffmpeg needed).
fn clip() -> Vec<u8> {
    let photo = image::open(demo().join("astronaut.jpg")).unwrap().to_rgb8();
    let path =
        std::env::temp_dir().join(format!("gagavatar_serve_clip_{}.mp4", std::process::id()));
    let mut w = gagavatar_video::VideoWriter::create(
        &path,
        128,
        128,
        gagavatar_video::VideoOptions {
            fps: 12.5,
            watermark: false,
        },
    )
    .unwrap();
    for i in 0..6u32 {
        let view = image::imageops::crop_imm(&photo, 90 + 4 * i, 0, 280, 280).to_image();
        let f = image::imageops::resize(&view, 128, 128, image::imageops::FilterType::Triangle);
        w.push_rgb(f.as_raw()).unwrap();
    }
    w.finish().unwrap();
    let b = std::fs::read(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    b
}

#[test]
fn a_video_is_reenacted_as_a_job_with_progress_and_limits() {
    set_cache();
    let s = Server::start(ServeConfig::default());
    let id = s.create(&astronaut());
    let video = clip();
    let started = s.post(&format!("/v1/avatars/{id}/reenact"), &video);
    assert_eq!(started.status, 202, "{}", started.text());
    let job = started.json()["job"].as_str().unwrap().to_string();
    let deadline = std::time::Instant::now() + Duration::from_secs(120);
    let status = loop {
        let st = s.get(&format!("/v1/jobs/{job}")).json();
        match st["state"].as_str() {
            Some("done") => break st,
            Some("failed") | Some("cancelled") => panic!("{st}"),
            _ => {}
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the job did not finish: {st}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(
        (status["frames"].as_u64(), status["fps"].as_f64()),
        (Some(6), Some(12.5))
    );
    let mp4 = s.get(&format!("/v1/jobs/{job}/result.mp4"));
    assert_eq!(mp4.header("content-type"), Some("video/mp4"));
    let path =
        std::env::temp_dir().join(format!("gagavatar_serve_result_{}.mp4", std::process::id()));
    std::fs::write(&path, &mp4.body).unwrap();
    let info = gagavatar_video::mp4::read_mp4_info(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    assert_eq!((info.frames, info.width, info.height), (6, 64, 64));
    let d = request(s.addr, "DELETE", &format!("/v1/jobs/{job}"), &[], &[]).unwrap();
    assert_eq!(d.status, 204);
    assert_error(&s.get(&format!("/v1/jobs/{job}")), 404, "no job");

    // Not a video; a video past the frame limit; no room for another job.
    assert_error(
        &s.post(&format!("/v1/avatars/{id}/reenact"), b"not a video at all"),
        422,
        "not a video",
    );
    drop(s);
    let s = Server::start(ServeConfig {
        max_video_frames: 3,
        ..ServeConfig::default()
    });
    let id = s.create(&astronaut());
    assert_error(
        &s.post(&format!("/v1/avatars/{id}/reenact"), &video),
        413,
        "at most 3",
    );
    drop(s);
    let s = Server::start(ServeConfig {
        max_jobs: 0,
        ..ServeConfig::default()
    });
    let id = s.create(&astronaut());
    let busy = s.post(&format!("/v1/avatars/{id}/reenact"), &video);
    assert_error(&busy, 429, "already reenacting");
    assert_eq!(busy.header("retry-after"), Some("10"));
}

#[test]
fn a_webcam_stream_drives_the_avatar_over_a_websocket() {
    use tungstenite::Message;
    set_cache();
    let s = Server::start(ServeConfig::default());
    let id = s.create(&astronaut());
    let (mut ws, _) =
        tungstenite::connect(format!("ws://{}/v1/avatars/{id}/live", s.addr)).unwrap();
    let photo = image::open(demo().join("astronaut.jpg")).unwrap().to_rgb8();
    let mut frames = Vec::new();
    for i in 0..4u32 {
        let view = image::imageops::crop_imm(&photo, 80 + 6 * i, 0, 300, 300).to_image();
        let mut jpeg = Vec::new();
        view.write_to(
            &mut std::io::Cursor::new(&mut jpeg),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
        ws.send(Message::Binary(jpeg.into())).unwrap();
        match ws.read().unwrap() {
            Message::Binary(b) => frames.push(image::load_from_memory(&b).unwrap().to_rgb8()),
            other => panic!("frame {i}: {other:?}"),
        }
    }
    assert!(frames.iter().all(|f| f.dimensions() == (64, 64)));
    assert_ne!(
        frames[0].as_raw(),
        frames[3].as_raw(),
        "the head moved, the avatar did not"
    );
    // A frame without a face and one that is not an image: a note each, and the session goes on.
    let mut wall = Vec::new();
    image::RgbImage::from_pixel(160, 120, image::Rgb([90, 90, 90]))
        .write_to(
            &mut std::io::Cursor::new(&mut wall),
            image::ImageFormat::Png,
        )
        .unwrap();
    ws.send(Message::Binary(wall.into())).unwrap();
    let note = ws.read().unwrap().into_text().unwrap();
    assert!(note.contains("\"face\":false"), "{note}");
    ws.send(Message::Binary(b"garbage".to_vec().into()))
        .unwrap();
    let note = ws.read().unwrap().into_text().unwrap();
    assert!(note.contains("error"), "{note}");
    ws.close(None).unwrap();
    assert_eq!(s.metric("gagavatar_render_frames_total"), 4.0);
}

#[test]
fn thirty_two_clients_are_all_answered_correctly_with_and_without_batching() {
    use gagavatar_serve::loadtest::{run, LoadConfig};
    set_cache();
    let e = engine();
    let photos = [astronaut()];
    let mut calls = Vec::new();
    for max_batch in [1, 8] {
        let cfg = LoadConfig {
            clients: 32,
            requests_per_client: 2,
            batch: BatchConfig {
                max_batch,
                window: Duration::from_millis(if max_batch == 1 { 0 } else { 4 }),
                max_queue: 64,
            },
        };
        let r = run(e.clone(), &photos, &cfg).unwrap();
        assert_eq!((r.frames, r.wrong), (64, 0), "max batch {max_batch}");
        assert!(r.p99_ms >= r.p50_ms && r.p50_ms > 0.0);
        calls.push(r.batches);
    }
    assert_eq!(calls[0], 64, "one request at a time is one call a frame");
    assert!(
        calls[1] < 64,
        "32 concurrent clients were never batched ({} calls)",
        calls[1]
    );
}
