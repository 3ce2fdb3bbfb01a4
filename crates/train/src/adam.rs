//! Adam with the release's parameter groups and learning-rate schedule (spec section 11).
//!
//! - Update: `torch.optim.Adam` without weight decay or amsgrad, per parameter:
//!   `m = b1 m + (1 - b1) g`, `v = b2 v + (1 - b2) g^2`, `t += 1`,
//!   `p -= lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)`. The release uses
//!   betas (0.0, 0.99), eps 1e-8.
//! - Groups: a parameter takes the learning rate of the first [`LrRule`] with a substring in its
//!   name, else the base rate. The release: base 1e-4; names containing `style_mlp` or
//!   `final_linear` 1e-5 (its third group, `gaussian_conv` and the `gs_generator_g` heads, uses
//!   the base rate, so it needs no rule).
//! - Schedule: the release's `LinearLR(start_factor=1, end_factor=0.1, total_iters=T)`, stepped
//!   once after every optimiser step. Step `k` (0-based: the k-th call of [`Adam::step`]) uses
//!   `lr_k = lr0 * (1 - 0.9 min(k, T) / T)`, so step 0 uses `lr0` and steps from `T` on use
//!   `0.1 lr0`. (PyTorch evaluates the same line through a chain of ratios; they agree to
//!   ~1e-15 relative.)
//! - A parameter without a gradient in the [`GradStore`] is skipped: no moment update and no
//!   increase of its own `t` (PyTorch skips `grad is None` the same way). The schedule advances
//!   on every call regardless.
//! - State ([`Adam::state_tensors`] / [`Adam::load_state`]): per parameter `m`, `v` and its
//!   step count, plus the schedule's step, so a resumed run continues bit for bit.

use std::collections::HashMap;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};

use crate::error::{Result, TrainError};

/// Learning rate of the parameters whose name contains any of `contains`.
#[derive(Debug, Clone, PartialEq)]
pub struct LrRule {
    pub contains: Vec<String>,
    pub lr: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct AdamConfig {
    /// Base learning rate.
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Steps of the linear decay `T` (0: no decay).
    pub total_steps: u64,
    /// Factor reached at step `T` and kept after it.
    pub final_factor: f64,
    /// Group rules, first match wins.
    pub rules: Vec<LrRule>,
}

impl AdamConfig {
    /// The release's settings with decay over `total_steps` (200,000 in the release).
    pub fn release(total_steps: u64) -> Self {
        Self::with_lr(1e-4, total_steps)
    }

    /// The release's groups, betas, eps and decay with base rate `lr` (the low group at
    /// `0.1 lr`).
    pub fn with_lr(lr: f64, total_steps: u64) -> Self {
        Self {
            lr,
            beta1: 0.0,
            beta2: 0.99,
            eps: 1e-8,
            total_steps,
            final_factor: 0.1,
            rules: vec![LrRule {
                contains: vec!["style_mlp".into(), "final_linear".into()],
                lr: lr * 0.1,
            }],
        }
    }

    /// The schedule's factor at step `k` (0-based).
    pub fn factor(&self, k: u64) -> f64 {
        if self.total_steps == 0 {
            return 1.0;
        }
        let frac = k.min(self.total_steps) as f64 / self.total_steps as f64;
        1.0 - (1.0 - self.final_factor) * frac
    }

    /// The initial learning rate of parameter `name`.
    pub fn base_lr(&self, name: &str) -> f64 {
        self.rules
            .iter()
            .find(|r| r.contains.iter().any(|c| name.contains(c.as_str())))
            .map_or(self.lr, |r| r.lr)
    }
}

#[derive(Debug)]
struct Param {
    name: String,
    var: Var,
    lr0: f64,
    /// `(m, v)`, created at the parameter's first update (as PyTorch's lazy state).
    moments: Option<(Tensor, Tensor)>,
    step: u64,
}

/// Adam over named candle variables.
#[derive(Debug)]
pub struct Adam {
    cfg: AdamConfig,
    params: Vec<Param>,
    /// Calls of [`Adam::step`] so far (the schedule's position).
    t: u64,
    skipped: Vec<String>,
}

/// State key of the schedule's step count.
pub const SCHEDULE_STEP_KEY: &str = "adam.schedule_step";
const SUFFIX_M: &str = ".exp_avg";
const SUFFIX_V: &str = ".exp_avg_sq";
const SUFFIX_STEP: &str = ".step";

fn state_err(msg: impl Into<String>) -> TrainError {
    TrainError::State(msg.into())
}

impl Adam {
    /// `params`: (name, variable) pairs, names unique (e.g. a `VarMap`'s entries; pass only
    /// trainable ones, or pass all and check [`Adam::skipped`] for the frozen ones).
    pub fn new(params: impl IntoIterator<Item = (String, Var)>, cfg: AdamConfig) -> Result<Self> {
        let mut ps: Vec<Param> = Vec::new();
        for (name, var) in params {
            if !matches!(var.dtype(), DType::F32 | DType::F64) {
                return Err(state_err(format!(
                    "parameter `{name}` is {:?}; Adam needs f32 or f64",
                    var.dtype()
                )));
            }
            let lr0 = cfg.base_lr(&name);
            ps.push(Param {
                name,
                var,
                lr0,
                moments: None,
                step: 0,
            });
        }
        // Sorted names: a deterministic order for updates and state.
        ps.sort_by(|a, b| a.name.cmp(&b.name));
        if let Some(w) = ps.windows(2).find(|w| w[0].name == w[1].name) {
            return Err(state_err(format!(
                "parameter `{}` is given twice",
                w[0].name
            )));
        }
        for (k, v) in [("beta1", cfg.beta1), ("beta2", cfg.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return Err(state_err(format!("{k} = {v} must be in [0, 1)")));
            }
        }
        if !(cfg.eps > 0.0 && cfg.lr >= 0.0 && cfg.final_factor >= 0.0) {
            return Err(state_err(format!(
                "eps {} must be > 0, lr {} and final_factor {} >= 0",
                cfg.eps, cfg.lr, cfg.final_factor
            )));
        }
        Ok(Self {
            cfg,
            params: ps,
            t: 0,
            skipped: Vec::new(),
        })
    }

    pub fn config(&self) -> &AdamConfig {
        &self.cfg
    }

    /// Calls of [`Adam::step`] so far.
    pub fn schedule_step(&self) -> u64 {
        self.t
    }

    /// The learning rate parameter `name` gets at the next step (`None` if unknown).
    pub fn lr(&self, name: &str) -> Option<f64> {
        self.params
            .iter()
            .find(|p| p.name == name)
            .map(|p| p.lr0 * self.cfg.factor(self.t))
    }

    /// Names of the parameters, in update order.
    pub fn names(&self) -> Vec<&str> {
        self.params.iter().map(|p| p.name.as_str()).collect()
    }

    /// Parameters that got no gradient at the last [`Adam::step`] (so were not updated).
    pub fn skipped(&self) -> &[String] {
        &self.skipped
    }

    /// One update from the gradients of a backward pass; then advances the schedule.
    /// Errors (before changing anything) on a gradient of the wrong shape.
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        for p in &self.params {
            if let Some(g) = grads.get(p.var.as_tensor()) {
                if g.dims() != p.var.dims() {
                    return Err(state_err(format!(
                        "gradient of `{}` has shape {:?}, the parameter {:?}",
                        p.name,
                        g.dims(),
                        p.var.dims()
                    )));
                }
            }
        }
        let factor = self.cfg.factor(self.t);
        let (b1, b2, eps) = (self.cfg.beta1, self.cfg.beta2, self.cfg.eps);
        self.skipped.clear();
        for p in &mut self.params {
            let Some(g) = grads.get(p.var.as_tensor()) else {
                self.skipped.push(p.name.clone());
                continue;
            };
            let g = g.detach().to_dtype(p.var.dtype())?;
            let (m, v) = match p.moments.take() {
                Some((m, v)) => (m, v),
                None => (g.zeros_like()?, g.zeros_like()?),
            };
            let m = ((m * b1)? + (&g * (1.0 - b1))?)?;
            let v = ((v * b2)? + (g.sqr()? * (1.0 - b2))?)?;
            p.step += 1;
            let bc1 = 1.0 - b1.powf(p.step as f64);
            let bc2_sqrt = (1.0 - b2.powf(p.step as f64)).sqrt();
            let step_size = p.lr0 * factor / bc1;
            let denom = ((v.sqrt()? / bc2_sqrt)? + eps)?;
            let update = (m.div(&denom)? * step_size)?;
            let next = p.var.as_tensor().detach().sub(&update)?;
            p.var.set(&next)?;
            p.moments = Some((m, v));
        }
        self.t += 1;
        Ok(())
    }

    /// The optimiser state: `{name}.exp_avg`, `{name}.exp_avg_sq` (the parameter's shape and
    /// dtype) and `{name}.step` (`[1]` i64) for every parameter updated at least once, and
    /// [`SCHEDULE_STEP_KEY`] (`[1]` i64). Tensors stay on the parameters' devices.
    pub fn state_tensors(&self) -> Result<HashMap<String, Tensor>> {
        let mut out = HashMap::new();
        let count = |n: u64| -> Result<Tensor> {
            let n = i64::try_from(n).map_err(|_| state_err("step count exceeds i64"))?;
            Ok(Tensor::new(&[n], &Device::Cpu)?)
        };
        for p in &self.params {
            if let Some((m, v)) = &p.moments {
                out.insert(format!("{}{SUFFIX_M}", p.name), m.clone());
                out.insert(format!("{}{SUFFIX_V}", p.name), v.clone());
                out.insert(format!("{}{SUFFIX_STEP}", p.name), count(p.step)?);
            }
        }
        out.insert(SCHEDULE_STEP_KEY.to_string(), count(self.t)?);
        Ok(out)
    }

    /// Restores a state written by [`Adam::state_tensors`] (e.g. via safetensors). Every key
    /// must belong to a known parameter with the right shape, and each parameter has all three
    /// entries or none; errors list every problem and leave the optimiser unchanged.
    pub fn load_state(&mut self, state: &HashMap<String, Tensor>) -> Result<()> {
        let read_count = |t: &Tensor, key: &str| -> Result<u64> {
            let v: Vec<i64> = t
                .to_dtype(DType::I64)?
                .flatten_all()?
                .to_vec1()
                .map_err(|e| state_err(format!("`{key}`: {e}")))?;
            match v.as_slice() {
                [n] if *n >= 0 => Ok(*n as u64),
                _ => Err(state_err(format!(
                    "`{key}` must hold one count >= 0, got {v:?}"
                ))),
            }
        };
        let mut problems = Vec::new();
        let mut known = std::collections::HashSet::new();
        known.insert(SCHEDULE_STEP_KEY.to_string());
        let mut restored: Vec<Option<(Tensor, Tensor, u64)>> =
            Vec::with_capacity(self.params.len());
        for p in &self.params {
            let keys = [SUFFIX_M, SUFFIX_V, SUFFIX_STEP].map(|s| format!("{}{s}", p.name));
            let found: Vec<Option<&Tensor>> = keys.iter().map(|k| state.get(k)).collect();
            keys.iter().for_each(|k| {
                known.insert(k.clone());
            });
            match (found[0], found[1], found[2]) {
                (None, None, None) => restored.push(None),
                (Some(m), Some(v), Some(s)) => {
                    for (t, k) in [(m, &keys[0]), (v, &keys[1])] {
                        if t.dims() != p.var.dims() {
                            problems.push(format!(
                                "`{k}` has shape {:?}, the parameter {:?}",
                                t.dims(),
                                p.var.dims()
                            ));
                        }
                    }
                    let step = match read_count(s, &keys[2]) {
                        Ok(n) => n,
                        Err(e) => {
                            problems.push(e.to_string());
                            0
                        }
                    };
                    let dev = p.var.device();
                    let dt = p.var.dtype();
                    restored.push(Some((
                        m.to_device(dev)?.to_dtype(dt)?,
                        v.to_device(dev)?.to_dtype(dt)?,
                        step,
                    )));
                }
                _ => {
                    problems.push(format!("parameter `{}` has only some of {keys:?}", p.name));
                    restored.push(None);
                }
            }
        }
        let mut unknown: Vec<&String> = state.keys().filter(|k| !known.contains(*k)).collect();
        unknown.sort();
        if !unknown.is_empty() {
            problems.push(format!("keys of no parameter: {unknown:?}"));
        }
        let t = match state.get(SCHEDULE_STEP_KEY) {
            Some(s) => read_count(s, SCHEDULE_STEP_KEY).unwrap_or_else(|e| {
                problems.push(e.to_string());
                0
            }),
            None => {
                problems.push(format!("`{SCHEDULE_STEP_KEY}` is missing"));
                0
            }
        };
        if !problems.is_empty() {
            return Err(state_err(problems.join("; ")));
        }
        for (p, r) in self.params.iter_mut().zip(restored) {
            match r {
                Some((m, v, step)) => {
                    p.moments = Some((m, v));
                    p.step = step;
                }
                None => {
                    p.moments = None;
                    p.step = 0;
                }
            }
        }
        self.t = t;
        self.skipped.clear();
        Ok(())
    }
}
