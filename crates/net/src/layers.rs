//! Small building blocks shared by the modules: a convolution whose parameters are the
//! checkpoint's `weight`/`bias`, run by the fast kernels of `gagavatar-ops`.

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use gagavatar_ops::{conv2d, Conv2dSpec};

/// `nn.Conv2d` (square kernel, no groups or dilation).
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    pub spec: Conv2dSpec,
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
        })
    }

    /// A 3x3 convolution with padding 1 and bias, the most common layer.
    pub fn k3(vb: VarBuilder, cin: usize, cout: usize) -> Result<Self> {
        Self::new(vb, cin, cout, 3, 1, 1, true)
    }

    /// A 1x1 convolution with bias.
    pub fn k1(vb: VarBuilder, cin: usize, cout: usize) -> Result<Self> {
        Self::new(vb, cin, cout, 1, 1, 0, true)
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        conv2d(x, &self.weight, self.bias.as_ref(), self.spec)
    }
}

/// Leaky ReLU: `max(x, slope x)` for 0 < slope < 1.
pub fn leaky_relu(x: &Tensor, slope: f64) -> Result<Tensor> {
    x.maximum(&(x * slope)?)
}
