//! Reenact jobs: an uploaded video tracked (through the tracking cache), every frame rendered
//! through the shared batcher, the mp4 kept until the job is deleted. Progress is polled;
//! cancelling stops tracking or rendering at the next frame and leaves no file.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use gagavatar_avatar::{Avatar, CancelToken, Engine, Monitor, TrackTo};
use gagavatar_video::{VideoOptions, VideoWriter};
use serde::Serialize;
use tokio::sync::oneshot;

use crate::batcher::{Batcher, RenderJob};
use crate::error::one_line;

/// Frames a job keeps in flight in the batcher (its frames join other clients' batches).
const JOB_IN_FLIGHT: usize = 8;

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct JobStatus {
    /// `tracking`, `rendering`, `done`, `failed` or `cancelled`.
    pub state: &'static str,
    /// The current stage (`landmarks`, `fit | crop, matte, JPEG`, `render`).
    pub stage: String,
    pub done: u64,
    pub total: Option<u64>,
    pub error: Option<String>,
    pub frames: Option<usize>,
    pub fps: Option<f64>,
}

pub struct Job {
    pub id: String,
    status: Mutex<JobStatus>,
    pub cancel: CancelToken,
    pub result: Mutex<Option<PathBuf>>,
    pub dir: PathBuf,
    pub started: Instant,
}

impl Job {
    pub fn new(id: String, dir: PathBuf) -> Self {
        Job {
            id,
            status: Mutex::new(JobStatus {
                state: "tracking",
                stage: "queued".into(),
                done: 0,
                total: None,
                error: None,
                frames: None,
                fps: None,
            }),
            cancel: CancelToken::new(),
            result: Mutex::new(None),
            dir,
            started: Instant::now(),
        }
    }

    pub fn status(&self) -> JobStatus {
        self.status
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    fn update(&self, f: impl FnOnce(&mut JobStatus)) {
        f(&mut self.status.lock().unwrap_or_else(|p| p.into_inner()));
    }

    pub fn finished(&self) -> bool {
        matches!(self.status().state, "done" | "failed" | "cancelled")
    }
}

impl Monitor for Job {
    fn stage(&self, name: &str, total: Option<u64>) {
        self.update(|s| {
            s.stage = name.to_owned();
            s.total = total;
            s.done = 0;
        });
    }
    fn advance(&self, steps: u64) {
        self.update(|s| s.done += steps);
    }
    fn cancelled(&self) -> bool {
        self.cancel.is_cancelled()
    }
}

/// What a job needs besides itself.
pub struct JobInput {
    pub engine: Arc<Engine>,
    pub batcher: Arc<Batcher>,
    pub avatar: Arc<Avatar>,
    pub video: PathBuf,
    pub max_frames: usize,
    pub watermark: bool,
}

/// Runs `job` to its end (on a blocking thread).
pub fn run(job: &Job, input: JobInput) {
    let outcome = run_inner(job, &input);
    let _ = std::fs::remove_file(&input.video);
    match outcome {
        Ok(path) => {
            *job.result.lock().unwrap_or_else(|p| p.into_inner()) = Some(path);
            job.update(|s| s.state = "done");
        }
        Err(_) if job.cancel.is_cancelled() => {
            let _ = std::fs::remove_dir_all(&job.dir);
            job.update(|s| s.state = "cancelled");
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&job.dir);
            job.update(|s| {
                s.state = "failed";
                s.error = Some(e);
            });
        }
    }
}

fn run_inner(job: &Job, input: &JobInput) -> Result<PathBuf, String> {
    let tracked = input
        .engine
        .track_as(&input.video, &TrackTo::Cache, "the video", false, job)
        .map_err(|e| one_line(&e))?;
    let n = tracked.records.len();
    if tracked.kind != gagavatar_avatar::InputKind::Video {
        return Err("the upload is a photo, not a video".into());
    }
    if n > input.max_frames {
        return Err(format!(
            "the video has {n} frames; this server renders at most {}",
            input.max_frames
        ));
    }
    job.update(|s| {
        s.state = "rendering";
        s.stage = "render".into();
        s.done = 0;
        s.total = Some(n as u64);
        s.frames = Some(n);
        s.fps = Some(tracked.fps);
    });
    let size = input.avatar.image_size();
    let out = job.dir.join("result.mp4");
    let opts = VideoOptions {
        fps: tracked.fps,
        watermark: input.watermark,
    };
    let mut writer = VideoWriter::create(&out, size, size, opts).map_err(|e| one_line(&e))?;
    for chunk in tracked.records.chunks(JOB_IN_FLIGHT) {
        if job.cancel.is_cancelled() {
            return Err("cancelled".into());
        }
        let mut waits = Vec::with_capacity(chunk.len());
        for (i, rec) in chunk.iter().enumerate() {
            let codes = input
                .avatar
                .codes(rec, "a tracked frame")
                .map_err(|e| one_line(&e))?;
            let camera = rec
                .transform_matrix
                .ok_or_else(|| format!("tracked frame {i} has no camera"))?;
            let (tx, rx) = oneshot::channel();
            let submitted = input.batcher.submit(
                RenderJob {
                    avatar: input.avatar.clone(),
                    codes,
                    camera,
                    reply: tx,
                    queued: Instant::now(),
                },
                true,
            );
            if submitted.is_err() {
                return Err("the render queue refused a frame".into());
            }
            waits.push(rx);
        }
        for rx in waits {
            let frame = rx
                .blocking_recv()
                .map_err(|_| "the renderer stopped".to_string())??;
            writer.push_rgb(&frame).map_err(|e| one_line(&e))?;
            job.update(|s| s.done += 1);
        }
    }
    writer.finish().map_err(|e| one_line(&e))?;
    Ok(out)
}

/// A job's folder under the server's scratch folder.
pub fn job_dir(scratch: &Path, id: &str) -> PathBuf {
    scratch.join("jobs").join(id)
}
