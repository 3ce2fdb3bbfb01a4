//! The release's training loss (spec section 11): `total = img + box + percep + point` with
//! - `img = 0.5 (L1(coarse_rgb, gt) + L1(fine, gt))`, `coarse_rgb` = the first 3 channels of
//!   the splatted image, `L1` = mean absolute difference over all elements;
//! - `box = 0.5 (L1(coarse_rgb crop, gt crop) + L1(fine crop, gt crop))` on the target's
//!   head box (see [`crate::head_box`](mod@crate::head_box)), each crop resized to `box_size` (512 in the release);
//! - `percep = 0.01 (P(coarse_rgb crop, gt crop) + P(fine crop, gt crop))` with the frozen
//!   [`PerceptualLoss`] (off when no weights are given: the caller warns);
//! - `point = 10 mean_m |target_m - nearest lifted point|^2` ([`crate::nearest::lifting_loss`];
//!   off for the paper's "without lifting loss" ablation).
//!
//! Every `|x|` here has gradient `sign(x)` with `sign(0) = 0`, as PyTorch's `l1_loss` (candle's
//! `abs` would push exactly-matching pixels, e.g. an empty background, by a full unit).

use candle_core::{DType, Tensor};

use crate::error::{input_err, Result};
use crate::head_box::{crop_resize, head_boxes, HeadBox};
use crate::nearest::lifting_loss;
use crate::perceptual::PerceptualLoss;

/// Which terms, and the sizes and weights that presets may change.
#[derive(Debug, Clone, PartialEq)]
pub struct LossConfig {
    /// Side of the resized head-box crops (release 512).
    pub box_size: usize,
    /// The lifting-distance term (`false`: the "without lifting loss" ablation).
    pub lifting: bool,
    /// Factor of the perceptual term (release 0.01).
    pub percep_weight: f64,
}

impl LossConfig {
    pub fn release() -> Self {
        Self {
            box_size: 512,
            lifting: true,
            percep_weight: 0.01,
        }
    }
}

impl Default for LossConfig {
    fn default() -> Self {
        Self::release()
    }
}

/// One training sample batch's tensors (all on one device).
#[derive(Debug, Clone, Copy)]
pub struct LossInputs<'a> {
    /// Splatted image `[B, C >= 3, H, W]`; channels 0..3 are the coarse RGB.
    pub coarse: &'a Tensor,
    /// Neural renderer output `[B, 3, H, W]`.
    pub fine: &'a Tensor,
    /// Target image `[B, 3, H, W]` in [0, 1].
    pub gt: &'a Tensor,
    /// Target face bbox `[B, 4]`, `(x0, y0, x1, y1)` normalised to [0, 1].
    pub bbox: &'a Tensor,
    /// Both lifted point sets `[B, 2 S^2, 3]` (the avatar's `lifted_xyz`).
    pub lifted: &'a Tensor,
    /// Scaled target FLAME vertices `[B, V, 3]`.
    pub targets: &'a Tensor,
}

/// A loss term: the scalar tensor (for backward) and its value (for logging).
#[derive(Debug, Clone)]
pub struct Term {
    pub tensor: Tensor,
    pub value: f64,
}

impl Term {
    fn new(tensor: Tensor) -> Result<Self> {
        let value = tensor.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        Ok(Self { tensor, value })
    }
}

/// Every term of one evaluation; `percep` / `point` are `None` when switched off.
#[derive(Debug, Clone)]
pub struct LossTerms {
    pub img: Term,
    pub box_l1: Term,
    pub percep: Option<Term>,
    pub point: Option<Term>,
    pub total: Term,
    /// The head boxes used, per sample.
    pub boxes: Vec<HeadBox>,
}

/// `|x|` whose gradient is `sign(x)` with `sign(0) = 0` (as PyTorch's `l1_loss`).
fn abs_zero_subgradient(x: &Tensor) -> candle_core::Result<Tensor> {
    // `sign` carries no gradient in candle, so the product differentiates as sign(x).
    x.mul(&x.sign()?)
}

/// Mean absolute difference over all elements, with PyTorch's `l1_loss` gradient.
pub fn l1_loss(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    if a.dims() != b.dims() {
        return Err(input_err(
            "l1 operands",
            format!("shapes {:?} and {:?} differ", a.dims(), b.dims()),
        ));
    }
    Ok(abs_zero_subgradient(&(a - b)?)?.mean_all()?)
}

/// The loss of spec section 11.
#[derive(Debug, Clone)]
pub struct TrainLosses {
    pub cfg: LossConfig,
    percep: Option<PerceptualLoss>,
}

impl TrainLosses {
    /// `percep: None` switches the perceptual term off (the caller should warn).
    pub fn new(cfg: LossConfig, percep: Option<PerceptualLoss>) -> Self {
        Self { cfg, percep }
    }

    pub fn percep_enabled(&self) -> bool {
        self.percep.is_some()
    }

    /// The perceptual network, when the term is on.
    pub fn percep(&self) -> Option<&PerceptualLoss> {
        self.percep.as_ref()
    }

    /// Evaluates every enabled term. Errors on mismatched shapes, a NaN or degenerate bbox,
    /// empty or non-finite point sets.
    pub fn compute(&self, x: &LossInputs) -> Result<LossTerms> {
        let (b, h, w) = match x.fine.dims() {
            &[b, 3, h, w] if b > 0 => (b, h, w),
            other => {
                return Err(input_err(
                    "fine",
                    format!("expected [B, 3, H, W], got {other:?}"),
                ))
            }
        };
        match x.coarse.dims() {
            &[cb, c, ch, cw] if cb == b && c >= 3 && ch == h && cw == w => {}
            other => {
                return Err(input_err(
                    "coarse",
                    format!("expected [{b}, C >= 3, {h}, {w}], got {other:?}"),
                ))
            }
        }
        if x.gt.dims() != x.fine.dims() {
            return Err(input_err(
                "gt",
                format!("expected {:?}, got {:?}", x.fine.dims(), x.gt.dims()),
            ));
        }
        let dtype = x.fine.dtype();
        let coarse = x.coarse.narrow(1, 0, 3)?.to_dtype(dtype)?;
        let gt = x.gt.detach().to_dtype(dtype)?;
        let fine = x.fine;

        let img = ((l1_loss(&coarse, &gt)? + l1_loss(fine, &gt)?)? * 0.5)?;

        let boxes = head_boxes(x.bbox, h, w)?;
        if boxes.len() != b {
            return Err(input_err(
                "bbox",
                format!("{} boxes for a batch of {b}", boxes.len()),
            ));
        }
        let s = self.cfg.box_size;
        let gt_crop = crop_resize(&gt, &boxes, s)?;
        let coarse_crop = crop_resize(&coarse, &boxes, s)?;
        let fine_crop = crop_resize(fine, &boxes, s)?;
        let box_l1 = ((l1_loss(&coarse_crop, &gt_crop)? + l1_loss(&fine_crop, &gt_crop)?)? * 0.5)?;

        let percep = match &self.percep {
            Some(p) => {
                // One forward over both predictions; the target's features are shared.
                let target = p.features(&gt_crop)?;
                let pred = p.features(&Tensor::cat(&[&coarse_crop, &fine_crop], 0)?)?;
                let d = PerceptualLoss::distance(&pred, &target)?.to_dtype(dtype)?;
                Some((d * self.cfg.percep_weight)?)
            }
            None => None,
        };
        let point = if self.cfg.lifting {
            Some(lifting_loss(x.lifted, x.targets)?.to_dtype(dtype)?)
        } else {
            None
        };

        let mut total = (&img + &box_l1)?;
        for t in percep.iter().chain(point.iter()) {
            total = (total + t)?;
        }
        Ok(LossTerms {
            img: Term::new(img)?,
            box_l1: Term::new(box_l1)?,
            percep: percep.map(Term::new).transpose()?,
            point: point.map(Term::new).transpose()?,
            total: Term::new(total)?,
            boxes,
        })
    }
}
