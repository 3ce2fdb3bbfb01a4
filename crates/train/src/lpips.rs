//! LPIPS v0.1, AlexNet variant (Zhang et al. 2018, the `lpips` package's `LPIPS(net='alex')`),
//! an evaluation metric: lower is more similar.
//!
//! Distance of two images in [0, 1]: map to [-1, 1], then `(x - shift) / scale` with
//! [`SHIFT`], [`SCALE`]; AlexNet features after its five ReLUs; each feature map unit-normalised
//! over channels (`f / (sqrt(sum_c f^2) + 1e-10)`); the squared difference weighted by the
//! layer's linear head `lin_k` (a bias-free 1x1 convolution to one channel); the spatial mean;
//! the sum over the five layers.
//!
//! The weights are the `lpips` package's state dict saved as safetensors:
//!
//! ```text
//! python3 -c "import lpips; from safetensors.torch import save_file; save_file({k: v.contiguous() for k, v in lpips.LPIPS(net='alex').state_dict().items() if not k.startswith('lins.')}, 'lpips_alex.safetensors')"
//! ```
//!
//! (`lins.*` repeats `lin0..4` as shared tensors, which `save_file` refuses.) Keys read:
//! `net.slice1.0`, `net.slice2.3`, `net.slice3.6`, `net.slice4.8`, `net.slice5.10` (`.weight`,
//! `.bias`; torchvision's `AlexNet.features` indices) and `lin{k}.model.1.weight` (or
//! `lins.{k}.model.1.weight`) of shape `[1, C_k, 1, 1]`. Other keys (the scaling layer's
//! buffers, whose values are the constants below) are ignored. The channel widths are read from
//! the file and checked to chain (the released network has 64, 192, 384, 256, 256), so a
//! narrowed network with the same layout also loads (the golden test uses one).
//!
//! This is the standard metric, not the training loss's perceptual distance
//! ([`crate::perceptual`] uses ImageNet normalisation, L1 and fixed layer weights).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use gagavatar_net::layers::Conv2d;
use gagavatar_ops::Conv2dSpec;

use crate::error::{input_err, Result, TrainError};
use crate::kernels::{maxpool2d, relu};

/// The scaling layer's shift, applied to inputs in [-1, 1].
pub const SHIFT: [f64; 3] = [-0.030, -0.088, -0.188];
/// The scaling layer's scale.
pub const SCALE: [f64; 3] = [0.458, 0.448, 0.450];
/// The channel norm's epsilon, as `lpips.normalize_tensor`.
pub const EPS: f64 = 1e-10;
/// The released network's channel widths of the five layers.
pub const ALEX_WIDTHS: [usize; 5] = [64, 192, 384, 256, 256];

/// AlexNet convolutions: (key, kernel, stride, padding, max-pool 3x3/2 before).
const CONVS: [(&str, usize, usize, usize, bool); 5] = [
    ("net.slice1.0", 11, 4, 2, false),
    ("net.slice2.3", 5, 1, 2, true),
    ("net.slice3.6", 3, 1, 1, true),
    ("net.slice4.8", 3, 1, 1, false),
    ("net.slice5.10", 3, 1, 1, false),
];

/// The smallest side AlexNet's pooling chain accepts.
pub const MIN_SIDE: usize = 31;

/// The LPIPS (AlexNet) network with its linear heads.
#[derive(Debug, Clone)]
pub struct Lpips {
    convs: Vec<Conv2d>,
    /// `[1, C_k, 1, 1]` per layer.
    lins: Vec<Tensor>,
}

fn weights_err(path: Option<&Path>, reason: String) -> TrainError {
    TrainError::Weights {
        path: path.map(Path::to_path_buf),
        reason,
    }
}

impl Lpips {
    /// Loads the weights from a safetensors file (see the module docs for the keys) onto
    /// `device`, as f32.
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let w = gagavatar_net::checkpoint::read_weights(path)?;
        Self::from_tensors(&w.tensors, device, Some(path))
    }

    /// From a key -> tensor map with the `lpips` state-dict names; `path` only names the source
    /// in errors. Every missing or misshapen key is reported.
    pub fn from_tensors(
        tensors: &HashMap<String, Tensor>,
        device: &Device,
        path: Option<&Path>,
    ) -> Result<Self> {
        let mut problems = Vec::new();
        let mut convs = Vec::with_capacity(5);
        let mut lins = Vec::with_capacity(5);
        let mut cin = Some(3usize);
        for (i, &(name, k, stride, padding, _)) in CONVS.iter().enumerate() {
            let wkey = format!("{name}.weight");
            let bkey = format!("{name}.bias");
            let weight = match tensors.get(&wkey) {
                None => {
                    problems.push(format!("`{wkey}` is missing"));
                    None
                }
                Some(t) => match (t.dims(), cin) {
                    (&[cout, ci, kh, kw], Some(c)) if ci == c && kh == k && kw == k && cout > 0 => {
                        Some((t, cout))
                    }
                    // The previous layer was broken: only the kernel can be checked.
                    (&[cout, _, kh, kw], None) if kh == k && kw == k && cout > 0 => Some((t, cout)),
                    (dims, c) => {
                        problems.push(format!(
                            "`{wkey}` has shape {dims:?}, expected [C, {}, {k}, {k}]",
                            c.map_or("C_in".to_string(), |c| c.to_string())
                        ));
                        None
                    }
                },
            };
            let cout = weight.map(|(_, c)| c);
            let bias = match (tensors.get(&bkey), cout) {
                (None, _) => {
                    problems.push(format!("`{bkey}` is missing"));
                    None
                }
                (Some(t), Some(c)) if t.dims() != [c] => {
                    problems.push(format!("`{bkey}` has shape {:?}, expected [{c}]", t.dims()));
                    None
                }
                (Some(t), _) => Some(t),
            };
            let lkey = format!("lin{i}.model.1.weight");
            let alt = format!("lins.{i}.model.1.weight");
            let lin = match tensors.get(&lkey).or_else(|| tensors.get(&alt)) {
                None => {
                    problems.push(format!("`{lkey}` is missing"));
                    None
                }
                Some(t) => match cout {
                    Some(c) if t.dims() != [1, c, 1, 1] => {
                        problems.push(format!(
                            "`{lkey}` has shape {:?}, expected [1, {c}, 1, 1]",
                            t.dims()
                        ));
                        None
                    }
                    _ => Some(t),
                },
            };
            if let (Some((w, _)), Some(b), Some(l)) = (weight, bias, lin) {
                let prep = |t: &Tensor| -> Result<Tensor> {
                    Ok(t.to_dtype(DType::F32)?.to_device(device)?)
                };
                convs.push(Conv2d::from_parts(
                    prep(w)?,
                    Some(prep(b)?),
                    Conv2dSpec { stride, padding },
                ));
                lins.push(prep(l)?);
            }
            cin = cout;
        }
        if !problems.is_empty() {
            return Err(weights_err(
                path,
                format!("LPIPS (AlexNet): {}", problems.join("; ")),
            ));
        }
        Ok(Self { convs, lins })
    }

    /// The channel widths of the five layers.
    pub fn widths(&self) -> Vec<usize> {
        self.lins.iter().map(|l| l.dims()[1]).collect()
    }

    fn features(&self, x: &Tensor) -> Result<Vec<Tensor>> {
        let dev = x.device();
        let shift = Tensor::new(&SHIFT.map(|v| v as f32), dev)?.reshape((1, 3, 1, 1))?;
        let scale = Tensor::new(&SCALE.map(|v| v as f32), dev)?.reshape((1, 3, 1, 1))?;
        let mut h = x
            .affine(2.0, -1.0)?
            .broadcast_sub(&shift)?
            .broadcast_div(&scale)?;
        let mut out = Vec::with_capacity(5);
        for (conv, spec) in self.convs.iter().zip(CONVS) {
            if spec.4 {
                h = maxpool2d(&h, 3, 2)?;
            }
            h = relu(&conv.forward(&h)?)?;
            out.push(h.clone());
        }
        Ok(out)
    }

    /// The per-layer distances `[5, B]` between image batches `[B, 3, H, W]` in [0, 1] of the
    /// same shape (`H, W >= 31`); [`Lpips::distance`] sums them.
    pub fn layer_distances(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        for (name, t) in [("LPIPS input a", a), ("LPIPS input b", b)] {
            match t.dims() {
                &[n, 3, h, w] if n > 0 && h >= MIN_SIDE && w >= MIN_SIDE => {}
                other => {
                    return Err(input_err(
                        name,
                        format!("expected [B, 3, H, W] with H, W >= {MIN_SIDE}, got {other:?}"),
                    ))
                }
            }
        }
        if a.dims() != b.dims() {
            return Err(input_err(
                "LPIPS input b",
                format!("shape {:?} differs from {:?}", b.dims(), a.dims()),
            ));
        }
        let dev = self.lins[0].device();
        let a = a.to_dtype(DType::F32)?.to_device(dev)?;
        let b = b.to_dtype(DType::F32)?.to_device(dev)?;
        let (fa, fb) = (self.features(&a)?, self.features(&b)?);
        let mut layers = Vec::with_capacity(5);
        for ((fa, fb), lin) in fa.iter().zip(&fb).zip(&self.lins) {
            let d = (unit(fa)? - unit(fb)?)?.sqr()?;
            // A 1x1 convolution to one channel is a channel-weighted sum.
            let weighted = d.broadcast_mul(lin)?.sum_keepdim(1)?;
            layers.push(weighted.flatten_from(1)?.mean(1)?);
        }
        Ok(Tensor::stack(&layers, 0)?)
    }

    /// LPIPS per image pair: `[B]` (f32).
    pub fn distance(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        Ok(self.layer_distances(a, b)?.sum(0)?)
    }

    /// LPIPS per image pair, on the host.
    pub fn distances(&self, a: &Tensor, b: &Tensor) -> Result<Vec<f64>> {
        Ok(self
            .distance(a, b)?
            .to_dtype(DType::F64)?
            .to_device(&Device::Cpu)?
            .to_vec1()?)
    }
}

/// `f / (sqrt(sum_c f^2) + eps)` over the channel axis.
fn unit(f: &Tensor) -> Result<Tensor> {
    let norm = (f.sqr()?.sum_keepdim(1)?.sqrt()? + EPS)?;
    Ok(f.broadcast_div(&norm)?)
}
