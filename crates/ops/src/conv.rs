//! 2-D convolution for NCHW f32 tensors.

use candle_core::{Result, Tensor};

/// Stride, padding (same on every side) and dilation-free, group-free 2-D convolution settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Conv2dSpec {
    pub stride: usize,
    pub padding: usize,
}

impl Default for Conv2dSpec {
    fn default() -> Self {
        Self {
            stride: 1,
            padding: 0,
        }
    }
}

/// `x` [B, Cin, H, W], `w` [Cout, Cin, kh, kw], optional `bias` [Cout].
pub fn conv2d(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, spec: Conv2dSpec) -> Result<Tensor> {
    let y = x.conv2d(w, spec.padding, spec.stride, 1, 1)?;
    match bias {
        Some(b) => y.broadcast_add(&b.reshape((1, b.elem_count(), 1, 1))?),
        None => Ok(y),
    }
}
