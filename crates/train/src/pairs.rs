//! Training and evaluation pairs (spec section 11) and their loading.
//!
//! - Training: each sample's target runs through the train split's frames in a fresh random
//!   order per epoch (as the release's shuffled data loader does); its source is another frame
//!   of the same video, drawn uniformly, or with probability `cross_identity` a frame of another
//!   video. Everything is a pure function of `(seed, step, index in the batch)`, so a resumed
//!   run, or any number of loader threads in any timing, draws exactly the same pairs.
//! - Validation / test: the first frame of each video (natural frame order) is the source of
//!   every other frame of that video; pairs follow the split's listed order (the release's
//!   protocol; it validates the first 16).
//!
//! A sample holds the source image and camera, the target image, camera and face bbox, and the
//! target's FLAME vertices from the target's own record (shape, expression, jaw, eyes; x5 as
//! everywhere), as the release's loader builds them. Images are resized to the model's size
//! (bilinear with antialiasing) when the dataset's differ; the model resizes the source to its
//! DINO input itself.

use std::collections::BTreeMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;

use candle_core::{Device, Tensor};
use gagavatar_data::{group_by_video, Dataset};
use gagavatar_flame::{FlameModel, TrackedFrame};
use gagavatar_ops::{resize, ResizeMode};
use gagavatar_splat::rng::Rng;
use image::RgbImage;

use crate::run_error::{RunError, RunResult};

/// SplitMix64's finaliser: a well-mixed 64-bit function of its input.
pub fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// An independent stream id for `(a, b)`.
pub fn mix(a: u64, b: u64) -> u64 {
    splitmix(splitmix(a) ^ b.wrapping_mul(0xD1B5_4A32_D192_ED03))
}

/// Stream salts, so the target order, the source choice and anything later never share values.
const SALT_EPOCH: u64 = 0x0E90_C400;
const SALT_SOURCE: u64 = 0x50C4_CE00;

/// A source frame driving a target frame.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Pair {
    pub source: String,
    pub target: String,
}

/// Draws the training pairs of every step (see the module docs).
#[derive(Debug)]
pub struct PairSampler {
    seed: u64,
    batch: usize,
    cross_identity: f64,
    /// Frames per video, natural order; only videos with two or more frames.
    videos: Vec<Vec<String>>,
    /// `(video, frame)` of every target, in split order.
    targets: Vec<(u32, u32)>,
    /// The last epoch's order (recomputing it per sample would cost O(n) each).
    epoch_cache: Mutex<Option<(u64, Arc<Vec<u32>>)>>,
    /// The first pair and the number of pairs of each step's batch this sampler draws (the
    /// whole batch unless [`PairSampler::shard`]ed).
    share: (usize, usize),
}

impl PairSampler {
    /// Pairs from the train split's frame names. Videos with a single frame cannot form a pair
    /// and are left out (the second value counts them); errors when no
    /// video has two frames, or cross-identity pairs are asked for with one video.
    pub fn new(
        train: &[String],
        seed: u64,
        batch: usize,
        cross_identity: f64,
    ) -> RunResult<(Self, usize)> {
        let grouped = group_by_video(train.iter().map(String::as_str));
        let total = grouped.len();
        let videos: Vec<Vec<String>> = grouped.into_values().filter(|f| f.len() >= 2).collect();
        let single = total - videos.len();
        if videos.is_empty() {
            return Err(RunError::Config {
                path: None,
                reason: format!(
                    "the train split has no video with two or more frames ({} frames in {total} \
                     videos; frames are grouped by the `<video>_<frame>` naming rule)",
                    train.len()
                ),
            });
        }
        if cross_identity > 0.0 && videos.len() < 2 {
            return Err(RunError::Config {
                path: None,
                reason: "[data] cross_identity needs two or more videos in the train split".into(),
            });
        }
        let targets = videos
            .iter()
            .enumerate()
            .flat_map(|(v, f)| (0..f.len()).map(move |i| (v as u32, i as u32)))
            .collect();
        Ok((
            Self {
                seed,
                batch,
                share: (0, batch),
                cross_identity,
                videos,
                targets,
                epoch_cache: Mutex::new(None),
            },
            single,
        ))
    }

    /// Frames that can be targets.
    pub fn len(&self) -> usize {
        self.targets.len()
    }

    pub fn is_empty(&self) -> bool {
        self.targets.is_empty()
    }

    pub fn videos(&self) -> usize {
        self.videos.len()
    }

    pub fn batch(&self) -> usize {
        self.batch
    }

    /// The target order of epoch `e`: a Fisher-Yates shuffle seeded by `(seed, e)`.
    fn epoch_order(&self, e: u64) -> Arc<Vec<u32>> {
        let mut cache = self.epoch_cache.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((ce, order)) = cache.as_ref() {
            if *ce == e {
                return order.clone();
            }
        }
        let n = self.targets.len();
        let mut order: Vec<u32> = (0..n as u32).collect();
        let mut rng = Rng::from_state(mix(mix(self.seed, SALT_EPOCH), e));
        for i in (1..n).rev() {
            let j = rng.below(i + 1);
            order.swap(i, j);
        }
        let order = Arc::new(order);
        *cache = Some((e, order.clone()));
        order
    }

    /// Keeps this sampler to rank `rank`'s share of each step's batch (of `size` equal
    /// shares): pairs `rank b..(rank + 1) b` of the step's `size b`, the same pairs one
    /// process would draw at that place in the batch.
    pub fn shard(&mut self, rank: usize, size: usize) -> RunResult<()> {
        if size == 0 || rank >= size || !self.batch.is_multiple_of(size) {
            return Err(crate::run_error::RunError::Config {
                path: None,
                reason: format!(
                    "a batch of {} does not split into {size} equal shares (one per rank):                      make the batch a multiple of the rank count",
                    self.batch
                ),
            });
        }
        let b = self.batch / size;
        self.share = (rank * b, b);
        Ok(())
    }

    /// The first pair of this sampler's share of a step's batch, and the share's size.
    pub fn share(&self) -> (usize, usize) {
        self.share
    }

    /// The pairs of 0-based step `step` (this sampler's share of them, see [`PairSampler::shard`]).
    pub fn pairs(&self, step: u64) -> Vec<Pair> {
        let n = self.targets.len() as u64;
        let (first, count) = self.share;
        (first as u64..(first + count) as u64)
            .map(|i| {
                let k = step * self.batch as u64 + i;
                let order = self.epoch_order(k / n);
                let (v, f) = self.targets[order[(k % n) as usize] as usize];
                let frames = &self.videos[v as usize];
                let mut rng = Rng::from_state(mix(mix(self.seed, SALT_SOURCE), k));
                let source = if self.cross_identity > 0.0 && rng.uniform() < self.cross_identity {
                    let mut u = rng.below(self.videos.len() - 1);
                    if u >= v as usize {
                        u += 1;
                    }
                    let other = &self.videos[u];
                    other[rng.below(other.len())].clone()
                } else {
                    let mut j = rng.below(frames.len() - 1);
                    if j >= f as usize {
                        j += 1;
                    }
                    frames[j].clone()
                };
                Pair {
                    source,
                    target: frames[f as usize].clone(),
                }
            })
            .collect()
    }
}

/// Validation / test pairs of a split (see the module docs), at most `limit`.
pub fn eval_pairs(split: &[String], limit: Option<usize>) -> Vec<Pair> {
    let videos = group_by_video(split.iter().map(String::as_str));
    let firsts: BTreeMap<&str, &str> = videos
        .iter()
        .filter_map(|(v, f)| f.first().map(|s| (v.as_str(), s.as_str())))
        .collect();
    let mut out = Vec::new();
    for name in split {
        if limit.is_some_and(|l| out.len() >= l) {
            break;
        }
        let video = gagavatar_data::names::video_of(name);
        match firsts.get(video) {
            Some(&first) if first != name => out.push(Pair {
                source: first.to_string(),
                target: name.clone(),
            }),
            _ => {}
        }
    }
    out
}

/// One loaded pair, on the host, in f32.
#[derive(Debug, Clone)]
pub struct Sample {
    pub pair: Pair,
    /// `[3, S, S]` in [0, 1].
    pub source_image: Vec<f32>,
    /// `[3, 4]` row-major.
    pub source_transform: [f32; 12],
    pub target_image: Vec<f32>,
    pub target_transform: [f32; 12],
    /// `[V, 3]`, scaled by 5.
    pub target_vertices: Vec<f32>,
    /// `(x0, y0, x1, y1)` normalised.
    pub bbox: [f32; 4],
}

/// A batch of samples for one step.
#[derive(Debug, Clone)]
pub struct HostBatch {
    /// 0-based step this batch belongs to.
    pub step: u64,
    pub samples: Vec<Sample>,
    pub image_size: usize,
    pub n_vertices: usize,
}

/// A batch as tensors on the training device.
#[derive(Debug, Clone)]
pub struct BatchTensors {
    /// `[B, 3, S, S]`
    pub source_image: Tensor,
    /// `[B, 3, 4]`
    pub source_transform: Tensor,
    pub target_image: Tensor,
    pub target_transform: Tensor,
    /// `[B, V, 3]`
    pub target_vertices: Tensor,
    /// `[B, 4]`
    pub bbox: Tensor,
}

impl HostBatch {
    pub fn to_tensors(&self, device: &Device) -> RunResult<BatchTensors> {
        let b = self.samples.len();
        let s = self.image_size;
        let v = self.n_vertices;
        let cat = |f: &dyn Fn(&Sample) -> &[f32]| -> Vec<f32> {
            self.samples
                .iter()
                .flat_map(|x| f(x).iter().copied())
                .collect()
        };
        let t = |data: Vec<f32>, shape: &[usize]| -> RunResult<Tensor> {
            Ok(Tensor::from_vec(data, shape, device)?)
        };
        Ok(BatchTensors {
            source_image: t(cat(&|x| &x.source_image), &[b, 3, s, s])?,
            source_transform: t(cat(&|x| &x.source_transform), &[b, 3, 4])?,
            target_image: t(cat(&|x| &x.target_image), &[b, 3, s, s])?,
            target_transform: t(cat(&|x| &x.target_transform), &[b, 3, 4])?,
            target_vertices: t(cat(&|x| &x.target_vertices), &[b, v, 3])?,
            bbox: t(cat(&|x| &x.bbox), &[b, 4])?,
        })
    }
}

/// Turns pairs into samples: reads images and records from the dataset, runs FLAME.
#[derive(Debug)]
pub struct SampleSource {
    pub dataset: Arc<Dataset>,
    pub flame: Arc<FlameModel>,
    pub image_size: usize,
}

fn sample_err(dir: &std::path::Path, frame: &str, reason: impl Into<String>) -> RunError {
    RunError::Sample {
        dir: dir.to_path_buf(),
        frame: frame.to_string(),
        reason: reason.into(),
    }
}

impl SampleSource {
    pub fn new(dataset: Arc<Dataset>, flame: Arc<FlameModel>, image_size: usize) -> Self {
        Self {
            dataset,
            flame,
            image_size,
        }
    }

    fn dir(&self) -> PathBuf {
        self.dataset.dir().to_path_buf()
    }

    /// `[3, S, S]` f32 of a frame's image, resized to the model's size when needed.
    pub fn image(&self, name: &str) -> RunResult<Vec<f32>> {
        let img = self.dataset.image(name)?;
        image_to_chw(&img, self.image_size).map_err(|e| sample_err(&self.dir(), name, e))
    }

    fn record(&self, name: &str) -> RunResult<&TrackedFrame> {
        Ok(self.dataset.record(name)?)
    }

    fn transform(&self, name: &str, r: &TrackedFrame) -> RunResult<[f32; 12]> {
        let tm = r
            .transform_matrix
            .ok_or_else(|| sample_err(&self.dir(), name, "the record has no transform_matrix"))?;
        let mut out = [0f32; 12];
        for (o, v) in out.iter_mut().zip(tm.iter().flatten()) {
            *o = *v as f32;
        }
        Ok(out)
    }

    /// FLAME vertices `[V, 3]` (x5) of a frame's own record.
    pub fn vertices(&self, name: &str) -> RunResult<Vec<f32>> {
        let r = self.record(name)?;
        let run = || -> Result<Vec<f32>, gagavatar_flame::FlameError> {
            let out = self.flame.forward(&r.params(&self.flame)?)?;
            out.vertices
                .to_dtype(candle_core::DType::F32)
                .and_then(|t| t.flatten_all())
                .and_then(|t| t.to_vec1())
                .map_err(gagavatar_flame::FlameError::from)
        };
        run().map_err(|e| sample_err(&self.dir(), name, format!("FLAME codes: {e}")))
    }

    pub fn load(&self, pair: &Pair) -> RunResult<Sample> {
        let t = self.record(&pair.target)?;
        let bbox = t
            .bbox
            .ok_or_else(|| sample_err(&self.dir(), &pair.target, "the record has no bbox"))?;
        let s = self.record(&pair.source)?;
        Ok(Sample {
            source_image: self.image(&pair.source)?,
            source_transform: self.transform(&pair.source, s)?,
            target_image: self.image(&pair.target)?,
            target_transform: self.transform(&pair.target, t)?,
            target_vertices: self.vertices(&pair.target)?,
            bbox: bbox.map(|x| x as f32),
            pair: pair.clone(),
        })
    }

    pub fn load_batch(&self, step: u64, pairs: &[Pair]) -> RunResult<HostBatch> {
        Ok(HostBatch {
            step,
            samples: pairs
                .iter()
                .map(|p| self.load(p))
                .collect::<RunResult<_>>()?,
            image_size: self.image_size,
            n_vertices: self.flame.n_vertices,
        })
    }
}

/// An RGB image as `[3, size, size]` f32 in [0, 1]; square images only, resized with
/// antialiasing when their side differs.
pub fn image_to_chw(img: &RgbImage, size: usize) -> Result<Vec<f32>, String> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    if w != h {
        return Err(format!("the image is {w}x{h}; training needs square crops"));
    }
    let mut chw = vec![0f32; 3 * w * h];
    for (i, p) in img.pixels().enumerate() {
        for c in 0..3 {
            chw[c * w * h + i] = p.0[c] as f32 / 255.0;
        }
    }
    if w == size {
        return Ok(chw);
    }
    let resized = Tensor::from_vec(chw, (1, 3, h, w), &Device::Cpu)
        .and_then(|t| resize(&t, size, size, ResizeMode::Antialias))
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1::<f32>())
        .map_err(|e| format!("resizing to {size}x{size}: {e}"))?;
    Ok(resized)
}

#[derive(Debug)]
struct LoaderState {
    /// Next step a worker will take.
    next: u64,
    /// The step the trainer waits for; workers stay within `window` of it.
    consumed: u64,
    stop: bool,
}

type Shared = Arc<(Mutex<LoaderState>, Condvar)>;

/// Loads the batches of steps `first..end` in order, `workers` threads keeping up to `window`
/// batches ready (0 workers: each batch is loaded when asked for). Results arrive in step order
/// whatever the threads' timing; a load error is returned for its step.
pub struct Loader {
    source: Arc<SampleSource>,
    sampler: Arc<PairSampler>,
    next: u64,
    end: u64,
    shared: Shared,
    rx: Option<Receiver<(u64, RunResult<HostBatch>)>>,
    pending: BTreeMap<u64, RunResult<HostBatch>>,
    handles: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for Loader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Loader")
            .field("next", &self.next)
            .field("end", &self.end)
            .field("workers", &self.handles.len())
            .finish()
    }
}

fn worker(
    source: Arc<SampleSource>,
    sampler: Arc<PairSampler>,
    shared: Shared,
    window: u64,
    end: u64,
    tx: Sender<(u64, RunResult<HostBatch>)>,
) {
    loop {
        let step = {
            let (lock, cv) = &*shared;
            let mut st = lock.lock().unwrap_or_else(|p| p.into_inner());
            while !st.stop && st.next < end && st.next >= st.consumed + window {
                st = cv.wait(st).unwrap_or_else(|p| p.into_inner());
            }
            if st.stop || st.next >= end {
                return;
            }
            st.next += 1;
            st.next - 1
        };
        let result = catch_unwind(AssertUnwindSafe(|| {
            source.load_batch(step, &sampler.pairs(step))
        }))
        .unwrap_or_else(|_| {
            Err(RunError::Stopped {
                step,
                reason: "a loader thread panicked".into(),
            })
        });
        if tx.send((step, result)).is_err() {
            return;
        }
    }
}

impl Loader {
    pub fn start(
        source: Arc<SampleSource>,
        sampler: Arc<PairSampler>,
        first: u64,
        end: u64,
        workers: usize,
        window: usize,
    ) -> Self {
        let shared: Shared = Arc::new((
            Mutex::new(LoaderState {
                next: first,
                consumed: first,
                stop: false,
            }),
            Condvar::new(),
        ));
        let mut handles = Vec::new();
        let mut rx = None;
        if workers > 0 {
            let (tx, r) = channel();
            rx = Some(r);
            for _ in 0..workers {
                let (source, sampler, shared, tx) =
                    (source.clone(), sampler.clone(), shared.clone(), tx.clone());
                let window = window.max(1) as u64;
                handles.push(std::thread::spawn(move || {
                    worker(source, sampler, shared, window, end, tx)
                }));
            }
        }
        Self {
            source,
            sampler,
            next: first,
            end,
            shared,
            rx,
            pending: BTreeMap::new(),
            handles,
        }
    }

    /// The next step's batch.
    pub fn next_batch(&mut self) -> RunResult<HostBatch> {
        let want = self.next;
        if want >= self.end {
            return Err(RunError::Stopped {
                step: want,
                reason: format!("the loader was started for steps before {}", self.end),
            });
        }
        let result = match &self.rx {
            None => self.source.load_batch(want, &self.sampler.pairs(want)),
            Some(rx) => loop {
                if let Some(r) = self.pending.remove(&want) {
                    break r;
                }
                match rx.recv() {
                    Ok((s, r)) => {
                        self.pending.insert(s, r);
                    }
                    Err(_) => {
                        break Err(RunError::Stopped {
                            step: want,
                            reason: "the loader threads ended early".into(),
                        })
                    }
                }
            },
        };
        self.next += 1;
        let (lock, cv) = &*self.shared;
        lock.lock().unwrap_or_else(|p| p.into_inner()).consumed = self.next;
        cv.notify_all();
        result
    }
}

impl Drop for Loader {
    fn drop(&mut self) {
        {
            let (lock, cv) = &*self.shared;
            lock.lock().unwrap_or_else(|p| p.into_inner()).stop = true;
            cv.notify_all();
        }
        // Unblock senders, then wait for the threads (each finishes its current batch at most).
        self.rx = None;
        for h in self.handles.drain(..) {
            let _ = h.join();
        }
    }
}
