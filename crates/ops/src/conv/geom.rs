//! The settings and shapes of one convolution, shared by the kernels below
//! [`crate::conv`].

use candle_core::{bail, Result, Shape};

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

/// Shapes of one convolution. Padding may differ between the axes internally (the input
/// gradient of a rectangular kernel needs `kh-1-p` rows but `kw-1-p` columns).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Geom {
    pub b: usize,
    pub cin: usize,
    pub h: usize,
    pub w: usize,
    pub cout: usize,
    pub kh: usize,
    pub kw: usize,
    pub stride: usize,
    pub ph: usize,
    pub pw: usize,
    pub oh: usize,
    pub ow: usize,
}

impl Geom {
    pub(super) fn new(xd: &[usize], wd: &[usize], spec: Conv2dSpec) -> Result<Self> {
        let (&[b, cin, h, w], &[cout, wcin, kh, kw]) = (xd, wd) else {
            bail!("conv2d: input must be [B, Cin, H, W] and weight [Cout, Cin, kh, kw], got {xd:?} and {wd:?}");
        };
        if cin != wcin {
            bail!("conv2d: input {xd:?} has {cin} channels but weight {wd:?} expects {wcin}");
        }
        Self::with_pads(
            b,
            cin,
            h,
            w,
            cout,
            kh,
            kw,
            spec.stride,
            spec.padding,
            spec.padding,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn with_pads(
        b: usize,
        cin: usize,
        h: usize,
        w: usize,
        cout: usize,
        kh: usize,
        kw: usize,
        stride: usize,
        ph: usize,
        pw: usize,
    ) -> Result<Self> {
        if [b, cin, h, w, cout, kh, kw].contains(&0) {
            bail!("conv2d: empty dimension in input [{b}, {cin}, {h}, {w}] or weight [{cout}, {cin}, {kh}, {kw}]");
        }
        if stride == 0 {
            bail!("conv2d: stride must be positive");
        }
        if h + 2 * ph < kh || w + 2 * pw < kw {
            bail!(
                "conv2d: padded input {}x{} is smaller than the {kh}x{kw} kernel",
                h + 2 * ph,
                w + 2 * pw
            );
        }
        let (oh, ow) = (
            (h + 2 * ph - kh) / stride + 1,
            (w + 2 * pw - kw) / stride + 1,
        );
        Ok(Self {
            b,
            cin,
            h,
            w,
            cout,
            kh,
            kw,
            stride,
            ph,
            pw,
            oh,
            ow,
        })
    }

    /// Rows of the patch matrix.
    pub fn k(&self) -> usize {
        self.cin * self.kh * self.kw
    }

    pub(super) fn out_shape(&self) -> Shape {
        Shape::from((self.b, self.cout, self.oh, self.ow))
    }

    /// The input gradient of a stride-1 convolution is itself a stride-1 convolution of the
    /// output gradient with the flipped, transposed filters and padding `k-1-p`.
    pub(super) fn transposed(&self) -> Option<Self> {
        if self.stride != 1 || self.ph >= self.kh || self.pw >= self.kw {
            return None;
        }
        let (ph, pw) = (self.kh - 1 - self.ph, self.kw - 1 - self.pw);
        let g = Self::with_pads(
            self.b, self.cout, self.oh, self.ow, self.cin, self.kh, self.kw, 1, ph, pw,
        )
        .ok()?;
        (g.oh == self.h && g.ow == self.w).then_some(g)
    }
}
