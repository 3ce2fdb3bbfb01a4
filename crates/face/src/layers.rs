//! The layers the face networks are built from, each loading its weights by the TFLite layer
//! name (`<layer>.kernel`, `<layer>.bias`, `<layer>.alpha`) and running on [`crate::kernels`].

use candle_core::Result;
use candle_nn::VarBuilder;

use crate::kernels::{self, Act, DwWeights, Geom, Packed, Residual};
use crate::tensor::Nhwc;
use crate::weights::get_vec;

/// How a convolution pads: TFLite SAME (the odd pixel after), VALID, or an explicit symmetric
/// zero padding (a ZeroPadding2D layer folded into the VALID convolution after it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pad {
    Same,
    Valid,
    Explicit(usize),
}

impl Pad {
    fn geom(self, h: usize, w: usize, k: usize, stride: usize) -> Geom {
        match self {
            Pad::Same => Geom::same(h, w, k, stride),
            Pad::Valid => Geom::valid(h, w, k, stride),
            Pad::Explicit(p) => Geom::padded(h, w, k, stride, p),
        }
    }
}

/// CONV_2D: kernel `[cout, k, k, cin]`, bias `[cout]`.
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub cin: usize,
    pub cout: usize,
    pub k: usize,
    pub stride: usize,
    pub pad: Pad,
    pk: Packed,
}

impl Conv2d {
    pub fn new(
        vb: &VarBuilder,
        name: &str,
        cin: usize,
        cout: usize,
        k: usize,
        stride: usize,
        pad: Pad,
    ) -> Result<Self> {
        let vb = vb.pp(name);
        let w = get_vec(&vb, &[cout, k, k, cin], "kernel")?;
        let b = get_vec(&vb, &[cout], "bias")?;
        Ok(Conv2d {
            cin,
            cout,
            k,
            stride,
            pad,
            pk: Packed::new(&w, &b, cout, k * k * cin),
        })
    }

    /// A 1x1 stride-1 convolution.
    pub fn pointwise(vb: &VarBuilder, name: &str, cin: usize, cout: usize) -> Result<Self> {
        Self::new(vb, name, cin, cout, 1, 1, Pad::Valid)
    }

    /// The convolution with fused activation.
    pub fn forward(&self, x: &Nhwc, act: &Act) -> Nhwc {
        self.forward_res(x, None, act)
    }

    /// `act(conv(x) + res)`; the residual may have fewer channels (zero channel padding). Only
    /// for 1x1 stride-1 convolutions, the only ones a residual follows in these networks.
    pub fn forward_res(&self, x: &Nhwc, res: Option<&Nhwc>, act: &Act) -> Nhwc {
        self.forward_with(x, res.map_or(Residual::None, Residual::Same), act)
    }

    /// A 1x1 convolution of `x` scaled per input channel by `s` (a squeeze-and-excitation
    /// gate folded into the weights), plus `res`.
    pub fn forward_gated(&self, x: &Nhwc, s: &[f32], res: Option<&Nhwc>, act: &Act) -> Nhwc {
        assert!(
            self.k == 1 && self.stride == 1,
            "gated input on a non-pointwise convolution"
        );
        let pk = self.pk.scale_inputs(s);
        kernels::pointwise(x, &pk, res.map_or(Residual::None, Residual::Same), act)
    }

    /// `relu(conv(x)) * s` per output channel, for positive `s` (folded into the weights:
    /// `relu(s z) = s relu(z)` when `s > 0`).
    pub fn forward_relu_scaled(&self, x: &Nhwc, s: &[f32]) -> Nhwc {
        assert!(
            self.k == 1 && self.stride == 1,
            "scaled output on a non-pointwise convolution"
        );
        assert!(s.iter().all(|&v| v > 0.0), "output scales must be positive");
        let pk = self.pk.scale_outputs(s);
        kernels::pointwise(x, &pk, Residual::None, &Act::Relu)
    }

    /// `act(conv(x) + res)` with any kind of residual.
    pub fn forward_with(&self, x: &Nhwc, res: Residual, act: &Act) -> Nhwc {
        if self.k == 1 && self.stride == 1 {
            kernels::pointwise(x, &self.pk, res, act)
        } else {
            assert!(
                matches!(res, Residual::None),
                "residual after a non-pointwise convolution"
            );
            kernels::conv(
                x,
                &self.pk,
                self.pad.geom(x.h, x.w, self.k, self.stride),
                act,
            )
        }
    }
}

/// DEPTHWISE_CONV_2D: kernel `[1, k, k, c]`, bias `[c]`.
#[derive(Debug, Clone)]
pub struct DepthwiseConv2d {
    pub stride: usize,
    pub pad: Pad,
    w: DwWeights,
}

impl DepthwiseConv2d {
    pub fn new(
        vb: &VarBuilder,
        name: &str,
        c: usize,
        k: usize,
        stride: usize,
        pad: Pad,
    ) -> Result<Self> {
        let vb = vb.pp(name);
        let w = get_vec(&vb, &[1, k, k, c], "kernel")?;
        let bias = get_vec(&vb, &[c], "bias")?;
        Ok(DepthwiseConv2d {
            stride,
            pad,
            w: DwWeights {
                kh: k,
                kw: k,
                c,
                w,
                bias,
            },
        })
    }

    pub fn forward(&self, x: &Nhwc, act: &Act) -> Nhwc {
        let g = self.pad.geom(x.h, x.w, self.w.kh, self.stride);
        kernels::depthwise(x, &self.w, g, act)
    }

    /// `x + act(dw(x))` (stride 1).
    pub fn forward_plus_input(&self, x: &Nhwc, act: &Act) -> Nhwc {
        let g = self.pad.geom(x.h, x.w, self.w.kh, self.stride);
        kernels::depthwise_ext(x, &self.w, g, act, true)
    }
}

/// PRELU: slopes `[1, 1, c]`, as an activation fused into the op before it.
pub fn prelu(vb: &VarBuilder, name: &str, c: usize) -> Result<Act> {
    Ok(Act::prelu(&get_vec(&vb.pp(name), &[1, 1, c], "alpha")?))
}

/// BlazeBlock (BlazeFace, the face mesh): `act(pw(dw3x3(x)) + skip)` where the skip is `x`,
/// or for stride 2 a 2x2 max pool of `x`, zero-extended to the output channels.
#[derive(Debug, Clone)]
pub struct BlazeBlock {
    pub dw: DepthwiseConv2d,
    pub pw: Conv2d,
    pub act: Act,
}

impl BlazeBlock {
    /// `names` = (depthwise layer, pointwise layer); `act` the activation after the add.
    pub fn new(
        vb: &VarBuilder,
        names: (&str, &str),
        cin: usize,
        cout: usize,
        stride: usize,
        act: Act,
    ) -> Result<Self> {
        Ok(BlazeBlock {
            dw: DepthwiseConv2d::new(vb, names.0, cin, 3, stride, Pad::Same)?,
            pw: Conv2d::pointwise(vb, names.1, cin, cout)?,
            act,
        })
    }

    pub fn forward(&self, x: &Nhwc) -> Nhwc {
        let d = self.dw.forward(x, &Act::None);
        let res = if self.dw.stride == 1 {
            Residual::Same(x)
        } else {
            Residual::MaxPool2(x)
        };
        self.pw.forward_with(&d, res, &self.act)
    }
}
