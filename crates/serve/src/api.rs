//! The routes. Version 1 of the API:
//!
//! | method and path | body | answer |
//! |---|---|---|
//! | `POST /v1/avatars` | a photo (PNG, JPEG, WebP, BMP) | 201 `{id, image_size, cached, track_ms, reconstruct_ms}` (200 when the photo's avatar is in memory) |
//! | `GET /v1/avatars/{id}` | | `{id, image_size, record}` |
//! | `DELETE /v1/avatars/{id}` | | 204 |
//! | `GET /v1/avatars/{id}/crop.png` | | the tracked 512 crop |
//! | `GET /v1/avatars/{id}/avatar.ply` | | the Gaussians as a 3DGS `.ply` |
//! | `POST /v1/avatars/{id}/render` | JSON codes + camera | PNG or JPEG |
//! | `POST /v1/avatars/{id}/reenact` | a video | 202 `{job}` |
//! | `GET /v1/jobs/{id}` | | progress `{state, stage, done, total, error}` |
//! | `GET /v1/jobs/{id}/result.mp4` | | the reenactment |
//! | `DELETE /v1/jobs/{id}` | | 204; cancels a running job |
//! | `GET /v1/avatars/{id}/live` | WebSocket: camera frames (JPEG/PNG, binary) in | rendered JPEG frames out; text `{"error"}` / `{"face": false}` notes |
//! | `GET /v1/health`, `GET /metrics` | | JSON; Prometheus text |

use std::io::Cursor;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use gagavatar_avatar::orbit::orbit_transform;
use gagavatar_avatar::{AvatarError, CancelToken, TrackTo};
use serde::Deserialize;
use sha2::{Digest, Sha256};
use tokio::sync::oneshot;

use crate::batcher::RenderJob;
use crate::error::{one_line, ApiError, ApiResult};
use crate::jobs::{self, Job, JobInput};
use crate::page;
use crate::store::Stored;
use crate::AppState;

type St = State<Arc<AppState>>;

/// Finished jobs kept for their results; older finished ones are dropped with their files.
const KEEP_FINISHED_JOBS: usize = 16;

pub fn router(state: Arc<AppState>) -> Router {
    let limit = state.cfg.max_video_bytes.max(state.cfg.max_photo_bytes);
    let api = Router::new()
        .route("/v1/health", get(health))
        .route("/v1/avatars", post(create_avatar))
        .route("/v1/avatars/{id}", get(avatar_info).delete(delete_avatar))
        .route("/v1/avatars/{id}/crop.png", get(avatar_crop))
        .route("/v1/avatars/{id}/avatar.ply", get(avatar_ply))
        .route("/v1/avatars/{id}/render", post(render))
        .route("/v1/avatars/{id}/reenact", post(reenact))
        .route("/v1/avatars/{id}/live", get(live))
        .route("/v1/jobs/{id}", get(job_status).delete(delete_job))
        .route("/v1/jobs/{id}/result.mp4", get(job_result))
        .route("/metrics", get(metrics))
        .layer(middleware::from_fn_with_state(state.clone(), authorize));
    Router::new()
        .route("/", get(|| async { html(page::INDEX_HTML) }))
        .route(
            "/app.js",
            get(|| async { asset("text/javascript; charset=utf-8", page::APP_JS) }),
        )
        .route(
            "/style.css",
            get(|| async { asset("text/css; charset=utf-8", page::STYLE_CSS) }),
        )
        .merge(api)
        .fallback(|| async { ApiError::not_found("no such page or API route") })
        .layer(DefaultBodyLimit::max(limit))
        .layer(middleware::from_fn_with_state(state.clone(), count_answers))
        .with_state(state)
}

fn html(text: &'static str) -> Response {
    asset("text/html; charset=utf-8", text)
}

fn asset(kind: &'static str, text: &'static str) -> Response {
    ([(header::CONTENT_TYPE, kind)], text).into_response()
}

async fn count_answers(State(s): St, req: Request, next: Next) -> Response {
    let r = next.run(req).await;
    s.metrics.add_answer(r.status().as_u16());
    r
}

/// The bearer token, from the header or (for download links) `?token=`.
async fn authorize(State(s): St, req: Request, next: Next) -> Response {
    if let Some(want) = &s.cfg.token {
        let header_ok = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .is_some_and(|t| same(t, want));
        let query_ok = req.uri().query().is_some_and(|q| {
            q.split('&')
                .filter_map(|kv| kv.strip_prefix("token="))
                .any(|t| same(t, want))
        });
        if !(header_ok || query_ok) {
            return ApiError::new(
                StatusCode::UNAUTHORIZED,
                "this server needs its token: Authorization: Bearer <token>",
            )
            .into_response();
        }
    }
    next.run(req).await
}

/// Compares without stopping at the first difference.
fn same(a: &str, b: &str) -> bool {
    a.len() == b.len()
        && a.bytes()
            .zip(b.bytes())
            .fold(0u8, |acc, (x, y)| acc | (x ^ y))
            == 0
}

/// A random 64-bit value (job ids, scratch names): the std hasher's per-process random keys
/// mixed with the time.
pub fn random_u64() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0),
    );
    h.finish()
}

/// An id from a path: 16 lowercase hex digits, or 404 (so no client text reaches a path).
fn check_id(id: &str, what: &str) -> ApiResult<()> {
    if id.len() == 16
        && id
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        Ok(())
    } else {
        Err(ApiError::not_found(format!("no {what} `{}`", short(id))))
    }
}

fn short(s: &str) -> String {
    s.chars().take(40).collect()
}

fn stored(s: &AppState, id: &str) -> ApiResult<Arc<Stored>> {
    check_id(id, "avatar")?;
    s.store.get(id).ok_or_else(|| {
        ApiError::not_found(format!(
            "no avatar `{id}` (it may have been dropped to free memory: upload the photo again)"
        ))
    })
}

fn body_error(e: BytesRejection, limit: usize, what: &str) -> ApiError {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        too_large(limit, what)
    } else {
        ApiError::bad_request(format!("cannot read the {what}: {}", e.body_text()))
    }
}

async fn health(State(s): St) -> Response {
    let (avatars, bytes) = s.store.usage();
    Json(serde_json::json!({
        "status": "ok",
        "version": 1,
        "image_size": s.engine.image_size(),
        "model": s.engine.model().cfg.name,
        "flame": s.engine.flame_label(),
        "device": s.cfg.device,
        "avatars": avatars,
        "avatar_bytes": bytes,
        "queue_depth": s.batcher.queue_depth(),
        "max_batch": s.batcher.config().max_batch,
    }))
    .into_response()
}

async fn metrics(State(s): St) -> Response {
    let (avatars, bytes) = s.store.usage();
    let jobs = s
        .jobs
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .values()
        .filter(|j| !j.finished())
        .count();
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        s.metrics.render_text(avatars, bytes, jobs),
    )
        .into_response()
}

/// Cancels its token when dropped before [`Armed::disarm`]: a client that disconnects stops
/// the work it started.
struct Armed(Option<CancelToken>);
impl Armed {
    fn disarm(&mut self) {
        self.0 = None;
    }
}
impl Drop for Armed {
    fn drop(&mut self) {
        if let Some(t) = &self.0 {
            t.cancel();
        }
    }
}

/// Counts a pending photo; uncounted when dropped.
struct Pending<'a>(&'a AppState);
impl Drop for Pending<'_> {
    fn drop(&mut self) {
        self.0.pending_avatars.fetch_sub(1, Ordering::SeqCst);
    }
}

fn content_id(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .take(8)
        .map(|b| format!("{b:02x}"))
        .collect()
}

async fn create_avatar(State(s): St, body: Result<Bytes, BytesRejection>) -> ApiResult<Response> {
    let limit = s.cfg.max_photo_bytes;
    let body = body.map_err(|e| body_error(e, limit, "photo"))?;
    if body.len() > limit {
        return Err(too_large(limit, "photo"));
    }
    if body.is_empty() {
        return Err(ApiError::bad_request(
            "the upload is empty: send the photo's bytes as the request body",
        ));
    }
    let id = content_id(&body);
    if let Some(st) = s.store.get(&id) {
        return Ok(created(StatusCode::OK, &id, &st, true, 0.0, 0.0));
    }
    // The header alone says what it is and how large.
    let (w, h) = image::ImageReader::new(Cursor::new(&body[..]))
        .with_guessed_format()
        .ok()
        .filter(|r| r.format().is_some())
        .and_then(|r| r.into_dimensions().ok())
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "the upload is not a photo this server reads (PNG, JPEG, WebP or BMP)",
            )
        })?;
    if (w as u64) * (h as u64) > s.cfg.max_pixels {
        return Err(ApiError::too_large(format!(
            "the photo is {w}x{h}; this server takes at most {} megapixels",
            s.cfg.max_pixels / 1_000_000
        )));
    }
    if s.pending_avatars.fetch_add(1, Ordering::SeqCst) >= s.cfg.max_pending_avatars {
        s.pending_avatars.fetch_sub(1, Ordering::SeqCst);
        return Err(ApiError::busy(
            "the server is busy making other avatars; try again in a few seconds",
            5,
        ));
    }
    let _pending = Pending(&s);
    let _permit = s
        .compute
        .acquire()
        .await
        .map_err(|_| ApiError::internal("the server is stopping"))?;
    let cancel = CancelToken::new();
    let mut armed = Armed(Some(cancel.clone()));
    let state = s.clone();
    let id2 = id.clone();
    let made = tokio::task::spawn_blocking(move || make_avatar(&state, &id2, &body, &cancel))
        .await
        .map_err(|_| ApiError::internal("the avatar worker stopped"))??;
    armed.disarm();
    let (st, track_ms, recon_ms) = made;
    let dropped = s.store.insert(&id, st.clone());
    s.metrics.avatar_created();
    s.metrics.avatars_evicted(dropped);
    Ok(created(
        StatusCode::CREATED,
        &id,
        &st,
        false,
        track_ms,
        recon_ms,
    ))
}

fn too_large(limit: usize, what: &str) -> ApiError {
    ApiError::too_large(format!(
        "the {what} is larger than this server takes ({} MB)",
        limit >> 20
    ))
}

fn created(
    status: StatusCode,
    id: &str,
    st: &Stored,
    cached: bool,
    track_ms: f64,
    reconstruct_ms: f64,
) -> Response {
    (
        status,
        Json(serde_json::json!({
            "id": id,
            "image_size": st.avatar.image_size(),
            "cached": cached,
            "track_ms": track_ms,
            "reconstruct_ms": reconstruct_ms,
            "avatar_bytes": st.bytes,
        })),
    )
        .into_response()
}

/// Tracks the upload (through the tracking cache) and reconstructs; on a blocking thread.
fn make_avatar(
    s: &AppState,
    id: &str,
    body: &[u8],
    cancel: &CancelToken,
) -> ApiResult<(Arc<Stored>, f64, f64)> {
    let path = s.scratch.join("uploads").join(id);
    std::fs::write(&path, body)
        .map_err(|e| ApiError::internal(format!("cannot keep the upload: {e}")))?;
    let t0 = Instant::now();
    let tracked = s
        .engine
        .track_as(&path, &TrackTo::Cache, "the photo", true, cancel);
    let _ = std::fs::remove_file(&path);
    let tracked = tracked.map_err(|e| avatar_error(e, &path))?;
    let track_ms = 1e3 * t0.elapsed().as_secs_f64();
    let (Some(crop), Some(record)) = (tracked.crop, tracked.records.into_iter().next()) else {
        return Err(ApiError::internal("the tracking holds no photo"));
    };
    let t1 = Instant::now();
    let avatar = s
        .engine
        .avatar(&crop, &record)
        .map_err(|e| avatar_error(e, &path))?;
    let recon_ms = 1e3 * t1.elapsed().as_secs_f64();
    let mut png = Vec::new();
    crop.write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|e| ApiError::internal(format!("cannot encode the crop: {e}")))?;
    let bytes = avatar.memory_bytes() + png.len();
    Ok((
        Arc::new(Stored {
            avatar: Arc::new(avatar),
            crop_png: png,
            record,
            bytes,
        }),
        track_ms,
        recon_ms,
    ))
}

/// A library error as the client's answer: the server's own paths replaced by "the upload".
fn avatar_error(e: AvatarError, path: &std::path::Path) -> ApiError {
    use gagavatar_avatar::AvatarError as E;
    let line = one_line(&e).replace(&path.display().to_string(), "the upload");
    match e {
        E::Track(gagavatar_track::TrackError::NoFace { .. }) => ApiError::unprocessable(
            "no face found in the photo: use a photo with one face, facing the camera",
        ),
        E::Cancelled => ApiError::new(
            StatusCode::from_u16(499).unwrap_or(StatusCode::BAD_REQUEST),
            line,
        ),
        E::Input { .. } | E::Format(_) | E::Track(_) | E::Face(_) | E::Video(_) => {
            ApiError::unprocessable(line)
        }
        _ => ApiError::internal(line),
    }
}

async fn avatar_info(State(s): St, Path(id): Path<String>) -> ApiResult<Response> {
    let st = stored(&s, &id)?;
    let r = &st.record;
    Ok(Json(serde_json::json!({
        "id": id,
        "image_size": st.avatar.image_size(),
        "avatar_bytes": st.bytes,
        "record": {
            "shapecode": r.shapecode, "expcode": r.expcode, "posecode": r.posecode,
            "eyecode": r.eyecode, "transform_matrix": r.transform_matrix, "bbox": r.bbox,
        },
    }))
    .into_response())
}

async fn delete_avatar(State(s): St, Path(id): Path<String>) -> ApiResult<StatusCode> {
    check_id(&id, "avatar")?;
    if s.store.remove(&id) {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError::not_found(format!("no avatar `{id}`")))
    }
}

async fn avatar_crop(State(s): St, Path(id): Path<String>) -> ApiResult<Response> {
    let st = stored(&s, &id)?;
    Ok(([(header::CONTENT_TYPE, "image/png")], st.crop_png.clone()).into_response())
}

async fn avatar_ply(State(s): St, Path(id): Path<String>) -> ApiResult<Response> {
    let st = stored(&s, &id)?;
    let state = s.clone();
    let bytes = tokio::task::spawn_blocking(move || -> ApiResult<Vec<u8>> {
        let codes = st
            .avatar
            .codes(&st.record, "the source record")
            .map_err(|e| ApiError::internal(one_line(&e)))?;
        let scene = st
            .avatar
            .scene(&codes)
            .map_err(|e| ApiError::internal(one_line(&e)))?;
        let path = state
            .scratch
            .join("exports")
            .join(format!("{:016x}.ply", random_u64()));
        scene
            .save_ply(&path)
            .map_err(|e| ApiError::internal(one_line(&e)))?;
        let bytes = std::fs::read(&path).map_err(|e| ApiError::internal(e.to_string()));
        let _ = std::fs::remove_file(&path);
        bytes
    })
    .await
    .map_err(|_| ApiError::internal("the export worker stopped"))??;
    let mut headers = HeaderMap::new();
    headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/octet-stream"),
    );
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"avatar-{id}.ply\"")) {
        headers.insert(header::CONTENT_DISPOSITION, v);
    }
    Ok((headers, bytes).into_response())
}

/// A frame to render: codes (missing ones are the source's) and a camera (a 3x4 transform, or
/// yaw/pitch in degrees around the source view).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderRequest {
    pub expression: Option<Vec<f32>>,
    pub jaw: Option<[f32; 3]>,
    pub eyes: Option<[f32; 6]>,
    pub yaw: Option<f64>,
    pub pitch: Option<f64>,
    pub camera: Option<[[f64; 4]; 3]>,
    /// `png` (default) or `jpeg`.
    pub format: Option<String>,
    /// The visible "AI-generated" label (default on).
    pub watermark: Option<bool>,
}

async fn render(
    State(s): St,
    Path(id): Path<String>,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<Response> {
    let st = stored(&s, &id)?;
    let body = body.map_err(|e| body_error(e, s.cfg.max_photo_bytes, "render request"))?;
    // Any content type: the body is JSON (an empty body renders the source as it is).
    let req: RenderRequest = if body.iter().all(u8::is_ascii_whitespace) {
        RenderRequest::default()
    } else {
        serde_json::from_slice(&body)
            .map_err(|e| ApiError::bad_request(format!("bad render request: {e}")))?
    };
    let jpeg = match req.format.as_deref() {
        None | Some("png") => false,
        Some("jpeg") | Some("jpg") => true,
        Some(other) => {
            return Err(ApiError::bad_request(format!(
                "format must be png or jpeg, not `{}`",
                short(other)
            )))
        }
    };
    let avatar = &st.avatar;
    let mut codes = avatar
        .codes(&st.record, "the source record")
        .map_err(|e| ApiError::internal(one_line(&e)))?;
    let finite = |v: &[f32], what: &str| -> ApiResult<()> {
        match v.iter().position(|x| !x.is_finite()) {
            Some(i) => Err(ApiError::bad_request(format!(
                "{what}[{i}] is not a finite number"
            ))),
            None => Ok(()),
        }
    };
    if let Some(e) = &req.expression {
        let n = codes.expression.len();
        if e.len() > n {
            return Err(ApiError::bad_request(format!(
                "expression has {} values; this model's FLAME has {n}",
                e.len()
            )));
        }
        finite(e, "expression")?;
        codes.expression.iter_mut().for_each(|v| *v = 0.0);
        codes.expression[..e.len()].copy_from_slice(e);
    }
    if let Some(j) = &req.jaw {
        finite(j, "jaw")?;
        codes.pose[3..6].copy_from_slice(j);
    }
    if let Some(y) = &req.eyes {
        finite(y, "eyes")?;
        codes.eye = *y;
    }
    let camera = match (&req.camera, req.yaw, req.pitch) {
        (Some(c), None, None) => {
            if c.iter().flatten().any(|x| !x.is_finite()) {
                return Err(ApiError::bad_request(
                    "camera holds a value that is not finite",
                ));
            }
            *c
        }
        (Some(_), _, _) => {
            return Err(ApiError::bad_request(
                "give camera, or yaw and pitch, not both",
            ))
        }
        (None, yaw, pitch) => {
            let (yaw, pitch) = (yaw.unwrap_or(0.0), pitch.unwrap_or(0.0));
            if !(yaw.is_finite() && pitch.is_finite() && yaw.abs() <= 180.0 && pitch.abs() <= 90.0)
            {
                return Err(ApiError::bad_request(
                    "yaw must be within [-180, 180] degrees and pitch within [-90, 90]",
                ));
            }
            let base = avatar
                .source_camera()
                .map_err(|e| ApiError::internal(one_line(&e)))?;
            orbit_transform(&base, yaw.to_radians(), pitch.to_radians())
        }
    };
    let watermark = req.watermark.unwrap_or(true);
    let encoded = render_encoded(&s, avatar, codes, camera, watermark, jpeg).await?;
    let kind = if jpeg { "image/jpeg" } else { "image/png" };
    Ok(([(header::CONTENT_TYPE, kind)], encoded).into_response())
}

/// One frame through the shared batcher, encoded (PNG or JPEG, with or without the label).
/// Dropping the future (the client went away) tells the batcher to skip the frame.
async fn render_encoded(
    s: &AppState,
    avatar: &Arc<gagavatar_avatar::Avatar>,
    codes: gagavatar_avatar::FrameCodes,
    camera: gagavatar_avatar::Camera,
    watermark: bool,
    jpeg: bool,
) -> ApiResult<Vec<u8>> {
    let (tx, rx) = oneshot::channel();
    s.batcher
        .submit(
            RenderJob {
                avatar: avatar.clone(),
                codes,
                camera,
                reply: tx,
                queued: Instant::now(),
            },
            false,
        )
        .map_err(|_| ApiError::busy("the render queue is full; try again in a moment", 1))?;
    let frame = rx
        .await
        .map_err(|_| ApiError::internal("the renderer stopped"))?
        .map_err(ApiError::internal)?;
    let size = avatar.image_size();
    tokio::task::spawn_blocking(move || encode(frame, size, watermark, jpeg))
        .await
        .map_err(|_| ApiError::internal("the encoder stopped"))?
}

fn encode(mut rgb: Vec<u8>, size: usize, watermark: bool, jpeg: bool) -> ApiResult<Vec<u8>> {
    if watermark {
        gagavatar_video::draw_watermark(&mut rgb, size, size, gagavatar_video::WATERMARK_TEXT);
    }
    let img = image::RgbImage::from_raw(size as u32, size as u32, rgb)
        .ok_or_else(|| ApiError::internal("a frame of the wrong size"))?;
    let mut out = Vec::new();
    let r = if jpeg {
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 92).encode_image(&img)
    } else {
        img.write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
    };
    r.map_err(|e| ApiError::internal(format!("cannot encode the frame: {e}")))?;
    Ok(out)
}

#[derive(Debug, Default, Deserialize)]
pub struct ReenactQuery {
    pub watermark: Option<bool>,
}

async fn reenact(
    State(s): St,
    Path(id): Path<String>,
    Query(q): Query<ReenactQuery>,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<Response> {
    let st = stored(&s, &id)?;
    let limit = s.cfg.max_video_bytes;
    let body = body.map_err(|e| body_error(e, limit, "video"))?;
    if body.is_empty() {
        return Err(ApiError::bad_request(
            "the upload is empty: send the video's bytes as the request body",
        ));
    }
    {
        let jobs = s.jobs.lock().unwrap_or_else(|p| p.into_inner());
        if jobs.values().filter(|j| !j.finished()).count() >= s.cfg.max_jobs {
            return Err(ApiError::too_many(
                "this server is already reenacting as many videos as it takes; try again later",
                10,
            ));
        }
    }
    let job_id = format!("{:016x}", random_u64());
    let dir = jobs::job_dir(&s.scratch, &job_id);
    std::fs::create_dir_all(&dir)
        .map_err(|e| ApiError::internal(format!("cannot make the job's folder: {e}")))?;
    let video = dir.join("upload");
    std::fs::write(&video, &body)
        .map_err(|e| ApiError::internal(format!("cannot keep the upload: {e}")))?;
    // The length first: an over-long video is refused before any work.
    let probe = {
        let v = video.clone();
        tokio::task::spawn_blocking(move || {
            gagavatar_video::read::VideoReader::open(&v, &Default::default())
                .map(|r| r.expected_frames())
        })
        .await
        .map_err(|_| ApiError::internal("the probe stopped"))?
    };
    let refuse = |e: ApiError| {
        let _ = std::fs::remove_dir_all(&dir);
        e
    };
    match probe {
        Err(e) => {
            let line = one_line(&e).replace(&video.display().to_string(), "the upload");
            return Err(refuse(ApiError::unprocessable(format!(
                "the upload is not a video this server reads: {line}"
            ))));
        }
        Ok(Some(n)) if n as usize > s.cfg.max_video_frames => {
            return Err(refuse(ApiError::too_large(format!(
                "the video has {n} frames; this server takes at most {}",
                s.cfg.max_video_frames
            ))));
        }
        Ok(_) => {}
    }
    let job = Arc::new(Job::new(job_id.clone(), dir));
    {
        let mut jobs = s.jobs.lock().unwrap_or_else(|p| p.into_inner());
        jobs.insert(job_id.clone(), job.clone());
        prune_jobs(&mut jobs);
    }
    let input = JobInput {
        engine: s.engine.clone(),
        batcher: s.batcher.clone(),
        avatar: st.avatar.clone(),
        video,
        max_frames: s.cfg.max_video_frames,
        watermark: q.watermark.unwrap_or(true),
    };
    tokio::task::spawn_blocking(move || jobs::run(&job, input));
    Ok((
        StatusCode::ACCEPTED,
        Json(serde_json::json!({
            "job": job_id,
            "status": format!("/v1/jobs/{job_id}"),
            "result": format!("/v1/jobs/{job_id}/result.mp4"),
        })),
    )
        .into_response())
}

/// Drops the oldest finished jobs beyond [`KEEP_FINISHED_JOBS`], with their files.
fn prune_jobs(jobs: &mut std::collections::HashMap<String, Arc<Job>>) {
    let mut finished: Vec<(Instant, String)> = jobs
        .values()
        .filter(|j| j.finished())
        .map(|j| (j.started, j.id.clone()))
        .collect();
    if finished.len() <= KEEP_FINISHED_JOBS {
        return;
    }
    finished.sort();
    for (_, id) in finished.iter().take(finished.len() - KEEP_FINISHED_JOBS) {
        if let Some(j) = jobs.remove(id) {
            let _ = std::fs::remove_dir_all(&j.dir);
        }
    }
}

fn job(s: &AppState, id: &str) -> ApiResult<Arc<Job>> {
    check_id(id, "job")?;
    s.jobs
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .get(id)
        .cloned()
        .ok_or_else(|| ApiError::not_found(format!("no job `{id}`")))
}

async fn job_status(State(s): St, Path(id): Path<String>) -> ApiResult<Response> {
    let j = job(&s, &id)?;
    Ok(Json(j.status()).into_response())
}

async fn job_result(State(s): St, Path(id): Path<String>) -> ApiResult<Response> {
    let j = job(&s, &id)?;
    let path = j.result.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let Some(path) = path else {
        let st = j.status();
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            match st.error {
                Some(e) => format!("the job {}: {e}", st.state),
                None => format!("the job is not done yet ({})", st.state),
            },
        ));
    };
    let bytes = tokio::fs::read(&path)
        .await
        .map_err(|e| ApiError::internal(format!("cannot read the result: {e}")))?;
    let mut headers = HeaderMap::new();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("video/mp4"));
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"reenact-{id}.mp4\"")) {
        headers.insert(header::CONTENT_DISPOSITION, v);
    }
    Ok((headers, bytes).into_response())
}

async fn delete_job(State(s): St, Path(id): Path<String>) -> ApiResult<StatusCode> {
    let j = job(&s, &id)?;
    j.cancel.cancel();
    s.jobs.lock().unwrap_or_else(|p| p.into_inner()).remove(&id);
    if j.finished() {
        let _ = std::fs::remove_dir_all(&j.dir);
    }
    Ok(StatusCode::NO_CONTENT)
}

/// Live driving over a WebSocket: each binary message is a camera frame (JPEG or PNG); the
/// server tracks it in video mode (the face tracker's ROI and the fit carried from frame to
/// frame), renders the avatar with its codes and camera through the shared batcher, and answers
/// with the frame as JPEG. A frame without a face answers `{"face": false}` as text; a bad frame
/// answers `{"error": ...}`; the session goes on. The client sends its next frame after the answer, so nothing queues up.
async fn live(
    State(s): St,
    Path(id): Path<String>,
    ws: axum::extract::ws::WebSocketUpgrade,
) -> ApiResult<Response> {
    let st = stored(&s, &id)?;
    let open = s.live_sessions.load(Ordering::SeqCst);
    if open >= s.cfg.max_live {
        return Err(ApiError::too_many(
            "this server is driving as many live sessions as it takes; try again later",
            10,
        ));
    }
    let limit = s.cfg.max_photo_bytes;
    Ok(ws
        .max_message_size(limit)
        .on_upgrade(move |socket| live_session(s, st, socket)))
}

/// Counts an open live session; uncounted when dropped.
struct LiveCount(Arc<AppState>);
impl Drop for LiveCount {
    fn drop(&mut self) {
        self.0.live_sessions.fetch_sub(1, Ordering::SeqCst);
    }
}

async fn live_session(s: Arc<AppState>, st: Arc<Stored>, mut socket: axum::extract::ws::WebSocket) {
    use axum::extract::ws::Message;
    s.live_sessions.fetch_add(1, Ordering::SeqCst);
    let _count = LiveCount(s.clone());
    let note = |v: serde_json::Value| Message::Text(v.to_string().into());
    let engine = s.engine.clone();
    let tracker = match tokio::task::spawn_blocking(move || engine.tracker()).await {
        Ok(Ok(t)) => t,
        Ok(Err(e)) => {
            let _ = socket
                .send(note(serde_json::json!({"error": one_line(&e)})))
                .await;
            return;
        }
        Err(_) => return,
    };
    let live = Arc::new(std::sync::Mutex::new(gagavatar_avatar::LiveTracker::new(
        tracker,
    )));
    let max_pixels = s.cfg.max_pixels;
    while let Some(Ok(msg)) = socket.recv().await {
        let bytes = match msg {
            Message::Binary(b) => b,
            Message::Close(_) => break,
            _ => continue,
        };
        let lt = live.clone();
        let tracked = tokio::task::spawn_blocking(move || -> Result<Option<_>, String> {
            let reader = image::ImageReader::new(Cursor::new(&bytes[..]))
                .with_guessed_format()
                .map_err(|e| e.to_string())?;
            let (w, h) = reader
                .into_dimensions()
                .map_err(|_| "a live frame must be a JPEG or PNG image".to_string())?;
            if (w as u64) * (h as u64) > max_pixels {
                return Err(format!("a live frame of {w}x{h} is too large"));
            }
            let img = image::load_from_memory(&bytes)
                .map_err(|e| format!("cannot decode a live frame: {e}"))?
                .to_rgb8();
            lt.lock()
                .unwrap_or_else(|p| p.into_inner())
                .frame(&img)
                .map_err(|e| one_line(&e))
        })
        .await;
        let answer = match tracked {
            Err(_) => break,
            Ok(Err(e)) => note(serde_json::json!({ "error": e })),
            Ok(Ok(None)) => note(serde_json::json!({ "face": false })),
            Ok(Ok(Some(rec))) => match live_frame(&s, &st, &rec).await {
                Ok(jpeg) => Message::Binary(jpeg.into()),
                Err(e) => note(serde_json::json!({ "error": e.message })),
            },
        };
        if socket.send(answer).await.is_err() {
            break;
        }
    }
}

/// The avatar with a live record's codes and camera, as a labelled JPEG.
async fn live_frame(
    s: &AppState,
    st: &Stored,
    rec: &gagavatar_flame::TrackedFrame,
) -> ApiResult<Vec<u8>> {
    let codes = st
        .avatar
        .codes(rec, "a live frame")
        .map_err(|e| ApiError::internal(one_line(&e)))?;
    let camera = rec
        .transform_matrix
        .ok_or_else(|| ApiError::internal("a live record has no camera"))?;
    render_encoded(s, &st.avatar, codes, camera, true, true).await
}
