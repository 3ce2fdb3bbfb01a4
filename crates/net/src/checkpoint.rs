//! Weights on disk: the release checkpoint (`GAGAvatar.pt`, a torch zip pickle
//! `{"model": state_dict, "meta_cfg": ...}`) and safetensors with the same keys; the expected key
//! set of a configuration; seeded random weights; atomic safetensors writing.
//!
//! The expected keys are not a hand-kept list: the model is built once with a recording
//! `VarBuilder` backend, so the loader asks for exactly what the modules ask for.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::Mutex;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use rayon::prelude::*;

use gagavatar_formats::pickle::{DictKey, PyValue};
use gagavatar_formats::safetensors::TensorOut;
use gagavatar_formats::tensor::{RawData, RawTensor};

use crate::config::ModelConfig;
use crate::error::{NetError, Result};

/// Keys of the release checkpoint that inference does not need (the frozen perceptual-loss
/// networks). They are accepted, kept by `convert`, and ignored by the model.
pub const IGNORED_PREFIXES: [&str; 1] = ["percep_loss."];
/// Safetensors metadata key holding the model configuration as JSON.
pub const CONFIG_METADATA_KEY: &str = "gagavatar.config";
/// Safetensors metadata key holding the fingerprint (16 hex digits) of the FLAME asset the
/// weights were trained with (`FlameAsset::fingerprint`).
pub const FLAME_METADATA_KEY: &str = "gagavatar.flame";
/// The release pickle nests the state dict under this key.
const RELEASE_STATE_DICT: &str = "model.";

/// A `VarBuilder` backend that records every requested (key, shape) and hands out broadcast
/// zeros, so building a model costs no weight memory. Clones share one record.
#[derive(Default, Clone)]
struct Recorder(std::sync::Arc<Mutex<KeyShapes>>);

type KeyShapes = Vec<(String, Vec<usize>)>;

impl SimpleBackend for Recorder {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        if let Ok(mut seen) = self.0.lock() {
            seen.push((name.to_string(), s.dims().to_vec()));
        }
        Tensor::zeros((), dtype, dev)?.broadcast_as(s)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("the key recorder needs a shape for `{name}`")
    }

    fn contains_tensor(&self, _: &str) -> bool {
        true
    }
}

/// A `VarBuilder` backend that hands each tensor over and forgets it. Modules that keep a
/// re-laid-out copy of a frozen weight (the ViT's transposed linears) then free the original as
/// soon as the copy exists, instead of holding both until the whole model is built: 340 MB less
/// peak memory for the release model.
struct TakingBackend(Mutex<HashMap<String, Tensor>>);

impl SimpleBackend for TakingBackend {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let t = self.get_unchecked(name, dtype, dev)?;
        if t.shape() != &s {
            candle_core::bail!(
                "weight `{name}` has shape {:?}, the model expects {:?}",
                t.dims(),
                s.dims()
            )
        }
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let t = match self.0.lock() {
            Ok(mut map) => map.remove(name),
            Err(_) => candle_core::bail!("weight map poisoned"),
        };
        match t {
            Some(t) => t.to_dtype(dtype)?.to_device(dev),
            None => candle_core::bail!("weight `{name}` is missing (or was requested twice)"),
        }
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.0.lock().map(|m| m.contains_key(name)).unwrap_or(false)
    }
}

/// Builds the model from checked weights, consuming them (see [`TakingBackend`]).
pub fn build_model(
    cfg: &ModelConfig,
    tensors: HashMap<String, Tensor>,
    device: &Device,
) -> Result<crate::model::GagAvatar> {
    build_model_as(cfg, tensors, DType::F32, device)
}

/// [`build_model`] in `dtype` (f32 or f64). Tensors already of that dtype and device are used
/// as they are, so variables among them stay variables (see [`crate::train`]).
pub fn build_model_as(
    cfg: &ModelConfig,
    mut tensors: HashMap<String, Tensor>,
    dtype: DType,
    device: &Device,
) -> Result<crate::model::GagAvatar> {
    tensors.retain(|k, _| !ignored(k));
    let vb = VarBuilder::from_backend(
        Box::new(TakingBackend(Mutex::new(tensors))),
        dtype,
        device.clone(),
    );
    crate::model::GagAvatar::new(cfg, vb)
}

/// Every key the model with `cfg` asks for, with its shape, sorted by key.
pub fn expected_keys(cfg: &ModelConfig) -> Result<BTreeMap<String, Vec<usize>>> {
    cfg.validate().map_err(NetError::Config)?;
    let rec = Recorder::default();
    let vb = VarBuilder::from_backend(Box::new(rec.clone()), DType::F32, Device::Cpu);
    crate::model::GagAvatar::new(cfg, vb)?;
    let seen = rec
        .0
        .lock()
        .map_err(|_| NetError::Config("key recorder poisoned".into()))?;
    let mut out = BTreeMap::new();
    for (k, s) in seen.iter() {
        if let Some(prev) = out.insert(k.clone(), s.clone()) {
            if &prev != s {
                return Err(NetError::Config(format!(
                    "modules ask for `{k}` with two shapes: {prev:?} and {s:?}"
                )));
            }
        }
    }
    Ok(out)
}

/// Weights read from a file, plus the configuration stored with them if any.
pub struct Weights {
    pub tensors: HashMap<String, Tensor>,
    /// From the safetensors metadata (`gagavatar.config`); `None` for the release `.pt`.
    pub config: Option<ModelConfig>,
    /// Every safetensors metadata entry (empty for the release `.pt`).
    pub metadata: BTreeMap<String, String>,
}

fn io_err(path: &Path, err: std::io::Error) -> NetError {
    NetError::Io {
        path: path.to_owned(),
        err,
    }
}

fn format_err(path: &Path, reason: impl std::fmt::Display) -> NetError {
    NetError::Format {
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

/// Reads a torch zip checkpoint (the release's `{"model": ..., "meta_cfg": ...}` or a bare state
/// dict) or a safetensors file. The pickle is only parsed as data, never executed.
pub fn read_weights(path: &Path) -> Result<Weights> {
    use std::io::Read;
    let mut head = [0u8; 4];
    let n = std::fs::File::open(path)
        .and_then(|mut f| f.read(&mut head))
        .map_err(|e| io_err(path, e))?;
    if n == 4 && &head == b"PK\x03\x04" {
        return read_torch(path);
    }
    read_safetensors_file(path)
}

fn read_torch(path: &Path) -> Result<Weights> {
    let map = gagavatar_formats::torch_zip::read_torch_zip(path)?;
    let nested = map.keys().any(|k| k.starts_with(RELEASE_STATE_DICT));
    let mut tensors = HashMap::new();
    for (key, raw) in map {
        let key = if nested {
            match key.strip_prefix(RELEASE_STATE_DICT) {
                Some(k) => k.to_string(),
                // `meta_cfg` and anything else beside the state dict.
                None => continue,
            }
        } else {
            key
        };
        let t = float_tensor(path, &key, raw)?;
        tensors.insert(key, t);
    }
    Ok(Weights {
        tensors,
        config: None,
        metadata: BTreeMap::new(),
    })
}

fn float_tensor(path: &Path, key: &str, raw: RawTensor) -> Result<Tensor> {
    match raw.data {
        RawData::Float(v) => Ok(Tensor::from_vec(v, raw.shape, &Device::Cpu)?),
        RawData::Int(_) => Err(format_err(
            path,
            format!(
                "`{key}` is an integer tensor ({}); the model's weights are floating point",
                raw.file_dtype
            ),
        )),
    }
}

fn read_safetensors_file(path: &Path) -> Result<Weights> {
    let bytes = std::fs::read(path).map_err(|e| io_err(path, e))?;
    let label = path.display().to_string();
    let header = gagavatar_formats::safetensors::read_header(&bytes, &label)
        .map_err(|e| format_err(path, format!("neither a torch zip nor safetensors: {e}")))?;
    let config = match header.metadata.get(CONFIG_METADATA_KEY) {
        Some(json) => Some(
            serde_json::from_str::<ModelConfig>(json)
                .map_err(|e| format_err(path, format!("bad `{CONFIG_METADATA_KEY}`: {e}")))?,
        ),
        None => None,
    };
    let file = gagavatar_formats::safetensors::parse_safetensors(&bytes, &label)?;
    drop(bytes);
    let mut tensors = HashMap::new();
    for (name, raw) in file.tensors {
        let t = float_tensor(path, &name, raw)?;
        let name = name
            .strip_prefix(RELEASE_STATE_DICT)
            .unwrap_or(&name)
            .to_string();
        tensors.insert(name, t);
    }
    Ok(Weights {
        tensors,
        config,
        metadata: header.metadata,
    })
}

pub(crate) fn ignored(key: &str) -> bool {
    IGNORED_PREFIXES.iter().any(|p| key.starts_with(p))
}

/// Compares `tensors` with what `cfg` expects: one error listing every missing, unexpected and
/// misshapen key (ignored prefixes such as `percep_loss.` are allowed).
pub fn check_keys(cfg: &ModelConfig, tensors: &HashMap<String, Tensor>) -> Result<()> {
    let want = expected_keys(cfg)?;
    let mut missing = Vec::new();
    let mut shape = Vec::new();
    for (k, s) in &want {
        match tensors.get(k) {
            None => missing.push(k.clone()),
            Some(t) if t.dims() != s.as_slice() => {
                shape.push(format!("{k} (expected {s:?}, found {:?})", t.dims()))
            }
            Some(_) => {}
        }
    }
    let mut extra: Vec<String> = tensors
        .keys()
        .filter(|k| !want.contains_key(*k) && !ignored(k))
        .cloned()
        .collect();
    extra.sort();
    if missing.is_empty() && extra.is_empty() && shape.is_empty() {
        return Ok(());
    }
    let list = |name: &str, v: &[String]| -> Option<String> {
        const SHOW: usize = 12;
        if v.is_empty() {
            return None;
        }
        let mut s = format!("{} {name}: {}", v.len(), v[..v.len().min(SHOW)].join(", "));
        if v.len() > SHOW {
            s.push_str(&format!(", ... ({} more)", v.len() - SHOW));
        }
        Some(s)
    };
    let summary = [
        list("missing", &missing),
        list("unexpected", &extra),
        list("misshapen", &shape),
    ]
    .into_iter()
    .flatten()
    .collect::<Vec<_>>()
    .join("; ");
    Err(NetError::Keys {
        preset: cfg.name.clone(),
        summary,
    })
}

/// Splits a seed and a key into an independent stream, so one key's values do not depend on
/// which other keys exist.
fn key_seed(seed: u64, key: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325 ^ seed.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    for b in key.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

/// How a parameter is initialised, from its name and shape.
fn init_rule(key: &str, shape: &[usize]) -> (f64, f64) {
    // (mean, std) of a normal draw.
    let last = key.rsplit('.').next().unwrap_or(key);
    let numel: usize = shape.iter().product();
    if key.contains("noises.noise") || key.ends_with("constant_input.weight") {
        return (0.0, 1.0);
    }
    if key.ends_with("modulation.bias") {
        // StyleGAN2 starts styles at 1 so modulation is the identity.
        return (1.0, 0.05);
    }
    if key == "head_base" {
        return (0.0, 0.5);
    }
    match last {
        "cls_token" | "pos_embed" | "mask_token" => (0.0, 0.02),
        "gamma" => (0.1, 0.02),
        "bias" => (0.0, 0.02),
        "weight" if shape.len() <= 1 && numel == 1 => (0.1, 0.0), // StyleConv noise strength
        "weight" if shape.len() <= 1 => (1.0, 0.05),              // LayerNorm
        "weight" => {
            // He-style fan-in scaling: [out, in, k, k], [1, out, in, k, k] (modulated),
            // [in, out, k, k] for the transposed convs (every output sees `in` inputs).
            let fan_in = if key.contains("resize_layers.0.") || key.contains("resize_layers.1.") {
                shape[0]
            } else if shape.len() == 5 {
                shape[2..].iter().product()
            } else {
                shape[1..].iter().product()
            };
            (0.0, (1.0 / fan_in.max(1) as f64).sqrt())
        }
        _ => (0.0, 0.02),
    }
}

/// Weights as plain data: key -> (shape, row-major values).
pub type WeightData = BTreeMap<String, (Vec<usize>, Vec<f32>)>;

/// Seeded random weights for every key of `cfg`, with realistic magnitudes.
pub fn init_weights(cfg: &ModelConfig, seed: u64) -> Result<WeightData> {
    init_weights_where(cfg, seed, &|_| true)
}

/// [`init_weights`] for the keys `keep` accepts only (each key's values depend on the seed and
/// the key alone, so they are the same as in the full set).
pub fn init_weights_where(
    cfg: &ModelConfig,
    seed: u64,
    keep: &(dyn Fn(&str) -> bool + Sync),
) -> Result<WeightData> {
    let mut keys = expected_keys(cfg)?;
    keys.retain(|k, _| keep(k));
    Ok(keys
        .into_par_iter()
        .map(|(k, shape)| {
            let (mean, std) = init_rule(&k, &shape);
            let n: usize = shape.iter().product();
            let mut rng = gagavatar_splat::testscene::Rng::new(key_seed(seed, &k));
            let v = (0..n).map(|_| (mean + std * rng.normal()) as f32).collect();
            (k, (shape, v))
        })
        .collect())
}

/// The safetensors metadata written with weights: `format: pt` (what other tools expect) and
/// the configuration, when given.
fn weights_metadata(config: Option<&ModelConfig>) -> Result<BTreeMap<String, String>> {
    let mut meta = BTreeMap::new();
    meta.insert("format".to_string(), "pt".to_string());
    if let Some(cfg) = config {
        let json = serde_json::to_string(cfg).map_err(|e| NetError::Config(e.to_string()))?;
        meta.insert(CONFIG_METADATA_KEY.to_string(), json);
    }
    Ok(meta)
}

/// Writes f32 tensors as safetensors atomically (temp file + rename), with `config` in the
/// metadata when given.
pub fn write_safetensors<'a>(
    path: &Path,
    tensors: impl IntoIterator<Item = (String, &'a [usize], Cow<'a, [f32]>)>,
    config: Option<&ModelConfig>,
) -> Result<()> {
    let out: Vec<TensorOut> = tensors
        .into_iter()
        .map(|(k, shape, data)| TensorOut::f32(k, shape.to_vec(), data))
        .collect();
    let meta = weights_metadata(config)?;
    Ok(gagavatar_formats::safetensors::write_safetensors(
        path, &out, &meta,
    )?)
}

/// Writes candle tensors (converted to f32) as safetensors atomically.
pub fn write_tensors(
    path: &Path,
    tensors: &BTreeMap<String, Tensor>,
    config: Option<&ModelConfig>,
) -> Result<()> {
    write_tensors_with_metadata(path, tensors, config, &BTreeMap::new())
}

/// [`write_tensors`] with further metadata entries (e.g. [`FLAME_METADATA_KEY`]).
pub fn write_tensors_with_metadata(
    path: &Path,
    tensors: &BTreeMap<String, Tensor>,
    config: Option<&ModelConfig>,
    extra: &BTreeMap<String, String>,
) -> Result<()> {
    let mut owned = Vec::with_capacity(tensors.len());
    for (k, t) in tensors {
        let v: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        owned.push((k.clone(), t.dims().to_vec(), v));
    }
    let out: Vec<TensorOut> = owned
        .iter()
        .map(|(k, s, v)| TensorOut::f32(k.clone(), s.clone(), v.as_slice()))
        .collect();
    let mut meta = weights_metadata(config)?;
    meta.extend(extra.iter().map(|(k, v)| (k.clone(), v.clone())));
    Ok(gagavatar_formats::safetensors::write_safetensors(
        path, &out, &meta,
    )?)
}

/// Writes `tensors` (converted to f32, row-major, one at a time) as a torch zip checkpoint
/// `{"model": state_dict, "meta_cfg": config}` that the release's Python code loads with
/// `torch.load`, atomically. `meta_cfg` is the configuration as a plain dict, or None.
pub fn write_torch_checkpoint(
    path: &Path,
    tensors: &BTreeMap<String, Tensor>,
    config: Option<&ModelConfig>,
) -> Result<()> {
    let cfg = config
        .map(serde_json::to_value)
        .transpose()
        .map_err(|e| NetError::Config(e.to_string()))?
        .map(|v| json_to_plain(&v));
    let shapes: Vec<(String, Vec<usize>)> = tensors
        .iter()
        .map(|(k, t)| (k.clone(), t.dims().to_vec()))
        .collect();
    let entries: Vec<(&str, &[usize])> = shapes
        .iter()
        .map(|(k, s)| (k.as_str(), s.as_slice()))
        .collect();
    let values: Vec<&Tensor> = tensors.values().collect();
    Ok(gagavatar_formats::torch_zip::write_torch_zip(
        path,
        &entries,
        cfg.as_ref(),
        |i| {
            values[i]
                .to_dtype(DType::F32)
                .and_then(|t| t.flatten_all())
                .and_then(|t| t.to_vec1::<f32>())
                .map_err(|e| e.to_string())
        },
    )?)
}

/// JSON (the configuration) as plain Python data.
fn json_to_plain(v: &serde_json::Value) -> PyValue {
    use serde_json::Value;
    match v {
        Value::Null => PyValue::None,
        Value::Bool(b) => PyValue::Bool(*b),
        Value::Number(n) => match n.as_i64() {
            Some(i) => PyValue::Int(i),
            None => PyValue::Float(n.as_f64().unwrap_or(f64::NAN)),
        },
        Value::String(s) => PyValue::Str(s.clone()),
        Value::Array(items) => PyValue::List(items.iter().map(json_to_plain).collect()),
        Value::Object(map) => PyValue::Dict(
            map.iter()
                .map(|(k, v)| (DictKey::Str(k.clone()), json_to_plain(v)))
                .collect(),
        ),
    }
}

/// Which configuration a weights file is for: an explicit choice wins, then the file's
/// metadata, then the release architecture (the `.pt` carries none we can use).
pub fn resolve_config(weights: &Weights, explicit: Option<&ModelConfig>) -> ModelConfig {
    explicit
        .cloned()
        .or_else(|| weights.config.clone())
        .unwrap_or_else(ModelConfig::release)
}

/// Reads weights, checks them against the configuration and builds the model.
pub fn load_model(
    path: &Path,
    explicit: Option<&ModelConfig>,
    device: &Device,
) -> Result<crate::model::GagAvatar> {
    let weights = read_weights(path)?;
    let cfg = resolve_config(&weights, explicit);
    check_keys(&cfg, &weights.tensors)?;
    build_model(&cfg, weights.tensors, device)
}
