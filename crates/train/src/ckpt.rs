//! A run folder's files and the resumable checkpoint.
//!
//! `RUN/checkpoint.safetensors` is one file (so it can be replaced atomically) holding
//! - every model weight under its checkpoint key (the release layout, f32), trainable or fixed,
//!   so a resumed run needs neither the `--init` file nor the seed's initialisation;
//! - the optimiser state under `optimizer.` (moments per parameter, per-parameter step counts
//!   and the schedule's position; see [`crate::adam::Adam::state_tensors`]);
//! - in the metadata, the model configuration (`gagavatar.config`, as every weights file has)
//!   and the training state (`gagavatar.train`, JSON [`TrainMeta`]): the step, the seed, and the
//!   effective configuration file. The random streams are pure functions of `(seed, step)`
//!   (pairs, renderer noise), so `(seed, step)` is the whole RNG state.
//!
//! `RUN/weights.safetensors` is the trained model alone in the release key layout (what
//! `gagavatar reenact --ckpt` and `load_model` read); it is derived, and rewritten with every
//! checkpoint.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use gagavatar_net::checkpoint::CONFIG_METADATA_KEY;
use gagavatar_net::ModelConfig;
use serde::{Deserialize, Serialize};

use crate::run_error::{ckpt_err, io_err, RunResult};

pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";
pub const WEIGHTS_FILE: &str = "weights.safetensors";
pub const CONFIG_FILE: &str = "config.toml";
pub const METRICS_FILE: &str = "metrics.jsonl";
/// Validation grids: `RUN/val/step_0001000.png`.
pub const VAL_DIR: &str = "val";
/// Key prefix of the optimiser state inside the checkpoint.
pub const OPTIM_PREFIX: &str = "optimizer.";
/// Metadata key of [`TrainMeta`].
pub const TRAIN_META_KEY: &str = "gagavatar.train";
/// Version of the checkpoint layout.
pub const CHECKPOINT_FORMAT: u32 = 1;

/// The training state stored beside the tensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainMeta {
    pub format: u32,
    /// Steps completed (skipped ones included); the next step's 0-based index.
    pub step: u64,
    pub seed: u64,
    /// Steps the NaN guard skipped so far.
    pub skipped_steps: u64,
    /// The run's effective configuration file.
    pub config_toml: String,
}

/// A checkpoint read back.
#[derive(Debug)]
pub struct Checkpoint {
    pub model: HashMap<String, Tensor>,
    pub optimizer: HashMap<String, Tensor>,
    pub model_config: ModelConfig,
    pub meta: TrainMeta,
}

/// One tensor for the safetensors writer; its bytes are made when written, one at a time.
struct TensorView {
    tensor: Tensor,
    shape: Vec<usize>,
    dtype: safetensors::Dtype,
}

impl TensorView {
    fn new(t: &Tensor) -> RunResult<Self> {
        let (t, dtype) = match t.dtype() {
            DType::I64 | DType::U32 | DType::U8 => {
                (t.to_dtype(DType::I64)?, safetensors::Dtype::I64)
            }
            _ => (t.to_dtype(DType::F32)?, safetensors::Dtype::F32),
        };
        Ok(Self {
            shape: t.dims().to_vec(),
            // On the host and contiguous, so `data` cannot fail.
            tensor: t.to_device(&Device::Cpu)?.contiguous()?,
            dtype,
        })
    }
}

impl safetensors::View for &TensorView {
    fn dtype(&self) -> safetensors::Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        // Conversion cannot fail for a contiguous CPU tensor of the dtype chosen in `new`;
        // an empty buffer would be caught by the size check of the writer.
        let flat = self.tensor.flatten_all();
        let bytes: Vec<u8> = match self.dtype {
            safetensors::Dtype::I64 => flat
                .and_then(|t| t.to_vec1::<i64>())
                .map(|v| v.iter().flat_map(|x| x.to_le_bytes()).collect())
                .unwrap_or_default(),
            _ => flat
                .and_then(|t| t.to_vec1::<f32>())
                .map(|v| v.iter().flat_map(|x| x.to_le_bytes()).collect())
                .unwrap_or_default(),
        };
        Cow::Owned(bytes)
    }
    fn data_len(&self) -> usize {
        let width = match self.dtype {
            safetensors::Dtype::I64 => 8,
            _ => 4,
        };
        self.shape.iter().product::<usize>() * width
    }
}

/// Writes tensors and metadata as safetensors, atomically (temp sibling + rename).
pub fn write_safetensors_atomic(
    path: &Path,
    tensors: &BTreeMap<String, Tensor>,
    metadata: HashMap<String, String>,
) -> RunResult<()> {
    let views: Vec<(String, TensorView)> = tensors
        .iter()
        .map(|(k, t)| Ok((k.clone(), TensorView::new(t)?)))
        .collect::<RunResult<_>>()?;
    let refs: Vec<(&str, &TensorView)> = views.iter().map(|(k, v)| (k.as_str(), v)).collect();
    gagavatar_formats::atomic::write_via_temp(
        path,
        |tmp| {
            safetensors::tensor::serialize_to_file(refs, Some(metadata), tmp)
                .map_err(|e| ckpt_err(path, format!("cannot write: {e}")))
        },
        |e| io_err(path, "cannot write")(e),
    )
}

/// Writes the checkpoint (see the module docs).
pub fn write_checkpoint(
    path: &Path,
    model: &BTreeMap<String, Tensor>,
    optimizer: &HashMap<String, Tensor>,
    model_config: &ModelConfig,
    meta: &TrainMeta,
) -> RunResult<()> {
    let mut all = model.clone();
    for (k, t) in optimizer {
        all.insert(format!("{OPTIM_PREFIX}{k}"), t.clone());
    }
    let mut md = HashMap::new();
    md.insert("format".to_string(), "pt".to_string());
    md.insert(
        CONFIG_METADATA_KEY.to_string(),
        serde_json::to_string(model_config).map_err(|e| ckpt_err(path, e.to_string()))?,
    );
    md.insert(
        TRAIN_META_KEY.to_string(),
        serde_json::to_string(meta).map_err(|e| ckpt_err(path, e.to_string()))?,
    );
    write_safetensors_atomic(path, &all, md)
}

/// Reads a checkpoint written by [`write_checkpoint`]; every problem is an error naming the
/// file.
pub fn read_checkpoint(path: &Path, device: &Device) -> RunResult<Checkpoint> {
    let bytes = std::fs::read(path).map_err(io_err(path, "cannot read"))?;
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes)
        .map_err(|e| ckpt_err(path, format!("not a safetensors file: {e}")))?;
    let md = header.metadata().clone().unwrap_or_default();
    let meta_json = md.get(TRAIN_META_KEY).ok_or_else(|| {
        ckpt_err(
            path,
            format!("no `{TRAIN_META_KEY}` metadata: not a training checkpoint (a weights file?)"),
        )
    })?;
    let meta: TrainMeta = serde_json::from_str(meta_json)
        .map_err(|e| ckpt_err(path, format!("`{TRAIN_META_KEY}` metadata: {e}")))?;
    if meta.format != CHECKPOINT_FORMAT {
        return Err(ckpt_err(
            path,
            format!(
                "checkpoint format {} (this build reads {CHECKPOINT_FORMAT})",
                meta.format
            ),
        ));
    }
    let model_config: ModelConfig = md
        .get(CONFIG_METADATA_KEY)
        .ok_or_else(|| ckpt_err(path, format!("no `{CONFIG_METADATA_KEY}` metadata")))
        .and_then(|j| {
            serde_json::from_str(j)
                .map_err(|e| ckpt_err(path, format!("`{CONFIG_METADATA_KEY}` metadata: {e}")))
        })?;
    let tensors = candle_core::safetensors::load_buffer(&bytes, device)
        .map_err(|e| ckpt_err(path, format!("cannot read the tensors: {e}")))?;
    let mut model = HashMap::new();
    let mut optimizer = HashMap::new();
    for (k, t) in tensors {
        match k.strip_prefix(OPTIM_PREFIX) {
            Some(rest) => {
                optimizer.insert(rest.to_string(), t);
            }
            None => {
                model.insert(k, t);
            }
        }
    }
    Ok(Checkpoint {
        model,
        optimizer,
        model_config,
        meta,
    })
}
