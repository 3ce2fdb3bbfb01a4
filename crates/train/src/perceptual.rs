//! The frozen perceptual distance of the box loss (spec section 11), with the weights the
//! release stores under `percep_loss.*`: AlexNet features (`net.slice1..5`, torchvision
//! `AlexNet.features` indices) and VGG-Face (VGG16 `features`, `vggface.network.*`).
//!
//! The spec leaves the distance open; this is the release's own (`FacePerceptualLoss` with
//! `loss_type='l1', weighted=True`), so the pretrained weights meet the distance they were
//! trained with:
//!
//! - AlexNet input: ImageNet normalisation `(x - mean) / std`; features after each of the five
//!   slices (`relu(conv1)`, `relu(conv2(maxpool(.)))`, `relu(conv3(maxpool(.)))`,
//!   `relu(conv4)`, `relu(conv5)`; max-pools 3x3 stride 2).
//! - VGG-Face input: `255 x - (129.186279296875, 104.76238250732422, 93.59396362304688)` (RGB,
//!   unit std); features `relu_1_1, relu_2_1, relu_3_1, relu_4_1, relu_5_1` (outputs of layers
//!   1, 6, 11, 18, 25; max-pools 2x2 stride 2). Layers 26 and 28 (`conv5_2`, `conv5_3`) exist in
//!   the checkpoint but lie past `relu_5_1`, so they are neither loaded nor run.
//! - Per layer `l` (weights `w = (0.1, 0.1, 1, 1, 1)`): unit-normalise both feature maps over
//!   channels (`f / (|f| + 1e-10)`), take `|a - b|`, **sum over channels, mean over batch and
//!   positions**, times `w_l` for AlexNet and `0.5 w_l` for VGG-Face; the distance is the sum
//!   over the ten terms. See [`layer_distance`].
//!
//! One deliberate difference from PyTorch: the channel norm is `sqrt(sum f^2 + 1e-20)`, because
//! PyTorch's `sqrt` has a NaN gradient at an all-zero feature vector (PyTorch later masks it in
//! the ReLU backward; a product with a mask would keep the NaN). The values agree to f32
//! precision (`sum f^2 + 1e-20 == sum f^2` unless `sum f^2 < ~1e-13`). As in PyTorch, `|d|`
//! has gradient `sign(d)` with `sign(0) = 0` (candle's `abs` uses +1 at 0), and ReLU passes no
//! gradient at 0.
//!
//! The weights are plain tensors, not variables, so the backward pass computes only input
//! gradients (the convolution op skips weight gradients for untracked weights). ReLU, max-pool
//! and the layer distance are fused CPU kernels ([`crate::kernels`]).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use gagavatar_net::layers::Conv2d;
use rayon::prelude::*;

use crate::error::{input_err, Result, TrainError};
pub use crate::kernels::{
    layer_distance, layer_distance_portable, maxpool2d, maxpool2d_portable, relu, NORM_EPS,
    NORM_SQRT_EPS,
};

/// Prefix of the perceptual networks' keys in the release checkpoint.
pub const PERCEP_PREFIX: &str = "percep_loss.";
/// Per-layer weights (`weighted=True`).
pub const LAYER_WEIGHTS: [f64; 5] = [0.1, 0.1, 1.0, 1.0, 1.0];
/// Extra factor of the VGG-Face terms.
pub const VGG_FACTOR: f64 = 0.5;
pub const IMAGENET_MEAN: [f64; 3] = [0.485, 0.456, 0.406];
pub const IMAGENET_STD: [f64; 3] = [0.229, 0.224, 0.225];
pub const VGGFACE_MEAN: [f64; 3] = [129.186279296875, 104.76238250732422, 93.59396362304688];

/// AlexNet convolutions: (key, cin, cout, kernel, stride, padding, max-pool before).
pub const ALEX: [(&str, usize, usize, usize, usize, usize, bool); 5] = [
    ("net.slice1.0", 3, 64, 11, 4, 2, false),
    ("net.slice2.3", 64, 192, 5, 1, 2, true),
    ("net.slice3.6", 192, 384, 3, 1, 1, true),
    ("net.slice4.8", 384, 256, 3, 1, 1, false),
    ("net.slice5.10", 256, 256, 3, 1, 1, false),
];

/// VGG16 convolutions: (features index, cin, cout). All 3x3, padding 1.
pub const VGG: [(usize, usize, usize); 13] = [
    (0, 3, 64),
    (2, 64, 64),
    (5, 64, 128),
    (7, 128, 128),
    (10, 128, 256),
    (12, 256, 256),
    (14, 256, 256),
    (17, 256, 512),
    (19, 512, 512),
    (21, 512, 512),
    (24, 512, 512),
    (26, 512, 512),
    (28, 512, 512),
];
/// The VGG convolutions run (up to `relu_5_1`), grouped by the feature each block ends with;
/// a 2x2 max-pool precedes every block but the first.
pub const VGG_BLOCKS: [&[usize]; 5] = [&[0], &[2, 5], &[7, 10], &[12, 14, 17], &[19, 21, 24]];

/// Every key (under `percep_loss.`) of the release's perceptual networks with its shape,
/// including the two VGG layers the loss never runs.
pub fn expected_keys() -> Vec<(String, Vec<usize>)> {
    let mut out = Vec::new();
    let mut push = |name: String, cin: usize, cout: usize, k: usize| {
        out.push((format!("{name}.weight"), vec![cout, cin, k, k]));
        out.push((format!("{name}.bias"), vec![cout]));
    };
    for (name, cin, cout, k, ..) in ALEX {
        push(name.to_string(), cin, cout, k);
    }
    for (idx, cin, cout) in VGG {
        push(format!("vggface.network.{idx}"), cin, cout, 3);
    }
    out
}

/// Feature maps of both networks for one image batch.
#[derive(Debug, Clone)]
pub struct PerceptualFeatures {
    pub alex: Vec<Tensor>,
    pub vgg: Vec<Tensor>,
}

/// The frozen AlexNet + VGG-Face perceptual distance.
#[derive(Debug, Clone)]
pub struct PerceptualLoss {
    alex: Vec<Conv2d>,
    /// The VGG convolutions of [`VGG_BLOCKS`], in order.
    vgg: Vec<Conv2d>,
}

fn channel_const(v: [f64; 3], like: &Tensor) -> Result<Tensor> {
    Ok(Tensor::new(&v, like.device())?
        .to_dtype(like.dtype())?
        .reshape((1, 3, 1, 1))?)
}

impl PerceptualLoss {
    /// Builds the networks from `vb` rooted at `percep_loss` (keys `net.slice1.0.weight`,
    /// `vggface.network.0.weight`, ...). The dtype and device are `vb`'s.
    pub fn new(vb: VarBuilder) -> Result<Self> {
        let alex = ALEX
            .iter()
            .map(|&(name, cin, cout, k, s, p, _)| {
                Conv2d::new(vb.pp(name), cin, cout, k, s, p, true)
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let shape = |idx: usize| VGG.iter().find(|v| v.0 == idx).map(|v| (v.1, v.2));
        let mut vgg = Vec::new();
        for idx in VGG_BLOCKS.iter().flat_map(|b| b.iter().copied()) {
            let (cin, cout) = shape(idx).ok_or_else(|| TrainError::Weights {
                path: None,
                reason: format!("no shape for VGG layer {idx}"),
            })?;
            vgg.push(Conv2d::new(
                vb.pp(format!("vggface.network.{idx}")),
                cin,
                cout,
                3,
                1,
                1,
                true,
            )?);
        }
        Ok(Self { alex, vgg })
    }

    /// From a full weight map (keys with the `percep_loss.` prefix, as [`read_weights`] returns
    /// them for the release checkpoint): `Ok(None)` when it holds no perceptual key at all (the
    /// term is then off; the caller warns), an error when some are missing or misshapen.
    ///
    /// [`read_weights`]: gagavatar_net::checkpoint::read_weights
    pub fn from_tensors(
        tensors: &HashMap<String, Tensor>,
        dtype: DType,
        device: &Device,
    ) -> Result<Option<Self>> {
        let sub: HashMap<String, Tensor> = tensors
            .iter()
            .filter_map(|(k, v)| {
                k.strip_prefix(PERCEP_PREFIX)
                    .map(|s| (s.to_string(), v.clone()))
            })
            .collect();
        if sub.is_empty() {
            return Ok(None);
        }
        Self::from_sub(sub, dtype, device, None).map(Some)
    }

    fn from_sub(
        sub: HashMap<String, Tensor>,
        dtype: DType,
        device: &Device,
        path: Option<&Path>,
    ) -> Result<Self> {
        let mut problems = Vec::new();
        for (key, shape) in expected_keys() {
            // Layers past relu_5_1 are optional: the loss never runs them.
            let optional =
                key.starts_with("vggface.network.26.") || key.starts_with("vggface.network.28.");
            match sub.get(&key) {
                Some(t) if t.dims() != shape.as_slice() => problems.push(format!(
                    "`{PERCEP_PREFIX}{key}` has shape {:?}, expected {shape:?}",
                    t.dims()
                )),
                None if !optional => problems.push(format!("`{PERCEP_PREFIX}{key}` is missing")),
                _ => {}
            }
        }
        if !problems.is_empty() {
            return Err(TrainError::Weights {
                path: path.map(Path::to_path_buf),
                reason: problems.join("; "),
            });
        }
        Self::new(VarBuilder::from_tensors(sub, dtype, device))
    }

    /// Loads the perceptual weights from the release checkpoint (`.pt`) or a safetensors file
    /// with `percep_loss.*` keys (or the same keys without the prefix). Errors when absent.
    pub fn load(path: &Path, dtype: DType, device: &Device) -> Result<Self> {
        let w = gagavatar_net::checkpoint::read_weights(path)?;
        let has_prefix = w.tensors.keys().any(|k| k.starts_with(PERCEP_PREFIX));
        let sub: HashMap<String, Tensor> = if has_prefix {
            w.tensors
                .into_iter()
                .filter_map(|(k, v)| k.strip_prefix(PERCEP_PREFIX).map(|s| (s.to_string(), v)))
                .collect()
        } else {
            w.tensors
        };
        if sub.is_empty() {
            return Err(TrainError::Weights {
                path: Some(path.to_path_buf()),
                reason: "no tensors".into(),
            });
        }
        Self::from_sub(sub, dtype, device, Some(path))
    }

    fn dtype(&self) -> DType {
        self.alex[0].weight.dtype()
    }

    /// The weights the loss runs, flattened f32, by key without the `percep_loss.` prefix (for
    /// another device's copy of the networks).
    pub fn host_weights(&self) -> Result<HashMap<String, Vec<f32>>> {
        let names = ALEX.iter().map(|a| a.0.to_string()).chain(
            VGG_BLOCKS
                .iter()
                .flat_map(|b| b.iter())
                .map(|i| format!("vggface.network.{i}")),
        );
        let mut out = HashMap::new();
        for (name, conv) in names.zip(self.alex.iter().chain(&self.vgg)) {
            let flat = |t: &Tensor| -> Result<Vec<f32>> {
                Ok(t.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()?)
            };
            out.insert(format!("{name}.weight"), flat(&conv.weight)?);
            if let Some(b) = &conv.bias {
                out.insert(format!("{name}.bias"), flat(b)?);
            }
        }
        Ok(out)
    }

    /// Features of an image batch `[B, 3, H, W]` in [0, 1] (cast to the weights' dtype). The
    /// input needs `H, W >= 31` for AlexNet's pooling chain.
    pub fn features(&self, x: &Tensor) -> Result<PerceptualFeatures> {
        match x.dims() {
            &[b, 3, h, w] if b > 0 && h >= 31 && w >= 31 => {}
            other => {
                return Err(input_err(
                    "perceptual input",
                    format!("expected [B, 3, H, W] with H, W >= 31, got {other:?}"),
                ))
            }
        }
        let x = x.to_dtype(self.dtype())?;
        Ok(PerceptualFeatures {
            alex: self.alex_features(&x)?,
            vgg: self.vgg_features(&x)?,
        })
    }

    fn alex_features(&self, x: &Tensor) -> Result<Vec<Tensor>> {
        let mut h = x
            .broadcast_sub(&channel_const(IMAGENET_MEAN, x)?)?
            .broadcast_div(&channel_const(IMAGENET_STD, x)?)?;
        let mut out = Vec::with_capacity(5);
        for (conv, spec) in self.alex.iter().zip(ALEX) {
            if spec.6 {
                h = maxpool2d(&h, 3, 2)?;
            }
            h = relu(&conv.forward(&h)?)?;
            out.push(h.clone());
        }
        Ok(out)
    }

    fn vgg_features(&self, x: &Tensor) -> Result<Vec<Tensor>> {
        let mut h = x
            .affine(255.0, 0.0)?
            .broadcast_sub(&channel_const(VGGFACE_MEAN, x)?)?;
        let mut convs = self.vgg.iter();
        let mut out = Vec::with_capacity(5);
        for (bi, block) in VGG_BLOCKS.iter().enumerate() {
            if bi > 0 {
                h = maxpool2d(&h, 2, 2)?;
            }
            for _ in block.iter() {
                let conv = convs.next().ok_or_else(|| TrainError::Weights {
                    path: None,
                    reason: "VGG layer list is short".into(),
                })?;
                h = relu(&conv.forward(&h)?)?;
            }
            out.push(h.clone());
        }
        Ok(out)
    }

    /// The ten weighted layer terms `[alex 1..5, vgg 1..5]` between `pred` features (batch
    /// `k B`, i.e. `k` groups of `B`) and `target` features (batch `B`): each is the sum over
    /// the `k` groups of [`layer_distance`], times the layer weight.
    pub fn layer_terms(
        pred: &PerceptualFeatures,
        target: &PerceptualFeatures,
    ) -> Result<Vec<Tensor>> {
        let mut terms = Vec::with_capacity(10);
        for (l, (a, b)) in pred.alex.iter().zip(&target.alex).enumerate() {
            terms.push((layer_distance(a, b)? * LAYER_WEIGHTS[l])?);
        }
        for (l, (a, b)) in pred.vgg.iter().zip(&target.vgg).enumerate() {
            terms.push((layer_distance(a, b)? * (LAYER_WEIGHTS[l] * VGG_FACTOR))?);
        }
        Ok(terms)
    }

    /// The distance between feature sets (sum of [`PerceptualLoss::layer_terms`]): a scalar.
    pub fn distance(pred: &PerceptualFeatures, target: &PerceptualFeatures) -> Result<Tensor> {
        let terms = Self::layer_terms(pred, target)?;
        let mut total = terms[0].clone();
        for t in &terms[1..] {
            total = (total + t)?;
        }
        Ok(total)
    }

    /// `P(pred, target)` for image batches in [0, 1] of the same shape; the target is detached.
    pub fn loss(&self, pred: &Tensor, target: &Tensor) -> Result<Tensor> {
        if pred.dims() != target.dims() {
            return Err(input_err(
                "perceptual target",
                format!("shape {:?} differs from {:?}", target.dims(), pred.dims()),
            ));
        }
        let tf = self.features(&target.detach())?;
        Self::distance(&self.features(pred)?, &tf)
    }
}

/// Seeded stand-in weights with the release's keys and shapes (all 13 VGG layers), for tests
/// and benchmarks without the real checkpoint: He-uniform weights (bound `sqrt(6 / fan_in)`)
/// and biases uniform in `[-0.1, 0.1)`, from a SplitMix64 stream that
/// `tools/reference/train_reference.py` reproduces bit for bit. Keys carry no prefix.
pub fn seeded_weights(seed: u64) -> Result<HashMap<String, Tensor>> {
    let mut out = HashMap::new();
    for (ki, (key, shape)) in expected_keys().into_iter().enumerate() {
        let n: usize = shape.iter().product();
        let bound = if key.ends_with(".weight") {
            let fan_in: usize = shape[1..].iter().product();
            (6.0 / fan_in as f64).sqrt()
        } else {
            0.1
        };
        let base = splitmix64(seed ^ ((ki as u64) << 32));
        let vals: Vec<f32> = (0..n as u64)
            .into_par_iter()
            .map(|i| {
                let z = splitmix64(base.wrapping_add(i.wrapping_mul(GOLDEN)));
                let u = (z >> 11) as f64 * (1.0 / (1u64 << 53) as f64);
                ((2.0 * u - 1.0) * bound) as f32
            })
            .collect();
        out.insert(key, Tensor::from_vec(vals, shape, &Device::Cpu)?);
    }
    Ok(out)
}

const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64's output function of state `x + golden`.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(GOLDEN);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
