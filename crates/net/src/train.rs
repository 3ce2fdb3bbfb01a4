//! The network as a trainable model (spec 11): every trained parameter is a candle `Var` in a
//! `VarMap` under its checkpoint key, so an optimiser can group parameters by name (the release
//! gives `style_mlp` and `final_linear` a tenth of the learning rate) and a trained model is
//! written back in the release key layout.
//!
//! What is not trained stays a fixed tensor outside the `VarMap`: the DINOv2 backbone when the
//! configuration freezes it ([`ModelConfig::backbone_frozen`], the release), which then also
//! keeps the fused inference kernels and receives no gradient; and the renderer's noise
//! buffers, which are buffers (not parameters) in the release. The perceptual-loss networks
//! (`percep_loss.*`) are never part of the model.
//!
//! The modules only hold views of the variables (no re-laid-out copies), so an optimiser's
//! in-place `Var::set` is what the next forward computes with.

use std::collections::{BTreeMap, HashMap};

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;

use crate::checkpoint::{build_model_as, check_keys, expected_keys, ignored, init_weights};
use crate::config::ModelConfig;
use crate::error::{NetError, Result};
use crate::model::GagAvatar;

pub use crate::config::{BACKBONE_PREFIX, NOISE_BUFFER_PREFIX};

/// Whether the checkpoint key `key` is a trained parameter of the model with `cfg`.
pub fn is_trainable_key(cfg: &ModelConfig, key: &str) -> bool {
    !(ignored(key)
        || key.starts_with(NOISE_BUFFER_PREFIX)
        || (cfg.backbone_frozen() && key.starts_with(BACKBONE_PREFIX)))
}

fn lock_err() -> NetError {
    NetError::Config("the VarMap lock is poisoned".into())
}

/// A float32 trainable model: see [`trainable_model_as`].
pub fn trainable_model(
    cfg: &ModelConfig,
    init: Option<HashMap<String, Tensor>>,
    seed: u64,
    device: &Device,
) -> Result<(GagAvatar, VarMap)> {
    trainable_model_as(cfg, init, seed, DType::F32, device)
}

/// The model with `cfg` in `dtype` (f32 or f64) and the `VarMap` of its trained parameters
/// (see [`is_trainable_key`]). Weights come from `init` (a checkpoint's tensors, e.g.
/// [`crate::checkpoint::read_weights`]; checked against `cfg`, `percep_loss.*` dropped) or,
/// when `None`, from [`init_weights`] with `seed`. The variables are copies: `init` itself is
/// never modified by training.
pub fn trainable_model_as(
    cfg: &ModelConfig,
    init: Option<HashMap<String, Tensor>>,
    seed: u64,
    dtype: DType,
    device: &Device,
) -> Result<(GagAvatar, VarMap)> {
    if !matches!(dtype, DType::F32 | DType::F64) {
        return Err(NetError::Config(format!(
            "a trainable model is f32 or f64, not {dtype:?}"
        )));
    }
    cfg.validate().map_err(NetError::Config)?;
    let tensors = match init {
        Some(mut t) => {
            t.retain(|k, _| !ignored(k));
            check_keys(cfg, &t)?;
            t
        }
        None => init_weights(cfg, seed)?
            .into_iter()
            .map(|(k, (shape, v))| Ok((k, Tensor::from_vec(v, shape, &Device::Cpu)?)))
            .collect::<Result<HashMap<_, _>>>()?,
    };
    let varmap = VarMap::new();
    let mut model_tensors = HashMap::with_capacity(tensors.len());
    {
        let mut vars = varmap.data().lock().map_err(|_| lock_err())?;
        for (k, t) in tensors {
            let t = t.to_dtype(dtype)?.to_device(device)?;
            if is_trainable_key(cfg, &k) {
                // `detach` first so that `from_tensor` always copies (it would share the
                // storage of a tensor that is already a variable).
                let var = Var::from_tensor(&t.detach())?;
                model_tensors.insert(k.clone(), var.as_tensor().clone());
                vars.insert(k, var);
            } else {
                model_tensors.insert(k, t);
            }
        }
    }
    let model = build_model_as(cfg, model_tensors, dtype, device)?;
    Ok((model, varmap))
}

/// Every weight of a trained model under its checkpoint key, in the checkpoint's layout: the
/// variables of `varmap` (copied, so later updates do not change the result) and the model's
/// fixed weights (frozen backbone, noise buffers). The key set and shapes are checked against
/// the model's configuration, so the result written with
/// [`crate::checkpoint::write_tensors`] loads back through [`crate::checkpoint::load_model`].
pub fn export_weights(model: &GagAvatar, varmap: &VarMap) -> Result<BTreeMap<String, Tensor>> {
    let mut out = BTreeMap::new();
    {
        let vars = varmap.data().lock().map_err(|_| lock_err())?;
        for (k, v) in vars.iter() {
            out.insert(k.clone(), v.as_tensor().detach().copy()?);
        }
    }
    for (k, t) in model.fixed_weights()? {
        // Fixed tensors never change, so they need no copy.
        out.entry(k).or_insert(t);
    }
    let want = expected_keys(&model.cfg)?;
    let mut problems = Vec::new();
    for (k, shape) in &want {
        match out.get(k) {
            None => problems.push(format!("missing {k}")),
            Some(t) if t.dims() != shape.as_slice() => {
                problems.push(format!("{k} is {:?}, expected {shape:?}", t.dims()))
            }
            Some(_) => {}
        }
    }
    problems.extend(
        out.keys()
            .filter(|k| !want.contains_key(*k))
            .map(|k| format!("unexpected {k}")),
    );
    if problems.is_empty() {
        Ok(out)
    } else {
        Err(NetError::Keys {
            preset: model.cfg.name.clone(),
            summary: problems.join("; "),
        })
    }
}
