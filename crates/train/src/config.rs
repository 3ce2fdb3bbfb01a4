//! The training configuration: a TOML file users edit (`crates/train/configs/tiny.toml`,
//! `release.toml`; `gagavatar train --preset NAME` uses these embedded copies, `--config FILE`
//! a user's own). Two keys are required because they decide what a run costs: `[model] preset`
//! (the network size: the release's is a 6 GB model) and `[train] steps` (the run length; the
//! command line's `--steps` may give it instead). Every other key is optional and takes the
//! release recipe's value (spec section 11). Unknown keys are errors, so a typo never silently
//! trains with a default.
//!
//! `[model]` names a network preset (`release`, `small`, `tiny`) and may override any field of
//! [`ModelConfig`], including the ablation switches (`one_plane`, `no_fid_in_expression`,
//! `no_neural_renderer`) and `freeze_backbone`; the "without lifting loss" ablation is
//! `[loss] lifting = false`.
//!
//! A run stores its *effective* configuration (every value resolved, paths absolute, the decay
//! horizon fixed) as `RUN/config.toml`; resuming reads it back, so a resumed run cannot drift
//! from the one it continues.

use std::path::{Path, PathBuf};

use gagavatar_net::ModelConfig;
use serde::{Deserialize, Serialize};

use crate::adam::{AdamConfig, LrRule};
use crate::losses::LossConfig;
use crate::run_error::{config_err, io_err, RunResult};

/// The embedded preset files, by name.
pub const PRESET_FILES: [(&str, &str); 2] = [
    ("tiny", include_str!("../configs/tiny.toml")),
    ("release", include_str!("../configs/release.toml")),
];

/// `[data]`: where samples come from and how they are loaded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DataConfig {
    /// Dataset folder (release layout `img_lmdb/` + `optim.pkl` + `dataset.json`, or the folder
    /// layout `images/` + `records.json`). The CLI's `--data` sets it.
    pub dir: Option<PathBuf>,
    /// FLAME asset (`FLAME_with_eye.pt` or safetensors with its keys); absent: the built-in
    /// synthetic asset `synthesize(0)`, the one `gagavatar synth-data` renders with.
    pub flame: Option<PathBuf>,
    /// Loader threads (0: load on the training thread).
    pub workers: usize,
    /// Batches loaded ahead of the one being trained on.
    pub prefetch: usize,
    /// Probability that a training pair takes its source from another video (another
    /// identity); the release trains with same-video pairs only (0).
    pub cross_identity: f64,
    /// Decode every image the splits name before anything is written (slow on large sets).
    pub check_images: bool,
}

impl Default for DataConfig {
    fn default() -> Self {
        Self {
            dir: None,
            flame: None,
            workers: 2,
            prefetch: 4,
            cross_identity: 0.0,
            check_images: false,
        }
    }
}

/// A parameter group: names containing any of `contains` train at `lr_factor` times the base
/// rate (first matching group wins).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LrGroup {
    pub contains: Vec<String>,
    pub lr_factor: f64,
}

/// `[optim]`: Adam and its schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OptimConfig {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Steps of the linear decay to `final_factor` (absent: the run's `train.steps`, fixed
    /// when the run starts; 0: no decay).
    pub decay_steps: Option<u64>,
    pub final_factor: f64,
    pub groups: Vec<LrGroup>,
}

impl Default for OptimConfig {
    fn default() -> Self {
        Self {
            lr: 1e-4,
            beta1: 0.0,
            beta2: 0.99,
            eps: 1e-8,
            decay_steps: None,
            final_factor: 0.1,
            groups: vec![LrGroup {
                contains: vec!["style_mlp".into(), "final_linear".into()],
                lr_factor: 0.1,
            }],
        }
    }
}

/// `[loss]`: which terms and their settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LossSettings {
    /// The lifting-distance term (`false`: the paper's "without lifting loss" ablation).
    pub lifting: bool,
    /// Factor of the perceptual term.
    pub percep_weight: f64,
    /// Side of the resized head-box crops (absent: the model's image size, 512 in the release).
    pub box_size: Option<usize>,
    /// Perceptual-network weights (`percep_loss.*` keys: the release `.pt` or safetensors);
    /// absent: taken from `train.init` when it has them, else the term is off (with a warning).
    pub percep: Option<PathBuf>,
}

impl Default for LossSettings {
    fn default() -> Self {
        Self {
            lifting: true,
            percep_weight: 0.01,
            box_size: None,
            percep: None,
        }
    }
}

/// `[train]`: the loop.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoopConfig {
    /// Total optimisation steps of the run.
    pub steps: u64,
    pub batch: usize,
    /// Seeds the initial weights (without `init`), the pair sampling and the renderer noise.
    pub seed: u64,
    /// A checkpoint every this many steps (and at the end, and on Ctrl-C); 0: only then.
    pub checkpoint_every: u64,
    /// Initial weights (a release `.pt` or a safetensors checkpoint); absent: seeded random.
    pub init: Option<PathBuf>,
}

impl Default for LoopConfig {
    fn default() -> Self {
        Self {
            steps: 200_000,
            batch: 8,
            seed: 42,
            checkpoint_every: 10_000,
            init: None,
        }
    }
}

/// `[val]`: validation during training.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ValConfig {
    /// Validate every this many steps (and at the end); 0: never.
    pub every: u64,
    /// Split to validate on (`val` or `test`).
    pub split: String,
    /// Pairs validated (the release: the first 16 of the split, first frames as sources).
    pub frames: usize,
    /// Pairs shown in the grid PNG (target | coarse | fine per row).
    pub grid_rows: usize,
}

impl Default for ValConfig {
    fn default() -> Self {
        Self {
            every: 10_000,
            split: "val".into(),
            frames: 16,
            grid_rows: 4,
        }
    }
}

/// `[log]`: what `metrics.jsonl` receives.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LogConfig {
    /// Every step up to and including this one is logged.
    pub every_step_until: u64,
    /// Afterwards every this many steps (validation and checkpoint steps always).
    pub every: u64,
}

impl Default for LogConfig {
    fn default() -> Self {
        Self {
            every_step_until: 300,
            every: 100,
        }
    }
}

/// A whole training configuration with the model resolved.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainConfig {
    pub model: ModelConfig,
    pub data: DataConfig,
    pub optim: OptimConfig,
    pub loss: LossSettings,
    pub train: LoopConfig,
    pub val: ValConfig,
    pub log: LogConfig,
}

/// Every section but `[model]`, as the file spells them.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct Sections {
    data: DataConfig,
    optim: OptimConfig,
    loss: LossSettings,
    train: LoopConfig,
    val: ValConfig,
    log: LogConfig,
}

/// The file layout when writing (sections in reading order).
#[derive(Serialize)]
struct FileOut<'a> {
    model: toml::Table,
    data: &'a DataConfig,
    optim: &'a OptimConfig,
    loss: &'a LossSettings,
    train: &'a LoopConfig,
    val: &'a ValConfig,
    log: &'a LogConfig,
}

/// `[model]`: a preset (default `release`) with any fields overridden.
fn resolve_model(mut table: toml::Table, path: Option<&Path>) -> RunResult<ModelConfig> {
    let preset = match table.remove("preset") {
        None => "release".to_string(),
        Some(toml::Value::String(s)) => s,
        Some(other) => {
            return Err(config_err(
                path,
                format!("[model] preset must be a string, got {other}"),
            ))
        }
    };
    let base = ModelConfig::preset(&preset).ok_or_else(|| {
        config_err(
            path,
            format!(
                "[model] preset `{preset}` is unknown (one of {:?})",
                ModelConfig::PRESETS
            ),
        )
    })?;
    let mut merged = toml::Table::try_from(&base)
        .map_err(|e| config_err(path, format!("[model]: cannot represent the preset: {e}")))?;
    let mut known: Vec<String> = merged.keys().cloned().collect();
    known.push("freeze_backbone".into());
    for (k, v) in table {
        if !known.contains(&k) {
            known.sort();
            return Err(config_err(
                path,
                format!(
                    "[model] has no key `{k}` (keys: preset, {})",
                    known.join(", ")
                ),
            ));
        }
        merged.insert(k, v);
    }
    let cfg: ModelConfig = merged
        .try_into()
        .map_err(|e| config_err(path, format!("[model]: {e}")))?;
    cfg.validate()
        .map_err(|e| config_err(path, format!("[model]: {e}")))?;
    Ok(cfg)
}

impl TrainConfig {
    /// Parses a configuration file's text (`path` only names it in errors). `[model] preset`
    /// and `[train] steps` must be present (see the module docs).
    pub fn from_toml_str(text: &str, path: Option<&Path>) -> RunResult<Self> {
        Self::from_toml_str_with_steps(text, path, None)
    }

    /// [`TrainConfig::from_toml_str`] with the run length given separately (the command
    /// line's `--steps`): it replaces `[train] steps`, which the file may then leave out.
    pub fn from_toml_str_with_steps(
        text: &str,
        path: Option<&Path>,
        steps: Option<u64>,
    ) -> RunResult<Self> {
        let mut doc: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| config_err(path, e.to_string()))?;
        let has = |section: &str, key: &str| {
            doc.get(section)
                .and_then(|s| s.as_table())
                .is_some_and(|t| t.contains_key(key))
        };
        let mut missing = Vec::new();
        if !has("model", "preset") {
            missing.push(
                "`[model] preset` (the network size: \"tiny\" trains on a CPU, \"release\" is the \
                 paper's 6 GB model)",
            );
        }
        if !has("train", "steps") && steps.is_none() {
            missing.push("`[train] steps` (the run length; or pass --steps)");
        }
        if !missing.is_empty() {
            return Err(config_err(
                path,
                format!(
                    "the configuration does not say {}; start from crates/train/configs/tiny.toml \
                     or release.toml",
                    missing.join(" or ")
                ),
            ));
        }
        if let Some(n) = steps {
            if let Some(toml::Value::Table(t)) = doc.get_mut("train") {
                t.insert(
                    "steps".into(),
                    toml::Value::Integer(n.min(i64::MAX as u64) as i64),
                );
            } else {
                let mut t = toml::Table::new();
                t.insert(
                    "steps".into(),
                    toml::Value::Integer(n.min(i64::MAX as u64) as i64),
                );
                doc.insert("train".into(), toml::Value::Table(t));
            }
        }
        let model = match doc.remove("model") {
            None => toml::Table::new(),
            Some(toml::Value::Table(t)) => t,
            Some(_) => return Err(config_err(path, "`model` must be a table ([model])")),
        };
        let model = resolve_model(model, path)?;
        let sections: Sections = doc
            .try_into()
            .map_err(|e: toml::de::Error| config_err(path, e.to_string()))?;
        let cfg = Self {
            model,
            data: sections.data,
            optim: sections.optim,
            loss: sections.loss,
            train: sections.train,
            val: sections.val,
            log: sections.log,
        };
        cfg.validate().map_err(|e| config_err(path, e))?;
        Ok(cfg)
    }

    pub fn read(path: &Path) -> RunResult<Self> {
        Self::read_with_steps(path, None)
    }

    /// [`TrainConfig::read`] with the run length given separately (see
    /// [`TrainConfig::from_toml_str_with_steps`]).
    pub fn read_with_steps(path: &Path, steps: Option<u64>) -> RunResult<Self> {
        let text = std::fs::read_to_string(path).map_err(io_err(path, "cannot read"))?;
        Self::from_toml_str_with_steps(&text, Some(path), steps)
    }

    /// An embedded preset file (`tiny`, `release`).
    pub fn preset(name: &str) -> RunResult<Self> {
        let (_, text) = PRESET_FILES
            .iter()
            .find(|(n, _)| *n == name)
            .ok_or_else(|| {
                config_err(
                    None,
                    format!(
                        "no training preset `{name}` (one of {:?}; or pass --config FILE)",
                        PRESET_FILES.map(|(n, _)| n)
                    ),
                )
            })?;
        Self::from_toml_str(text, Some(Path::new(&format!("configs/{name}.toml"))))
    }

    /// The configuration as a TOML file (every value, `[model]` as its preset name plus every
    /// field), which [`TrainConfig::from_toml_str`] reads back to an equal configuration.
    pub fn to_toml_string(&self) -> RunResult<String> {
        let mut model = toml::Table::try_from(&self.model)
            .map_err(|e| config_err(None, format!("[model]: {e}")))?;
        if ModelConfig::preset(&self.model.name).is_some() {
            model.insert(
                "preset".into(),
                toml::Value::String(self.model.name.clone()),
            );
        } else {
            // A renamed model: its fields are complete, any preset serves as the base.
            model.insert("preset".into(), toml::Value::String("release".into()));
        }
        let out = FileOut {
            model,
            data: &self.data,
            optim: &self.optim,
            loss: &self.loss,
            train: &self.train,
            val: &self.val,
            log: &self.log,
        };
        toml::to_string_pretty(&out).map_err(|e| config_err(None, e.to_string()))
    }

    /// Checks values the loop relies on.
    pub fn validate(&self) -> Result<(), String> {
        let t = &self.train;
        let o = &self.optim;
        let check = |ok: bool, msg: String| if ok { Ok(()) } else { Err(msg) };
        check(
            t.steps > 0,
            format!("[train] steps must be > 0, got {}", t.steps),
        )?;
        check(
            t.batch > 0,
            format!("[train] batch must be > 0, got {}", t.batch),
        )?;
        // TOML integers are i64.
        check(
            i64::try_from(t.seed).is_ok(),
            format!("[train] seed must be < 2^63, got {}", t.seed),
        )?;
        check(
            o.lr >= 0.0 && o.lr.is_finite(),
            format!("[optim] lr must be >= 0, got {}", o.lr),
        )?;
        for (k, v) in [("beta1", o.beta1), ("beta2", o.beta2)] {
            check(
                (0.0..1.0).contains(&v),
                format!("[optim] {k} must be in [0, 1), got {v}"),
            )?;
        }
        check(
            o.eps > 0.0,
            format!("[optim] eps must be > 0, got {}", o.eps),
        )?;
        check(
            o.final_factor >= 0.0 && o.final_factor.is_finite(),
            format!("[optim] final_factor must be >= 0, got {}", o.final_factor),
        )?;
        for g in &o.groups {
            check(
                g.lr_factor >= 0.0 && g.lr_factor.is_finite() && !g.contains.is_empty(),
                format!("[optim] group {g:?}: needs names and a factor >= 0"),
            )?;
        }
        check(
            (0.0..=1.0).contains(&self.data.cross_identity),
            format!(
                "[data] cross_identity is a probability, got {}",
                self.data.cross_identity
            ),
        )?;
        check(
            self.data.prefetch > 0,
            "[data] prefetch must be > 0".to_string(),
        )?;
        let l = &self.loss;
        check(
            l.percep_weight >= 0.0 && l.percep_weight.is_finite(),
            format!("[loss] percep_weight must be >= 0, got {}", l.percep_weight),
        )?;
        check(
            l.box_size.is_none_or(|s| s > 0),
            "[loss] box_size must be > 0".to_string(),
        )?;
        check(
            matches!(self.val.split.as_str(), "train" | "val" | "test"),
            format!(
                "[val] split must be train, val or test, got `{}`",
                self.val.split
            ),
        )?;
        Ok(())
    }

    /// Adam's settings (the decay horizon defaults to `train.steps`).
    pub fn adam(&self) -> AdamConfig {
        let o = &self.optim;
        AdamConfig {
            lr: o.lr,
            beta1: o.beta1,
            beta2: o.beta2,
            eps: o.eps,
            total_steps: o.decay_steps.unwrap_or(self.train.steps),
            final_factor: o.final_factor,
            rules: o
                .groups
                .iter()
                .map(|g| LrRule {
                    contains: g.contains.clone(),
                    lr: o.lr * g.lr_factor,
                })
                .collect(),
        }
    }

    /// The loss settings (the box side defaults to the model's image size).
    pub fn losses(&self) -> LossConfig {
        LossConfig {
            box_size: self.loss.box_size.unwrap_or(self.model.image_size),
            lifting: self.loss.lifting,
            percep_weight: self.loss.percep_weight,
        }
    }

    /// Fixes what a resumed run must not recompute differently: the decay horizon, and paths
    /// made absolute (so the run folder works from any working directory).
    pub fn pin(&mut self) -> RunResult<()> {
        if self.optim.decay_steps.is_none() {
            self.optim.decay_steps = Some(self.train.steps);
        }
        for p in [
            &mut self.data.dir,
            &mut self.data.flame,
            &mut self.loss.percep,
            &mut self.train.init,
        ]
        .into_iter()
        .flatten()
        {
            if p.is_relative() {
                *p = std::path::absolute(&*p).map_err(io_err(p, "cannot make absolute"))?;
            }
        }
        Ok(())
    }
}
