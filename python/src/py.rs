//! The bindings. Records cross the boundary as JSON text in the release's field names (the
//! Python side turns them into dicts of NumPy arrays), images and frames as `uint8` arrays
//! `[H, W, 3]` / `[N, H, W, 3]`. Every computation releases the GIL.

use std::path::PathBuf;
use std::sync::Arc;

use numpy::{
    PyArray1, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyReadonlyArray4,
    PyUntypedArrayMethods,
};
use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;

use gagavatar_avatar::orbit::orbit_cameras;
use gagavatar_avatar::{
    Camera, CpuDrive, Drive, Engine as CoreEngine, EngineConfig, FlameSource, FrameCodes, GpuDrive,
    Monitor, TrackTo,
};
use gagavatar_flame::TrackedFrame;
use gagavatar_gpu::reconstruct::GpuReconstruct;
use gagavatar_gpu::{AdapterPolicy, Gpu};
use gagavatar_net::style_unet::Noise;

create_exception!(
    gagavatar,
    Error,
    PyException,
    "Every failure of the package: one line, as the CLI prints it."
);

use gagavatar_avatar::one_line;

fn to_py(e: impl std::error::Error + 'static) -> PyErr {
    Error::new_err(one_line(&e))
}

/// A result with its error already turned into the one-line message (small to move out of a
/// closure that ran without the GIL).
fn lined<T>(r: Result<T, impl std::error::Error + 'static>) -> Result<T, String> {
    r.map_err(|e| one_line(&e))
}

fn bad(msg: impl Into<String>) -> PyErr {
    Error::new_err(msg.into())
}

fn record_from_json(text: &str, what: &str) -> PyResult<TrackedFrame> {
    TrackedFrame::from_json_str(text).map_err(|e| bad(format!("{what}: {}", one_line(&e))))
}

fn record_to_json(r: &TrackedFrame) -> String {
    serde_json::json!({
        "shapecode": r.shapecode,
        "expcode": r.expcode,
        "posecode": r.posecode,
        "eyecode": r.eyecode,
        "transform_matrix": r.transform_matrix,
        "bbox": r.bbox,
    })
    .to_string()
}

/// `frames` RGB u8 frames of `size` x `size` as one `[N, size, size, 3]` array.
fn frames_array<'py>(
    py: Python<'py>,
    frames: Vec<Vec<u8>>,
    size: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let n = frames.len();
    let mut flat: Vec<u8> = Vec::with_capacity(n * size * size * 3);
    for f in &frames {
        flat.extend_from_slice(f);
    }
    let arr = PyArray1::from_vec(py, flat).reshape([n, size, size, 3])?;
    Ok(arr.into_any())
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum DeviceChoice {
    Cpu,
    Gpu,
    Auto,
}

/// The model and FLAME, loaded once.
#[pyclass(module = "gagavatar._native")]
pub struct Engine {
    inner: Arc<CoreEngine>,
    device: DeviceChoice,
    gpu: Option<Arc<Gpu>>,
    /// The GPU drive's knobs with the chosen convolution precision.
    tuning: gagavatar_gpu::Tuning,
    /// The reconstruct pass on `gpu` (weights uploaded once).
    rec: Option<Arc<GpuReconstruct>>,
}

#[pymethods]
impl Engine {
    #[new]
    #[pyo3(signature = (ckpt, flame=None, device="cpu", preset=None, fresh_noise=false, precision="f32", gpu_precision="auto"))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        ckpt: PathBuf,
        flame: Option<PathBuf>,
        device: &str,
        preset: Option<String>,
        fresh_noise: bool,
        precision: &str,
        gpu_precision: &str,
    ) -> PyResult<Self> {
        let precision: gagavatar_avatar::Precision = precision.parse().map_err(bad)?;
        let gpu_precision: gagavatar_gpu::GpuPrecision = gpu_precision.parse().map_err(to_py)?;
        let device = match device {
            "cpu" => DeviceChoice::Cpu,
            "gpu" => DeviceChoice::Gpu,
            "auto" => DeviceChoice::Auto,
            other => {
                return Err(bad(format!(
                    "device must be cpu, gpu or auto, not `{other}`"
                )))
            }
        };
        let mut cfg = EngineConfig::new(ckpt);
        cfg.flame = flame
            .as_deref()
            .map_or(FlameSource::FromWeights, FlameSource::from_arg);
        cfg.preset = preset;
        cfg.precision = precision;
        cfg.noise = if fresh_noise {
            Noise::Fresh
        } else {
            Noise::Fixed
        };
        let inner = py.detach(|| lined(CoreEngine::open(&cfg))).map_err(bad)?;
        let gpu = match device {
            DeviceChoice::Cpu => None,
            DeviceChoice::Gpu => Some(Arc::new(
                py.detach(|| Gpu::new(AdapterPolicy::AllowCpu))
                    .map_err(to_py)?,
            )),
            DeviceChoice::Auto => py
                .detach(|| Gpu::new(AdapterPolicy::RealOnly))
                .ok()
                .map(Arc::new),
        };
        let tuning = gagavatar_gpu::Tuning::from_env().map_err(to_py)?;
        let tuning = match &gpu {
            Some(g) => tuning.with_precision(gpu_precision, g).map_err(to_py)?,
            None => tuning,
        };
        let rec = match &gpu {
            Some(g) => Some(Arc::new(
                py.detach(|| lined(inner.gpu_reconstruct(g.clone(), &tuning)))
                    .map_err(bad)?,
            )),
            None => None,
        };
        Ok(Engine {
            inner: Arc::new(inner),
            device,
            gpu,
            tuning,
            rec,
        })
    }

    /// The side of the square images the model reads and renders.
    #[getter]
    fn image_size(&self) -> usize {
        self.inner.image_size()
    }

    /// What loading noticed but did not stop for (a FLAME asset the weights were probably not
    /// trained with).
    #[getter]
    fn warnings(&self) -> Vec<String> {
        self.inner.warnings().to_vec()
    }

    /// Which FLAME asset drives the avatars.
    #[getter]
    fn flame(&self) -> String {
        self.inner.flame_label().to_string()
    }

    /// Where frames are rendered: `cpu`, or the GPU adapter's description.
    #[getter]
    fn device(&self) -> String {
        match &self.gpu {
            Some(g) => g.describe(),
            None if self.device == DeviceChoice::Auto => "cpu (no GPU adapter found)".into(),
            None => "cpu".into(),
        }
    }

    /// Reconstructs an avatar from a crop `[H, W, 3]` uint8 and its record (JSON text).
    fn _avatar_from_array(
        &self,
        py: Python<'_>,
        image: PyReadonlyArray3<'_, u8>,
        record_json: &str,
    ) -> PyResult<Avatar> {
        let img = image_from_array(&image)?;
        let record = record_from_json(record_json, "the source record")?;
        self.make_avatar(py, img, record)
    }

    /// Reconstructs an avatar from an image file (any common format) and its record (JSON).
    fn _avatar_from_file(
        &self,
        py: Python<'_>,
        path: PathBuf,
        record_json: &str,
    ) -> PyResult<Avatar> {
        let size = self.inner.image_size() as u32;
        let opts = gagavatar_formats::image::DecodeOptions {
            min_side: 1,
            fit_within: Some(4 * size),
        };
        let img = py
            .detach(|| gagavatar_formats::image::read_image(&path, &opts))
            .map_err(to_py)?
            .rgb;
        let record = record_from_json(record_json, "the source record")?;
        self.make_avatar(py, img, record)
    }

    /// Tracks a photo, a video or a folder of images into `output` (a folder), or into the
    /// tracking cache when `output` is `None` (a previous run's folder for the same bytes is
    /// reused). `progress(stage, done, total)` is called as it works.
    #[pyo3(signature = (path, output=None, progress=None))]
    fn _track_file<'py>(
        &self,
        py: Python<'py>,
        path: PathBuf,
        output: Option<PathBuf>,
        progress: Option<Py<PyAny>>,
    ) -> PyResult<TrackedTuple<'py>> {
        let to = output.map_or(TrackTo::Cache, TrackTo::Folder);
        let monitor = PyMonitor::new(progress);
        let engine = self.inner.clone();
        let r = py.detach(|| engine.track(&path, &to, &monitor).map_err(Box::new));
        let t = monitor.result(r)?;
        let kind = match t.kind {
            gagavatar_avatar::InputKind::Photo => "photo",
            gagavatar_avatar::InputKind::Video => "video",
        };
        let records = t.records.iter().map(record_to_json).collect();
        let crop = t.crop.map(|c| image_array(py, c)).transpose()?;
        Ok((
            kind,
            t.dir.display().to_string(),
            t.names,
            records,
            crop,
            t.fps,
            t.cached,
        ))
    }

    /// Tracks a photo given as an `[H, W, 3]` uint8 array, in memory: its record (JSON) and 512
    /// crop. `label` names it in "no face found in LABEL".
    fn _track_array<'py>(
        &self,
        py: Python<'py>,
        image: PyReadonlyArray3<'_, u8>,
        label: &str,
    ) -> PyResult<(String, Bound<'py, PyAny>)> {
        let img = image_from_array(&image)?;
        let engine = self.inner.clone();
        let t = py
            .detach(|| lined(engine.track_photo(&img, label)))
            .map_err(bad)?;
        let record = record_to_json(&gagavatar_avatar::cache::as_stored(t.record()));
        Ok((record, image_array(py, t.crop)?))
    }
}

/// Progress to a Python callable `progress(stage, done, total)` (total `None` when unknown),
/// and cancellation by Ctrl-C or by an exception the callable raises: the first such error is
/// kept and raised when the call returns.
struct PyMonitor {
    callback: Option<Py<PyAny>>,
    state: std::sync::Mutex<(String, Option<u64>, u64)>,
    error: std::sync::Mutex<Option<PyErr>>,
}

impl PyMonitor {
    fn new(callback: Option<Py<PyAny>>) -> Self {
        PyMonitor {
            callback,
            state: std::sync::Mutex::new((String::new(), None, 0)),
            error: std::sync::Mutex::new(None),
        }
    }
    fn fail(&self, e: PyErr) {
        let mut slot = self.error.lock().unwrap_or_else(|p| p.into_inner());
        if slot.is_none() {
            *slot = Some(e);
        }
    }
    fn report(&self) {
        let Some(cb) = &self.callback else { return };
        let (name, total, done) = self.state.lock().unwrap_or_else(|p| p.into_inner()).clone();
        Python::attach(|py| {
            if let Err(e) = cb.call1(py, (name, done, total)) {
                self.fail(e);
            }
        });
    }
    /// The kept error, else the call's own.
    fn result<T>(&self, r: Result<T, Box<gagavatar_avatar::AvatarError>>) -> PyResult<T> {
        if let Some(e) = self.error.lock().unwrap_or_else(|p| p.into_inner()).take() {
            return Err(e);
        }
        r.map_err(|e| to_py(*e))
    }
}

impl Monitor for PyMonitor {
    fn stage(&self, name: &str, total: Option<u64>) {
        *self.state.lock().unwrap_or_else(|p| p.into_inner()) = (name.to_string(), total, 0);
        self.report();
    }
    fn advance(&self, steps: u64) {
        self.state.lock().unwrap_or_else(|p| p.into_inner()).2 += steps;
        self.report();
    }
    fn cancelled(&self) -> bool {
        // Signals are delivered on the main thread only; elsewhere this is a no-op.
        if let Err(e) = Python::attach(|py| py.check_signals()) {
            self.fail(e);
        }
        self.error
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .is_some()
    }
}

/// An `[H, W, 3]` uint8 array as an image.
fn image_from_array(image: &PyReadonlyArray3<'_, u8>) -> PyResult<image::RgbImage> {
    let shape = image.shape();
    if shape[2] != 3 {
        return Err(bad(format!(
            "the image must be [H, W, 3] uint8 RGB, got {:?}",
            shape
        )));
    }
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let data: Vec<u8> = image.as_array().iter().copied().collect();
    image::RgbImage::from_raw(w, h, data)
        .ok_or_else(|| bad("the image data does not fill [H, W, 3]"))
}

fn image_array<'py>(py: Python<'py>, img: image::RgbImage) -> PyResult<Bound<'py, PyAny>> {
    let (w, h) = img.dimensions();
    Ok(PyArray1::from_vec(py, img.into_raw())
        .reshape([h as usize, w as usize, 3])?
        .into_any())
}

/// What `_track_file` returns: kind, folder, frame names, records (JSON), the photo's crop,
/// frame rate, and whether it came from the cache.
type TrackedTuple<'py> = (
    &'static str,
    String,
    Vec<String>,
    Vec<String>,
    Option<Bound<'py, PyAny>>,
    f64,
    bool,
);

impl Engine {
    fn make_avatar(
        &self,
        py: Python<'_>,
        img: image::RgbImage,
        record: TrackedFrame,
    ) -> PyResult<Avatar> {
        let engine = self.inner.clone();
        let gpu = self.gpu.clone().zip(self.rec.clone());
        let tuning = self.tuning.clone();
        py.detach(move || build_avatar(&engine, gpu, &tuning, &img, &record))
            .map_err(bad)
    }
}

/// Reconstructs an avatar and opens its drive (both on the GPU when given); errors as one
/// line.
fn build_avatar(
    engine: &CoreEngine,
    gpu: Option<(Arc<Gpu>, Arc<GpuReconstruct>)>,
    tuning: &gagavatar_gpu::Tuning,
    img: &image::RgbImage,
    record: &TrackedFrame,
) -> Result<Avatar, String> {
    let (avatar, drive) = match gpu {
        Some((g, rec)) => {
            let avatar = lined(engine.avatar_on_gpu(&rec, img, record))?;
            let drive = Drives::Gpu(Box::new(lined(avatar.gpu_drive(g, tuning))?));
            (avatar, drive)
        }
        None => {
            let avatar = lined(engine.avatar(img, record))?;
            let drive = Drives::Cpu(Box::new(avatar.cpu_drive()));
            (avatar, drive)
        }
    };
    Ok(Avatar {
        avatar,
        drive,
        library: std::time::Duration::ZERO,
    })
}

enum Drives {
    Cpu(Box<CpuDrive>),
    Gpu(Box<GpuDrive>),
}

impl Drives {
    fn get(&mut self) -> &mut dyn Drive {
        match self {
            Drives::Cpu(d) => d.as_mut(),
            Drives::Gpu(d) => d.as_mut(),
        }
    }
}

/// A reconstructed avatar and its drive.
#[pyclass(module = "gagavatar._native")]
pub struct Avatar {
    avatar: gagavatar_avatar::Avatar,
    drive: Drives,
    /// Wall time inside the library's `render_batch` calls.
    library: std::time::Duration,
}

fn watermark(frames: &mut [Vec<u8>], size: usize) {
    for f in frames {
        gagavatar_video::draw_watermark(f, size, size, gagavatar_video::WATERMARK_TEXT);
    }
}

#[pymethods]
impl Avatar {
    /// The source record (JSON text).
    fn _source_json(&self) -> String {
        record_to_json(self.avatar.source())
    }

    #[getter]
    fn image_size(&self) -> usize {
        self.avatar.image_size()
    }

    /// Frames rendered so far by this avatar's drive.
    #[getter]
    fn frames_rendered(&mut self) -> usize {
        self.drive.get().times().frames
    }

    /// Seconds spent inside the Rust library's `render_batch` (codes in, RGB frames out), for
    /// measuring what the Python layer adds.
    #[getter]
    fn library_seconds(&self) -> f64 {
        self.library.as_secs_f64()
    }

    /// Renders codes given as arrays, one row a frame: expression `[N, E]` and pose and eye
    /// codes `[N, 6]` (float32, the release's `expcode`, `posecode`, `eyecode`), cameras
    /// `[N, 3, 4]` (float64). Each row goes through the same checks as a record.
    #[pyo3(signature = (expcode, posecode, eyecode, cameras, batch=4, watermark=true))]
    #[allow(clippy::too_many_arguments)]
    fn _render_arrays<'py>(
        &mut self,
        py: Python<'py>,
        expcode: PyReadonlyArray2<'_, f32>,
        posecode: PyReadonlyArray2<'_, f32>,
        eyecode: PyReadonlyArray2<'_, f32>,
        cameras: PyReadonlyArray3<'_, f64>,
        batch: usize,
        watermark: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        let n_exp = self.avatar.flame().config.n_exp;
        let jobs = jobs_from_arrays(n_exp, &expcode, &posecode, &eyecode, &cameras)?;
        self.render_jobs(py, jobs, batch, watermark)
    }

    /// The orbit of `gagavatar orbit`: `frames` views on a figure-eight (degrees).
    #[pyo3(signature = (yaw=30.0, pitch=10.0, frames=60, batch=4, watermark=true))]
    fn orbit<'py>(
        &mut self,
        py: Python<'py>,
        yaw: f64,
        pitch: f64,
        frames: usize,
        batch: usize,
        watermark: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        if frames == 0 || !yaw.is_finite() || !pitch.is_finite() {
            return Err(bad("orbit needs frames >= 1 and finite angles"));
        }
        let base = self.avatar.source_camera().map_err(to_py)?;
        let codes = self
            .avatar
            .codes(self.avatar.source(), "the source record")
            .map_err(to_py)?;
        let jobs = orbit_cameras(&base, yaw, pitch, frames)
            .into_iter()
            .map(|c| (codes.clone(), c))
            .collect();
        self.render_jobs(py, jobs, batch, watermark)
    }

    /// Writes the avatar as a 3DGS `.ply`, the expression Gaussians placed for `record_json`
    /// (default: the source's own).
    #[pyo3(signature = (path, record_json=None))]
    fn _export_ply(
        &self,
        py: Python<'_>,
        path: PathBuf,
        record_json: Option<&str>,
    ) -> PyResult<()> {
        let record = match record_json {
            Some(t) => record_from_json(t, "the expression record")?,
            None => self.avatar.source().clone(),
        };
        let codes = self
            .avatar
            .codes(&record, "the expression record")
            .map_err(to_py)?;
        let scene = py
            .detach(|| lined(self.avatar.scene(&codes)))
            .map_err(bad)?;
        py.detach(|| scene.save_ply(&path)).map_err(to_py)
    }
}

impl Avatar {
    fn render_jobs<'py>(
        &mut self,
        py: Python<'py>,
        jobs: Vec<(FrameCodes, Camera)>,
        batch: usize,
        mark: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        if jobs.is_empty() {
            return Err(bad("nothing to render (no frames)"));
        }
        let size = self.avatar.image_size();
        let drive = &mut self.drive;
        let library = &mut self.library;
        let mut frames = py
            .detach(|| -> Result<Vec<Vec<u8>>, String> {
                let mut out = Vec::with_capacity(jobs.len());
                for chunk in jobs.chunks(batch.max(1)) {
                    let t0 = std::time::Instant::now();
                    out.extend(lined(drive.get().render_batch(chunk))?);
                    *library += t0.elapsed();
                }
                Ok(out)
            })
            .map_err(bad)?;
        if mark {
            watermark(&mut frames, size);
        }
        frames_array(py, frames, size)
    }
}

/// Frames' codes given as arrays, one row a frame: expression `[N, E]` and pose and eye codes
/// `[N, 6]` (float32), cameras `[N, 3, 4]` (float64); each row through a record's checks.
fn jobs_from_arrays(
    n_exp: usize,
    expcode: &PyReadonlyArray2<'_, f32>,
    posecode: &PyReadonlyArray2<'_, f32>,
    eyecode: &PyReadonlyArray2<'_, f32>,
    cameras: &PyReadonlyArray3<'_, f64>,
) -> PyResult<Vec<(FrameCodes, Camera)>> {
    let n = expcode.shape()[0];
    let shapes_ok =
        posecode.shape() == [n, 6] && eyecode.shape() == [n, 6] && cameras.shape() == [n, 3, 4];
    if !shapes_ok {
        return Err(bad(format!(
            "codes of {n} frames need posecode [{n}, 6], eyecode [{n}, 6] and cameras \
                 [{n}, 3, 4]; got {:?}, {:?}, {:?}",
            posecode.shape(),
            eyecode.shape(),
            cameras.shape()
        )));
    }
    let (e, p, y, c) = (
        expcode.as_array(),
        posecode.as_array(),
        eyecode.as_array(),
        cameras.as_array(),
    );
    let mut jobs: Vec<(FrameCodes, Camera)> = Vec::with_capacity(n);
    for i in 0..n {
        let mut cam = [[0.0; 4]; 3];
        for (r, row) in cam.iter_mut().enumerate() {
            for (k, v) in row.iter_mut().enumerate() {
                *v = c[[i, r, k]];
            }
        }
        let f64s = |a: &numpy::ndarray::ArrayView2<'_, f32>| -> Vec<f64> {
            a.row(i).iter().map(|&v| v as f64).collect()
        };
        let record = TrackedFrame {
            shapecode: Vec::new(),
            expcode: f64s(&e),
            posecode: f64s(&p),
            eyecode: f64s(&y),
            transform_matrix: Some(cam),
            bbox: None,
        };
        record
            .validate()
            .map_err(|err| bad(format!("frame {i}: {}", one_line(&err))))?;
        let mut expression: Vec<f32> = e.row(i).to_vec();
        if expression.len() > n_exp {
            return Err(bad(format!(
                "frame {i}: the expression (expcode) has {} values, this FLAME has {n_exp}",
                expression.len()
            )));
        }
        expression.resize(n_exp, 0.0);
        let six = |a: &numpy::ndarray::ArrayView2<'_, f32>| -> [f32; 6] {
            std::array::from_fn(|k| a[[i, k]])
        };
        let codes = FrameCodes {
            expression,
            pose: six(&p),
            eye: six(&y),
        };
        jobs.push((codes, cam));
    }
    Ok(jobs)
}

/// Frames of several avatars of one engine in one batched pass (`render_many`): frame `i` is
/// avatar `index[i]` with row `i` of the codes.
#[pyfunction]
#[pyo3(signature = (avatars, index, expcode, posecode, eyecode, cameras, watermark=true))]
#[allow(clippy::too_many_arguments)]
fn _render_many<'py>(
    py: Python<'py>,
    avatars: Vec<PyRef<'py, Avatar>>,
    index: Vec<usize>,
    expcode: PyReadonlyArray2<'_, f32>,
    posecode: PyReadonlyArray2<'_, f32>,
    eyecode: PyReadonlyArray2<'_, f32>,
    cameras: PyReadonlyArray3<'_, f64>,
    watermark: bool,
) -> PyResult<Bound<'py, PyAny>> {
    let Some(first) = avatars.first() else {
        return Err(bad("render_many needs at least one avatar"));
    };
    let n_exp = first.avatar.flame().config.n_exp;
    let size = first.avatar.image_size();
    let codes = jobs_from_arrays(n_exp, &expcode, &posecode, &eyecode, &cameras)?;
    if index.len() != codes.len() {
        return Err(bad(format!(
            "{} frames of codes but {} avatar indices",
            codes.len(),
            index.len()
        )));
    }
    let jobs: Vec<(usize, FrameCodes, Camera)> = index
        .into_iter()
        .zip(codes)
        .map(|(i, (c, cam))| (i, c, cam))
        .collect();
    let refs: Vec<&gagavatar_avatar::Avatar> = avatars.iter().map(|a| &a.avatar).collect();
    let mut frames = py
        .detach(|| lined(gagavatar_avatar::render_many(&refs, &jobs)))
        .map_err(bad)?;
    if watermark {
        self::watermark(&mut frames, size);
    }
    frames_array(py, frames, size)
}

/// A driving sequence (tracked folder, `.pkl`, JSON sequence): frame names, records (JSON) and
/// the frame rate.
#[pyfunction]
fn _read_driver(py: Python<'_>, path: PathBuf) -> PyResult<(Vec<String>, Vec<String>, f64)> {
    let seq = py
        .detach(|| gagavatar_data::DriverSequence::open(&path))
        .map_err(to_py)?;
    let names = seq.frames.iter().map(|f| f.name.clone()).collect();
    let records = seq
        .frames
        .iter()
        .map(|f| record_to_json(&f.record))
        .collect();
    Ok((names, records, seq.fps))
}

/// One record: a tracked-frame JSON, or frame `key` of a release `optim.pkl`.
#[pyfunction]
#[pyo3(signature = (path, key=None))]
fn _read_record(path: PathBuf, key: Option<&str>) -> PyResult<String> {
    let r = gagavatar_data::read_source_record(&path, key).map_err(to_py)?;
    Ok(record_to_json(&r))
}

/// Writes `[N, H, W, 3]` uint8 frames to a video (.mp4 H.264, .gif, else a folder of PNGs),
/// atomically; `watermark` draws the visible label (the frames of `render` already carry it).
#[pyfunction]
#[pyo3(signature = (path, frames, fps=25.0, watermark=false))]
fn write_video(
    py: Python<'_>,
    path: PathBuf,
    frames: PyReadonlyArray4<'_, u8>,
    fps: f64,
    watermark: bool,
) -> PyResult<()> {
    let shape = frames.shape().to_vec();
    if shape[3] != 3 || shape[0] == 0 {
        return Err(bad(format!(
            "frames must be [N >= 1, H, W, 3] uint8 RGB, got {shape:?}"
        )));
    }
    let (h, w) = (shape[1], shape[2]);
    let data: Vec<u8> = frames.as_array().iter().copied().collect();
    py.detach(|| -> Result<(), gagavatar_video::VideoError> {
        let opts = gagavatar_video::VideoOptions { fps, watermark };
        let mut writer = gagavatar_video::VideoWriter::create(&path, w, h, opts)?;
        for f in data.chunks_exact(w * h * 3) {
            writer.push_rgb(f)?;
        }
        writer.finish()
    })
    .map_err(to_py)
}

/// The shipped demo model's files (`weights.safetensors`, `source.png`, `source.json`), built
/// into the module so `Engine.demo()` needs no checkout.
#[pyfunction]
fn _demo_file(name: &str) -> PyResult<std::borrow::Cow<'static, [u8]>> {
    let bytes: &'static [u8] = match name {
        "weights.safetensors" => include_bytes!("../../assets/demo/weights.safetensors"),
        "source.png" => include_bytes!("../../assets/demo/source.png"),
        "source.json" => include_bytes!("../../assets/demo/source.json"),
        "driver.json" => include_bytes!("../../assets/demo/driver.json"),
        other => return Err(bad(format!("no demo file `{other}`"))),
    };
    Ok(std::borrow::Cow::Borrowed(bytes))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // At import, before the module starts threads of its own.
    gagavatar_gpu::device::quiet_probe_env();
    m.add("Error", m.py().get_type::<Error>())?;
    m.add_class::<Engine>()?;
    m.add_class::<Avatar>()?;
    m.add_function(wrap_pyfunction!(_read_driver, m)?)?;
    m.add_function(wrap_pyfunction!(_read_record, m)?)?;
    m.add_function(wrap_pyfunction!(write_video, m)?)?;
    m.add_function(wrap_pyfunction!(_render_many, m)?)?;
    m.add_function(wrap_pyfunction!(_demo_file, m)?)?;
    Ok(())
}
