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

    /// The gates for the per-channel means of the input.
    fn gates(&self, means: Vec<f32>) -> Vec<f32> {
        let pooled = Nhwc::from_vec(1, 1, means.len(), means);
        let h = self.fc1.forward(&pooled, &Act::Relu);
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
        let h = self.dw.forward(&h, &self.act);
        let res = self.residual.then_some(x);
        match &self.excite {
            // The gates scale the projection's input channels: folded into its weights.
            Some(e) => {
                let gates = e.gates(kernels::channel_means(&h));
                self.project.forward_gated(&h, &gates, res, &Act::None)
            }
            None => self.project.forward_res(&h, res, &Act::None),
        }
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
        // The 1x1 convolution commutes with the bilinear upsampling (both linear, the
        // interpolation weights sum to one), so it runs at the low resolution on the wider
        // input: a quarter of the work.
        let y = kernels::resize_bilinear(&self.reduce.forward(x, &Act::None), skip.h, skip.w);
        // mean(skip + y) = mean(skip) + mean(y).
        let means: Vec<f32> = kernels::channel_means(skip)
            .iter()
            .zip(kernels::channel_means(&y))
            .map(|(a, b)| a + b)
            .collect();
        let gates = self.excite.gates(means);
        let z = kernels::scale_add(skip, &gates, &y);
        let r = self.mix.forward(&z, &Act::Relu);
        self.dw.forward_plus_input(&r, &Act::Relu)
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
    /// The 2x2 stride-2 transposed convolution to one channel, as a 1x1 convolution from 16
    /// channels to the 4 taps (`[2][2]`, each with the bias).
    segment: kernels::Packed,
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
            segment: kernels::Packed::new(
                &get_vec(&seg, &[1, 2, 2, 16], "kernel")?,
                &[get_vec(&seg, &[1], "bias")?[0]; 4],
                4,
                16,
            ),
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
        // relu(z) * g = relu(g z) for the (positive) sigmoid gates: folded into the weights.
        let mut h = self.top.forward_relu_scaled(&h, &gates);
        h = self.up[0].forward(&h, &s32);
        h = self.up[1].forward(&h, &s64);
        h = self.up[2].forward(&h, &s128);
        self.transpose_conv(&h)
    }

    /// `out[2y+i][2x+j] = sigmoid(bias + sum_c h[y][x][c] w[i][j][c])`: the four taps of
    /// each input pixel as a 1x1 convolution to four channels, then unshuffled.
    fn transpose_conv(&self, h: &Nhwc) -> Nhwc {
        let mut taps = kernels::pointwise(h, &self.segment, kernels::Residual::None, &Act::None);
        kernels::sigmoid_in_place(&mut taps.data);
        let (oh, ow) = (h.h * 2, h.w * 2);
        let mut out = Nhwc::uninit(oh, ow, 1);
        for y in 0..h.h {
            let src = &taps.data[y * h.w * 4..(y + 1) * h.w * 4];
            for i in 0..2 {
                let row = &mut out.data[(2 * y + i) * ow..(2 * y + i + 1) * ow];
                for (pair, t) in row.chunks_exact_mut(2).zip(src.chunks_exact(4)) {
                    pair.copy_from_slice(&t[2 * i..2 * i + 2]);
                }
            }
        }
        out
    }
}
