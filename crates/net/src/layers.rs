//! Small building blocks shared by the modules: a convolution and a linear layer whose
//! parameters are the checkpoint's `weight`/`bias`, run by the kernels of `gagavatar-ops` in
//! f32 or, after `set_precision(Precision::Bf16)`, with bf16 products.

use candle_core::{bail, Result, Tensor};
use candle_nn::VarBuilder;
use gagavatar_ops::bf16::Bf16Linear;
use gagavatar_ops::conv::{conv2d_fixed, Bf16Conv, WinogradCache};
use gagavatar_ops::{Conv2dSpec, Precision};

/// `nn.Conv2d` (square kernel, no groups or dilation).
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    pub spec: Conv2dSpec,
    /// The weight prepared for bf16 products, under `Precision::Bf16`.
    bf16: Option<Bf16Conv>,
    /// The weight's Winograd transform, kept after the first inference call that runs Winograd.
    wino: WinogradCache,
}

impl Conv2d {
    /// Loads `weight` [cout, cin, k, k] and, when `bias`, `bias` [cout].
    pub fn new(
        vb: VarBuilder,
        cin: usize,
        cout: usize,
        k: usize,
        stride: usize,
        padding: usize,
        bias: bool,
    ) -> Result<Self> {
        let weight = vb.get((cout, cin, k, k), "weight")?;
        let bias = if bias {
            Some(vb.get(cout, "bias")?)
        } else {
            None
        };
        Ok(Self {
            weight,
            bias,
            spec: Conv2dSpec { stride, padding },
            bf16: None,
            wino: WinogradCache::default(),
        })
    }

    /// A convolution from tensors already loaded (f32 products until `set_precision`).
    pub fn from_parts(weight: Tensor, bias: Option<Tensor>, spec: Conv2dSpec) -> Self {
        Self {
            weight,
            bias,
            spec,
            bf16: None,
            wino: WinogradCache::default(),
        }
    }

    /// Switches between f32 and bf16 products (bf16: fixed weights only, inference).
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.bf16 = match precision {
            Precision::F32 => None,
            Precision::Bf16 => {
                fixed(&self.weight)?;
                Some(Bf16Conv::new(&self.weight, self.bias.as_ref(), self.spec)?)
            }
        };
        Ok(())
    }

    /// A 3x3 convolution with padding 1 and bias, the most common layer.
    pub fn k3(vb: VarBuilder, cin: usize, cout: usize) -> Result<Self> {
        Self::new(vb, cin, cout, 3, 1, 1, true)
    }

    /// `prefix.weight` and, with a bias, `prefix.bias` (the checkpoint's keys and shapes).
    pub fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        out.push((format!("{prefix}.weight"), self.weight.clone()));
        if let Some(b) = &self.bias {
            out.push((format!("{prefix}.bias"), b.clone()));
        }
    }

    /// A 1x1 convolution with bias.
    pub fn k1(vb: VarBuilder, cin: usize, cout: usize) -> Result<Self> {
        Self::new(vb, cin, cout, 1, 1, 0, true)
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match &self.bf16 {
            Some(packed) if !x.track_op() => packed.forward(x),
            _ => conv2d_fixed(
                x,
                &self.weight,
                None,
                self.bias.as_ref(),
                self.spec,
                &self.wino,
            ),
        }
    }
}

/// bf16 products are for inference: weights that train stay f32.
pub fn fixed(weight: &Tensor) -> Result<()> {
    if weight.track_op() || weight.is_variable() {
        bail!("bf16 precision is for inference; these weights are trainable");
    }
    Ok(())
}

/// `weight` [out, in] and `bias` packed for bf16 products under `Precision::Bf16` (fixed
/// weights only), nothing under `Precision::F32`.
pub fn packed_linear(
    precision: Precision,
    weight: &Tensor,
    bias: Option<&Tensor>,
) -> Result<Option<std::sync::Arc<Bf16Linear>>> {
    Ok(match precision {
        Precision::F32 => None,
        Precision::Bf16 => {
            fixed(weight)?;
            Some(std::sync::Arc::new(Bf16Linear::new(weight, bias)?))
        }
    })
}

/// `nn.Linear` (`y = x W^T + b` over the last dim) that can run its product in bf16.
#[derive(Debug, Clone)]
pub struct Linear {
    inner: candle_nn::Linear,
    bf16: Option<std::sync::Arc<Bf16Linear>>,
}

impl Linear {
    /// Loads `weight` [out, in] and `bias` [out].
    pub fn new(vb: VarBuilder, cin: usize, cout: usize) -> Result<Self> {
        Ok(Self {
            inner: candle_nn::linear(cin, cout, vb)?,
            bf16: None,
        })
    }

    /// The layer as candle holds it (its weight and bias).
    pub fn inner(&self) -> &candle_nn::Linear {
        &self.inner
    }

    /// `prefix.weight` and, with a bias, `prefix.bias`.
    pub fn named(&self, prefix: &str, out: &mut Vec<(String, Tensor)>) {
        out.push((format!("{prefix}.weight"), self.inner.weight().clone()));
        if let Some(b) = self.inner.bias() {
            out.push((format!("{prefix}.bias"), b.clone()));
        }
    }

    /// Switches between f32 and bf16 products (bf16: fixed weights only, inference).
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        self.bf16 = packed_linear(precision, self.inner.weight(), self.inner.bias())?;
        Ok(())
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match &self.bf16 {
            Some(packed) if !x.track_op() => packed.forward(x),
            _ => candle_nn::Module::forward(&self.inner, x),
        }
    }
}
