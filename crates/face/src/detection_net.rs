//! The two face detector networks (spec TRACKING.md section 8): BlazeFace short range (128x128
//! input, faces within about 2 m) and the full-range detector (192x192, a feature pyramid over
//! double BlazeBlocks). Both take the letterboxed image in [-1, 1] and return, per anchor, 16
//! regression values (box centre and size, six keypoints, in input pixels relative to the
//! anchor) and a face logit.

use candle_core::Result;
use candle_nn::VarBuilder;

use crate::kernels::{self, Act};
use crate::layers::{BlazeBlock, Conv2d, DepthwiseConv2d, Pad};
use crate::tensor::Nhwc;

/// Raw detector outputs: `regressors [anchors][16]` and `logits [anchors]`.
#[derive(Debug, Clone)]
pub struct RawDetections {
    pub regressors: Vec<f32>,
    pub logits: Vec<f32>,
}

/// BlazeFace short range: a 5x5 stride-2 stem, 16 BlazeBlocks (ReLU), SSD heads on the 16x16
/// (2 anchors per cell) and 8x8 (6 anchors per cell) maps: 896 anchors.
#[derive(Debug, Clone)]
pub struct ShortRangeNet {
    stem: Conv2d,
    blocks: Vec<BlazeBlock>,
    cls8: Conv2d,
    reg8: Conv2d,
    cls16: Conv2d,
    reg16: Conv2d,
}

/// (input, output channels, stride) of the short-range BlazeBlocks.
const SHORT_BLOCKS: [(usize, usize, usize); 16] = [
    (24, 24, 1),
    (24, 28, 1),
    (28, 32, 2),
    (32, 36, 1),
    (36, 42, 1),
    (42, 48, 2),
    (48, 56, 1),
    (56, 64, 1),
    (64, 72, 1),
    (72, 80, 1),
    (80, 88, 1),
    (88, 96, 2),
    (96, 96, 1),
    (96, 96, 1),
    (96, 96, 1),
    (96, 96, 1),
];

/// Index of the block whose output feeds the 16x16 heads.
const SHORT_TAP: usize = 10;

impl ShortRangeNet {
    pub const INPUT: usize = 128;
    pub const ANCHORS: usize = 896;

    pub fn new(vb: VarBuilder) -> Result<Self> {
        let stem = Conv2d::new(&vb, "conv2d", 3, 24, 5, 2, Pad::Same)?;
        let blocks = SHORT_BLOCKS
            .iter()
            .enumerate()
            .map(|(i, &(cin, cout, s))| {
                let dw = if i == 0 {
                    "depthwise_conv2d".to_owned()
                } else {
                    format!("depthwise_conv2d_{i}")
                };
                BlazeBlock::new(
                    &vb,
                    (&dw, &format!("conv2d_{}", i + 1)),
                    cin,
                    cout,
                    s,
                    Act::Relu,
                )
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(ShortRangeNet {
            stem,
            blocks,
            cls8: Conv2d::pointwise(&vb, "classificator_8", 88, 2)?,
            reg8: Conv2d::pointwise(&vb, "regressor_8", 88, 32)?,
            cls16: Conv2d::pointwise(&vb, "classificator_16", 96, 6)?,
            reg16: Conv2d::pointwise(&vb, "regressor_16", 96, 96)?,
        })
    }

    /// `x`: 128x128x3 in [-1, 1].
    pub fn forward(&self, x: &Nhwc) -> RawDetections {
        assert_eq!((x.h, x.w, x.c), (128, 128, 3), "short-range detector input");
        let mut tap = self.stem.forward(x, &Act::Relu);
        for b in &self.blocks[..=SHORT_TAP] {
            tap = b.forward(&tap);
        }
        let mut h = self.blocks[SHORT_TAP + 1].forward(&tap);
        for b in &self.blocks[SHORT_TAP + 2..] {
            h = b.forward(&h);
        }
        // NHWC reshapes: anchors ordered by row, column, then anchor within the cell.
        let mut logits = self.cls8.forward(&tap, &Act::None).into_vec();
        logits.extend(self.cls16.forward(&h, &Act::None).data.iter());
        let mut regressors = self.reg8.forward(&tap, &Act::None).into_vec();
        regressors.extend(self.reg16.forward(&h, &Act::None).data.iter());
        RawDetections { regressors, logits }
    }
}

/// Two BlazeBlocks in one (the full-range detector): `dw, 1x1 down (ReLU), dw, 1x1 up`, plus
/// the input and a ReLU at stride 1; at stride 2 the second 1x1 ends in a ReLU and there is
/// no skip. Depthwise convolutions pad one pixel on every side (explicit ZeroPadding2D).
#[derive(Debug, Clone)]
struct DoubleBlock {
    dw1: DepthwiseConv2d,
    pw1: Conv2d,
    dw2: DepthwiseConv2d,
    pw2: Conv2d,
    residual: bool,
}

impl DoubleBlock {
    /// `i`: the index of the first depthwise layer (`depthwise_conv2d_{i}`, the second is
    /// `i + 1`); `j`: the index of the first 1x1 layer (`conv2d_{j}`, then `j + 1`).
    fn new(
        vb: &VarBuilder,
        i: usize,
        j: usize,
        c: usize,
        mid: usize,
        cout: usize,
        stride: usize,
    ) -> Result<Self> {
        let dw = |n: usize| {
            if n == 0 {
                "depthwise_conv2d".to_owned()
            } else {
                format!("depthwise_conv2d_{n}")
            }
        };
        Ok(DoubleBlock {
            dw1: DepthwiseConv2d::new(vb, &dw(i), c, 3, stride, Pad::Explicit(1))?,
            pw1: Conv2d::pointwise(vb, &format!("conv2d_{j}"), c, mid)?,
            dw2: DepthwiseConv2d::new(vb, &dw(i + 1), mid, 3, 1, Pad::Explicit(1))?,
            pw2: Conv2d::pointwise(vb, &format!("conv2d_{}", j + 1), mid, cout)?,
            residual: stride == 1,
        })
    }

    fn forward(&self, x: &Nhwc) -> Nhwc {
        let h = self.dw1.forward(x, &Act::None);
        let h = self.pw1.forward(&h, &Act::Relu);
        let h = self.dw2.forward(&h, &Act::None);
        self.pw2
            .forward_res(&h, self.residual.then_some(x), &Act::Relu)
    }
}

/// The full-range face detector (the wheel's sparse model, densified): a 3x3 stride-2 stem, 15
/// double blocks down to 6x6, a top-down pyramid back to 48x48 (bilinear upsampling plus 1x1
/// lateral connections, five more double blocks), and heads that produce the 48x48 map of
/// one anchor per cell (2304 anchors) through a stride-2 depthwise convolution and a 2x2
/// depth-to-space.
#[derive(Debug, Clone)]
pub struct FullRangeNet {
    stem: Conv2d,
    down: Vec<DoubleBlock>,
    top: Conv2d,
    lateral12: Conv2d,
    up12: Vec<DoubleBlock>,
    to24: Conv2d,
    lateral24: Conv2d,
    up24: Vec<DoubleBlock>,
    to48: Conv2d,
    lateral48: Conv2d,
    up48: Vec<DoubleBlock>,
    cls: Conv2d,
    cls_dw: DepthwiseConv2d,
    reg: Conv2d,
    reg_dw: DepthwiseConv2d,
}

/// (first depthwise index, first 1x1 index, channels, bottleneck, output channels, stride) of
/// the full-range encoder's double blocks, and after which block the 48, 24 and 12 pyramid
/// taps are taken (indices 4, 7, 10).
const FULL_DOWN: [(usize, usize, usize, usize, usize, usize); 15] = [
    (0, 1, 32, 8, 32, 1),
    (2, 3, 32, 8, 32, 1),
    (4, 5, 32, 16, 64, 2),
    (6, 7, 64, 16, 64, 1),
    (8, 9, 64, 16, 64, 1),
    (10, 11, 64, 32, 128, 2),
    (12, 13, 128, 32, 128, 1),
    (14, 15, 128, 32, 128, 1),
    (16, 17, 128, 48, 192, 2),
    (18, 19, 192, 48, 192, 1),
    (20, 21, 192, 48, 192, 1),
    (22, 23, 192, 96, 384, 2),
    (24, 25, 384, 96, 384, 1),
    (26, 27, 384, 96, 384, 1),
    (28, 29, 384, 96, 384, 1),
];

impl FullRangeNet {
    pub const INPUT: usize = 192;
    pub const ANCHORS: usize = 2304;

    pub fn new(vb: VarBuilder) -> Result<Self> {
        let dbl = |t: &[(usize, usize, usize, usize, usize, usize)]| {
            t.iter()
                .map(|&(i, j, c, m, o, s)| DoubleBlock::new(&vb, i, j, c, m, o, s))
                .collect::<Result<Vec<_>>>()
        };
        Ok(FullRangeNet {
            stem: Conv2d::new(&vb, "conv2d", 3, 32, 3, 2, Pad::Explicit(1))?,
            down: dbl(&FULL_DOWN)?,
            top: Conv2d::pointwise(&vb, "conv2d_31", 384, 96)?,
            lateral12: Conv2d::pointwise(&vb, "conv2d_32", 192, 96)?,
            up12: dbl(&[(30, 33, 96, 48, 96, 1), (32, 35, 96, 48, 96, 1)])?,
            to24: Conv2d::pointwise(&vb, "conv2d_37", 96, 64)?,
            lateral24: Conv2d::pointwise(&vb, "conv2d_38", 128, 64)?,
            up24: dbl(&[(34, 39, 64, 32, 64, 1), (36, 41, 64, 32, 64, 1)])?,
            to48: Conv2d::pointwise(&vb, "conv2d_43", 64, 48)?,
            lateral48: Conv2d::pointwise(&vb, "conv2d_44", 64, 48)?,
            up48: dbl(&[(38, 45, 48, 24, 48, 1)])?,
            cls: Conv2d::pointwise(&vb, "classifier_face_4_NO_PRUNING", 48, 4)?,
            cls_dw: DepthwiseConv2d::new(&vb, "depthwise_conv2d_40", 4, 3, 2, Pad::Explicit(1))?,
            reg: Conv2d::pointwise(&vb, "regressor_face_4_NO_PRUNING", 48, 64)?,
            reg_dw: DepthwiseConv2d::new(&vb, "depthwise_conv2d_41", 64, 3, 2, Pad::Explicit(1))?,
        })
    }

    /// `x`: 192x192x3 in [-1, 1].
    pub fn forward(&self, x: &Nhwc) -> RawDetections {
        assert_eq!((x.h, x.w, x.c), (192, 192, 3), "full-range detector input");
        // Blocks in sequence from a borrowed input (each range is non-empty).
        let run = |blocks: &[DoubleBlock], x: &Nhwc| {
            let h = blocks[0].forward(x);
            blocks[1..].iter().fold(h, |h, b| b.forward(&h))
        };
        let stem = self.stem.forward(x, &Act::Relu);
        let t48 = &run(&self.down[..5], &stem);
        let t24 = &run(&self.down[5..8], t48);
        let t12 = &run(&self.down[8..11], t24);
        let h = run(&self.down[11..], t12);
        let up = |small: &Nhwc, conv: &Conv2d, lateral: &Conv2d, big: &Nhwc| {
            let s = conv.forward(small, &Act::Relu);
            let s = kernels::resize_bilinear(&s, big.h, big.w);
            let l = lateral.forward(big, &Act::Relu);
            kernels::add(&l, &s, &Act::None)
        };
        let mut h = up(&h, &self.top, &self.lateral12, t12);
        for b in &self.up12 {
            h = b.forward(&h);
        }
        let mut h = up(&h, &self.to24, &self.lateral24, t24);
        for b in &self.up24 {
            h = b.forward(&h);
        }
        let mut h = up(&h, &self.to48, &self.lateral48, t48);
        for b in &self.up48 {
            h = b.forward(&h);
        }
        let c = self.cls.forward(&h, &Act::None);
        let c = kernels::depth_to_space2(&self.cls_dw.forward(&c, &Act::None));
        let r = self.reg.forward(&h, &Act::None);
        let r = kernels::depth_to_space2(&self.reg_dw.forward(&r, &Act::None));
        RawDetections {
            regressors: r.into_vec(),
            logits: c.into_vec(),
        }
    }
}
