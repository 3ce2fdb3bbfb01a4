//! The selfie segmentation network (`selfie_segmentation.tflite`, spec TRACKING.md sections 8
//! and 11): a MobileNetV3-style encoder (inverted residuals with hard-swish and
//! squeeze-and-excitation) from the 256x256 image down to 16x16, and a decoder that upsamples
//! back through three gated skip connections to a 2x2 transposed convolution and a sigmoid:
//! the person probability per pixel of the 256x256 input.

use candle_core::Result;
use candle_nn::VarBuilder;

use crate::kernels::{self, sigmoid, Act};
use crate::layers::{Conv2d, DepthwiseConv2d, Pad};
use crate::tensor::Nhwc;
use crate::weights::get_vec;

/// Squeeze-and-excitation: channel gates `sigmoid(fc2(relu(fc1(mean(x)))))`.
#[derive(Debug, Clone)]
struct Excite {
    fc1: Conv2d,
    fc2: Conv2d,
}

impl Excite {
    fn new(vb: &VarBuilder, i: usize, c: usize, mid: usize) -> Result<Self> {
        Ok(Excite {
            fc1: Conv2d::pointwise(vb, &format!("conv2d_{i}"), c, mid)?,
            fc2: Conv2d::pointwise(vb, &format!("conv2d_{}", i + 1), mid, c)?,
        })
    }

    /// The gates for the pooled input.
    fn gates(&self, pooled: &Nhwc) -> Vec<f32> {
        let h = self.fc1.forward(pooled, &Act::Relu);
        self.fc2
            .forward(&h, &Act::None)
            .data
            .iter()
            .map(|&v| sigmoid(v))
            .collect()
    }
}

/// An inverted residual: 1x1 expansion, depthwise, optional excitation, 1x1 projection, and
/// the input added back when the shape allows.
#[derive(Debug, Clone)]
struct Bottleneck {
    expand: Conv2d,
    dw: DepthwiseConv2d,
    act: Act,
    excite: Option<Excite>,
    project: Conv2d,
    residual: bool,
}

/// (expand index, depthwise index, excitation index or 0, projection index, input, expanded,
/// output channels, kernel, stride, hard-swish) of the encoder's bottlenecks.
type Spec = (
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    bool,
);
const ENCODER: [Spec; 8] = [
    (1, 0, 2, 4, 16, 16, 16, 3, 2, false),
    (5, 1, 0, 6, 16, 72, 24, 3, 2, false),
    (7, 2, 0, 8, 24, 88, 24, 3, 1, false),
    (9, 3, 10, 12, 24, 96, 32, 5, 2, true),
    (13, 4, 14, 16, 32, 128, 32, 5, 1, true),
    (17, 5, 18, 20, 32, 128, 32, 5, 1, true),
    (21, 6, 22, 24, 32, 96, 32, 5, 1, true),
    (25, 7, 26, 28, 32, 96, 32, 5, 1, true),
];

fn dw_name(i: usize) -> String {
    if i == 0 {
        "depthwise_conv2d".into()
    } else {
        format!("depthwise_conv2d_{i}")
    }
}

impl Bottleneck {
    fn new(vb: &VarBuilder, s: Spec) -> Result<Self> {
        let (e, d, x, p, cin, mid, cout, k, stride, hswish) = s;
        let act = if hswish { Act::HardSwish } else { Act::Relu };
        Ok(Bottleneck {
            expand: Conv2d::pointwise(vb, &format!("conv2d_{e}"), cin, mid)?,
            dw: DepthwiseConv2d::new(vb, &dw_name(d), mid, k, stride, Pad::Same)?,
            act,
            excite: if x > 0 {
                Some(Excite::new(vb, x, mid, (mid / 4).max(8))?)
            } else {
                None
            },
            project: Conv2d::pointwise(vb, &format!("conv2d_{p}"), mid, cout)?,
            residual: stride == 1 && cin == cout,
        })
    }

    fn forward(&self, x: &Nhwc) -> Nhwc {
        let h = self.expand.forward(x, &self.act);
        let mut h = self.dw.forward(&h, &self.act);
        if let Some(e) = &self.excite {
            h = kernels::scale_channels(&h, &e.gates(&kernels::global_avg_pool(&h)));
        }
        self.project
            .forward_res(&h, self.residual.then_some(x), &Act::None)
    }
}

/// A decoder stage: upsample x2, 1x1 to the skip's channels, gate the skip by an excitation
/// of their sum, add, then `r + relu(dw(r))` with `r = relu(1x1(..))`.
#[derive(Debug, Clone)]
struct UpStage {
    reduce: Conv2d,
    excite: Excite,
    mix: Conv2d,
    dw: DepthwiseConv2d,
}

impl UpStage {
    fn new(vb: &VarBuilder, first: usize, dw: usize, cin: usize, c: usize) -> Result<Self> {
        Ok(UpStage {
            reduce: Conv2d::pointwise(vb, &format!("conv2d_{first}"), cin, c)?,
            excite: Excite::new(vb, first + 1, c, c)?,
            mix: Conv2d::pointwise(vb, &format!("conv2d_{}", first + 3), c, c)?,
            dw: DepthwiseConv2d::new(vb, &dw_name(dw), c, 3, 1, Pad::Same)?,
        })
    }

    fn forward(&self, x: &Nhwc, skip: &Nhwc) -> Nhwc {
        let up = kernels::resize_bilinear(x, skip.h, skip.w);
        let y = self.reduce.forward(&up, &Act::None);
        let sum = kernels::add(skip, &y, &Act::None);
        let gates = self.excite.gates(&kernels::global_avg_pool(&sum));
        let z = kernels::add(&kernels::scale_channels(skip, &gates), &y, &Act::None);
        let r = self.mix.forward(&z, &Act::Relu);
        let d = self.dw.forward(&r, &Act::Relu);
        kernels::add(&r, &d, &Act::None)
    }
}

/// The segmentation network.
#[derive(Debug, Clone)]
pub struct SelfieNet {
    stem: Conv2d,
    encoder: Vec<Bottleneck>,
    top: Conv2d,
    top_gate: Conv2d,
    up: [UpStage; 3],
    /// The 2x2 stride-2 transposed convolution to one channel: `[2][2][16]` and its bias.
    segment: Vec<f32>,
    segment_bias: f32,
}

impl SelfieNet {
    pub const INPUT: usize = 256;

    pub fn new(vb: VarBuilder) -> Result<Self> {
        let encoder = ENCODER
            .iter()
            .map(|&s| Bottleneck::new(&vb, s))
            .collect::<Result<_>>()?;
        let seg = vb.pp("segment");
        Ok(SelfieNet {
            stem: Conv2d::new(&vb, "conv2d", 3, 16, 3, 2, Pad::Same)?,
            encoder,
            top: Conv2d::pointwise(&vb, "conv2d_29", 32, 128)?,
            top_gate: Conv2d::pointwise(&vb, "conv2d_30", 32, 128)?,
            up: [
                UpStage::new(&vb, 31, 8, 128, 24)?,
                UpStage::new(&vb, 35, 9, 24, 16)?,
                UpStage::new(&vb, 39, 10, 16, 16)?,
            ],
            segment: get_vec(&seg, &[1, 2, 2, 16], "kernel")?,
            segment_bias: get_vec(&seg, &[1], "bias")?[0],
        })
    }

    /// `x`: 256x256x3 in [0, 1]; returns the 256x256 probabilities.
    pub fn forward(&self, x: &Nhwc) -> Nhwc {
        assert_eq!((x.h, x.w, x.c), (256, 256, 3), "segmentation input");
        let s128 = self.stem.forward(x, &Act::HardSwish);
        let s64 = self.encoder[0].forward(&s128);
        let h = self.encoder[1].forward(&s64);
        let s32 = self.encoder[2].forward(&h);
        let h = self.encoder[4..]
            .iter()
            .fold(self.encoder[3].forward(&s32), |h, b| b.forward(&h));
        let gates: Vec<f32> = self
            .top_gate
            .forward(&kernels::global_avg_pool(&h), &Act::None)
            .data
            .iter()
            .map(|&v| sigmoid(v))
            .collect();
        let mut h = kernels::scale_channels(&self.top.forward(&h, &Act::Relu), &gates);
        h = self.up[0].forward(&h, &s32);
        h = self.up[1].forward(&h, &s64);
        h = self.up[2].forward(&h, &s128);
        self.transpose_conv(&h)
    }

    /// `out[2y+i][2x+j] = sigmoid(bias + sum_c h[y][x][c] w[i][j][c])`.
    fn transpose_conv(&self, h: &Nhwc) -> Nhwc {
        let (oh, ow) = (h.h * 2, h.w * 2);
        let mut out = Nhwc::zeros(oh, ow, 1);
        for y in 0..h.h {
            for x in 0..h.w {
                let px = h.at(y, x);
                for i in 0..2 {
                    for j in 0..2 {
                        let w = &self.segment[(i * 2 + j) * h.c..(i * 2 + j + 1) * h.c];
                        let mut s = self.segment_bias;
                        for (a, b) in px.iter().zip(w) {
                            s += a * b;
                        }
                        out.data[(2 * y + i) * ow + 2 * x + j] = sigmoid(s);
                    }
                }
            }
        }
        out
    }
}
