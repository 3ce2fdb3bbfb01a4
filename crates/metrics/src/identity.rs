//! Face identity embeddings for CSIM: dlib's face-recognition ResNet
//! (`dlib_face_recognition_resnet_model_v1`, public domain; `anet_type` of dlib's
//! `dnn_face_recognition_ex.cpp`), run on dlib's 150x150 face chips.
//!
//! The network, from the input (dlib's template types read from the inside out):
//! * input: RGB chip, `(v - mean_rgb) / 256` per channel (`input_rgb_image_sized<150>`);
//! * stem: 7x7 convolution, 32 channels, stride 2, no padding (150 -> 72); affine; ReLU;
//!   3x3 max pool, stride 2, no padding (72 -> 35);
//! * residual blocks `relu(block(x) + shortcut(x))`, `block` = conv 3x3 (stride s), affine, ReLU,
//!   conv 3x3, affine; convolutions pad by 1 at stride 1 and not at all at stride 2 (dlib's
//!   default); a downsampling block's shortcut is a 2x2 average pool with stride 2. Stages
//!   (channels x blocks): 32 x 3 at 35, 64 x 4 (first down, 17), 128 x 3 (down, 8),
//!   256 x 3 (down: the block gives 3x3, the pool 4x4), 256 x 1 (down: 1x1 and 2x2);
//! * dlib adds tensors of different sizes by zero-extending both to the larger size in every
//!   dimension (`add_prev`), which happens at every downsampling block (more channels; and at
//!   the last two also a larger shortcut map);
//! * global average pool, 128 x 256 linear map without bias: the 128-D descriptor.
//!
//! dlib's affine layers are its batch norms frozen for inference (`x * gamma + beta`). The
//! descriptor is not normalised by dlib (its `loss_metric` compares raw descriptors by
//! Euclidean distance, 0.6 being its same-person threshold); CSIM is the cosine of two
//! descriptors, i.e. the dot product of the L2-normalised ones.
//!
//! Weight keys (`dlib_face_recognition_resnet_v1.safetensors`, written by
//! `tools/identity/convert_dlib.py`): `input.mean_rgb` [3]; `stem.conv.{weight,bias}`,
//! `stem.affine.{gamma,beta}`; `stages.{s}.{b}.conv{1,2}.{weight,bias}`,
//! `stages.{s}.{b}.affine{1,2}.{gamma,beta}`; `fc.weight` [128, 256].

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, D};
use candle_nn::VarBuilder;
use gagavatar_ops::{conv2d, Conv2dSpec};
use image::RgbImage;

use crate::align::{extract_image_chip, face_chip_details, CHIP_PADDING, CHIP_SIZE};
use crate::error::{input_err, Result};
use crate::geometry::FaceRect;
use crate::shape_predictor::{Landmarks5, ShapePredictor};
use crate::weights::{check_tensors, read_tensors, weights_err, RESNET_FILE, SHAPE_PREDICTOR_FILE};

/// The descriptor's length.
pub const EMBEDDING_DIM: usize = 128;

/// (channels, blocks, whether the first block halves the resolution), from the input side.
pub const STAGES: [(usize, usize, bool); 5] = [
    (32, 3, false),
    (64, 4, true),
    (128, 3, true),
    (256, 3, true),
    (256, 1, true),
];
const STEM_CHANNELS: usize = 32;

/// dlib's `con_`: square kernel, bias, padding `k / 2` at stride 1 and none otherwise.
#[derive(Debug, Clone)]
pub struct Conv {
    weight: Tensor,
    bias: Tensor,
    spec: Conv2dSpec,
}

impl Conv {
    pub fn new(vb: VarBuilder, cin: usize, cout: usize, k: usize, stride: usize) -> Result<Self> {
        Ok(Self {
            weight: vb.get((cout, cin, k, k), "weight")?,
            bias: vb.get(cout, "bias")?,
            spec: Conv2dSpec {
                stride,
                padding: if stride == 1 { k / 2 } else { 0 },
            },
        })
    }

    /// This convolution followed by `affine`, as one convolution: `w gamma`, `b gamma + beta`
    /// per output channel (dlib's affine layers only ever follow a convolution here).
    pub fn fold_affine(&self, affine: &Affine) -> Result<Self> {
        let c = self.bias.dim(0)?;
        let g = affine.gamma.reshape((c, 1, 1, 1))?;
        Ok(Self {
            weight: self.weight.broadcast_mul(&g)?,
            bias: ((&self.bias * affine.gamma.flatten_all()?)? + affine.beta.flatten_all()?)?,
            spec: self.spec,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(conv2d(x, &self.weight, Some(&self.bias), self.spec)?)
    }
}

/// dlib's `affine_` in convolution mode: `x * gamma[c] + beta[c]`.
#[derive(Debug, Clone)]
pub struct Affine {
    gamma: Tensor,
    beta: Tensor,
}

impl Affine {
    pub fn new(vb: VarBuilder, c: usize) -> Result<Self> {
        Ok(Self {
            gamma: vb.get(c, "gamma")?.reshape((1, c, 1, 1))?,
            beta: vb.get(c, "beta")?.reshape((1, c, 1, 1))?,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.broadcast_mul(&self.gamma)?.broadcast_add(&self.beta)?)
    }
}

/// Convolution 7x7/2, affine, ReLU, max pool 3x3/2 (the affine folded into the convolution).
#[derive(Debug, Clone)]
pub struct Stem {
    conv: Conv,
}

impl Stem {
    pub fn new(vb: VarBuilder) -> Result<Self> {
        let conv = Conv::new(vb.pp("conv"), 3, STEM_CHANNELS, 7, 2)?;
        let affine = Affine::new(vb.pp("affine"), STEM_CHANNELS)?;
        Ok(Self {
            conv: conv.fold_affine(&affine)?,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = self.conv.forward(x)?.relu()?;
        Ok(y.max_pool2d_with_stride(3, 2)?)
    }
}

/// One residual block (`ares` / `ares_down` of dlib's example), each affine folded into the
/// convolution before it.
#[derive(Debug, Clone)]
pub struct ResBlock {
    conv1: Conv,
    conv2: Conv,
    down: bool,
}

impl ResBlock {
    pub fn new(vb: VarBuilder, cin: usize, cout: usize, down: bool) -> Result<Self> {
        let conv1 = Conv::new(vb.pp("conv1"), cin, cout, 3, if down { 2 } else { 1 })?;
        let affine1 = Affine::new(vb.pp("affine1"), cout)?;
        let conv2 = Conv::new(vb.pp("conv2"), cout, cout, 3, 1)?;
        let affine2 = Affine::new(vb.pp("affine2"), cout)?;
        Ok(Self {
            conv1: conv1.fold_affine(&affine1)?,
            conv2: conv2.fold_affine(&affine2)?,
            down,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = self.conv1.forward(x)?.relu()?;
        let y = self.conv2.forward(&y)?;
        let shortcut = if self.down {
            x.avg_pool2d_with_stride(2, 2)?
        } else {
            x.clone()
        };
        Ok(add_zero_extended(&y, &shortcut)?.relu()?)
    }
}

/// dlib's `add_prev`: both tensors zero-extended (at the end of each dimension) to the larger
/// size, then added.
fn add_zero_extended(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    if a.dims() == b.dims() {
        return Ok((a + b)?);
    }
    let target: Vec<usize> = a
        .dims()
        .iter()
        .zip(b.dims())
        .map(|(x, y)| *x.max(y))
        .collect();
    let extend = |t: &Tensor| -> Result<Tensor> {
        let mut t = t.clone();
        for (d, &n) in target.iter().enumerate() {
            let have = t.dim(d)?;
            if have < n {
                t = t.pad_with_zeros(d, 0, n - have)?;
            }
        }
        Ok(t)
    };
    Ok((extend(a)? + extend(b)?)?)
}

/// dlib's face-recognition ResNet (see the module docs).
#[derive(Debug, Clone)]
pub struct FaceResNet {
    mean_rgb: [f32; 3],
    stem: Stem,
    blocks: Vec<ResBlock>,
    /// [128, 256]
    fc: Tensor,
}

impl FaceResNet {
    /// Every key of the weight file with its shape.
    pub fn expected_keys() -> BTreeMap<String, Vec<usize>> {
        let mut m = BTreeMap::new();
        let conv = |m: &mut BTreeMap<String, Vec<usize>>, p: &str, cin, cout, k| {
            m.insert(format!("{p}.weight"), vec![cout, cin, k, k]);
            m.insert(format!("{p}.bias"), vec![cout]);
        };
        let affine = |m: &mut BTreeMap<String, Vec<usize>>, p: &str, c| {
            m.insert(format!("{p}.gamma"), vec![c]);
            m.insert(format!("{p}.beta"), vec![c]);
        };
        m.insert("input.mean_rgb".into(), vec![3]);
        conv(&mut m, "stem.conv", 3, STEM_CHANNELS, 7);
        affine(&mut m, "stem.affine", STEM_CHANNELS);
        let mut cin = STEM_CHANNELS;
        for (s, &(ch, n, _)) in STAGES.iter().enumerate() {
            for b in 0..n {
                let p = format!("stages.{s}.{b}");
                conv(&mut m, &format!("{p}.conv1"), cin, ch, 3);
                affine(&mut m, &format!("{p}.affine1"), ch);
                conv(&mut m, &format!("{p}.conv2"), ch, ch, 3);
                affine(&mut m, &format!("{p}.affine2"), ch);
                cin = ch;
            }
        }
        m.insert("fc.weight".into(), vec![EMBEDDING_DIM, cin]);
        m
    }

    pub fn new(vb: VarBuilder) -> Result<Self> {
        let mean = vb.get(3, "input.mean_rgb")?.to_vec1::<f32>()?;
        let stem = Stem::new(vb.pp("stem"))?;
        let mut blocks = Vec::new();
        let mut cin = STEM_CHANNELS;
        for (s, &(ch, n, down)) in STAGES.iter().enumerate() {
            for b in 0..n {
                let vbb = vb.pp(format!("stages.{s}.{b}"));
                blocks.push(ResBlock::new(vbb, cin, ch, down && b == 0)?);
                cin = ch;
            }
        }
        Ok(Self {
            mean_rgb: [mean[0], mean[1], mean[2]],
            stem,
            blocks,
            fc: vb.get((EMBEDDING_DIM, cin), "fc.weight")?,
        })
    }

    /// Loads the converted weights (f16 or f32 in the file, f32 in memory) after checking that
    /// the file holds exactly the expected tensors.
    pub fn load(path: &Path) -> Result<Self> {
        let tensors = read_tensors(path)?;
        let expected = Self::expected_keys()
            .into_iter()
            .map(|(k, s)| (k, (s, None)))
            .collect();
        check_tensors(path, &tensors, &expected)?;
        for (k, t) in &tensors {
            if !matches!(t.dtype(), DType::F32 | DType::F16 | DType::BF16) {
                return Err(weights_err(
                    path,
                    format!("`{k}` is {:?}, not a float", t.dtype()),
                ));
            }
        }
        let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
        Self::new(vb)
    }

    /// The chips as the network's input: `[N, 3, 150, 150]`, `(v - mean_rgb) / 256`.
    pub fn input_tensor(&self, chips: &[&RgbImage]) -> Result<Tensor> {
        let n = CHIP_SIZE * CHIP_SIZE;
        let mut data = Vec::with_capacity(chips.len() * 3 * n);
        for (i, chip) in chips.iter().enumerate() {
            if chip.dimensions() != (CHIP_SIZE as u32, CHIP_SIZE as u32) {
                return Err(input_err(
                    "face chip",
                    format!(
                        "chip {i} is {}x{}, the network takes {CHIP_SIZE}x{CHIP_SIZE}",
                        chip.width(),
                        chip.height()
                    ),
                ));
            }
            for (c, mean) in self.mean_rgb.iter().enumerate() {
                data.extend(
                    chip.as_raw()
                        .chunks_exact(3)
                        .map(|p| (p[c] as f32 - mean) / 256.0),
                );
            }
        }
        Ok(Tensor::from_vec(
            data,
            (chips.len(), 3, CHIP_SIZE, CHIP_SIZE),
            &Device::Cpu,
        )?)
    }

    /// `x` [N, 3, 150, 150] (see [`Self::input_tensor`]) -> descriptors [N, 128].
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut y = self.stem.forward(x)?;
        for b in &self.blocks {
            y = b.forward(&y)?;
        }
        let pooled = y.mean(D::Minus1)?.mean(D::Minus1)?;
        Ok(pooled.matmul(&self.fc.t()?)?)
    }
}

/// A face's identity descriptor (dlib's raw 128-D output).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Embedding {
    pub descriptor: [f32; EMBEDDING_DIM],
}

impl Embedding {
    /// The descriptor scaled to unit length.
    pub fn unit(&self) -> Result<[f32; EMBEDDING_DIM]> {
        let norm = self
            .descriptor
            .iter()
            .map(|v| (*v as f64) * (*v as f64))
            .sum::<f64>()
            .sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(input_err(
                "embedding",
                format!("its norm is {norm}, not a positive finite number"),
            ));
        }
        let mut out = [0f32; EMBEDDING_DIM];
        for (o, v) in out.iter_mut().zip(&self.descriptor) {
            *o = (*v as f64 / norm) as f32;
        }
        Ok(out)
    }

    /// Cosine similarity with another embedding (CSIM), in [-1, 1].
    pub fn cosine(&self, other: &Embedding) -> Result<f64> {
        csim(self, other)
    }
}

/// CSIM: the cosine similarity of two identity descriptors (f64 accumulation).
pub fn csim(a: &Embedding, b: &Embedding) -> Result<f64> {
    let (mut ab, mut aa, mut bb) = (0f64, 0f64, 0f64);
    for (x, y) in a.descriptor.iter().zip(&b.descriptor) {
        let (x, y) = (*x as f64, *y as f64);
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    let denom = (aa * bb).sqrt();
    if !(denom.is_finite() && denom > 0.0 && ab.is_finite()) {
        return Err(input_err(
            "embedding",
            "a descriptor is zero or not finite; the cosine is undefined",
        ));
    }
    Ok((ab / denom).clamp(-1.0, 1.0))
}

/// A face aligned as dlib does for recognition.
#[derive(Debug, Clone)]
pub struct AlignedFace {
    pub landmarks: Landmarks5,
    /// The 150x150 chip.
    pub chip: RgbImage,
}

/// The whole identity pipeline: 5-point landmarks in a face rectangle, dlib's 150x150 chip,
/// the ResNet descriptor.
#[derive(Debug, Clone)]
pub struct IdentityNet {
    predictor: ShapePredictor,
    resnet: FaceResNet,
}

impl IdentityNet {
    /// Loads both models from a folder holding the converted files (see
    /// [`crate::weights::default_asset_dir`]).
    pub fn load(dir: &Path) -> Result<Self> {
        Self::from_files(&dir.join(SHAPE_PREDICTOR_FILE), &dir.join(RESNET_FILE))
    }

    pub fn from_files(predictor: &Path, resnet: &Path) -> Result<Self> {
        Ok(Self {
            predictor: ShapePredictor::load(predictor)?,
            resnet: FaceResNet::load(resnet)?,
        })
    }

    pub fn predictor(&self) -> &ShapePredictor {
        &self.predictor
    }

    pub fn resnet(&self) -> &FaceResNet {
        &self.resnet
    }

    /// Landmarks and chip of the face in `rect`.
    pub fn align(&self, img: &RgbImage, rect: FaceRect) -> Result<AlignedFace> {
        let landmarks = self.predictor.predict(img, rect)?;
        let details = face_chip_details(&landmarks, CHIP_SIZE, CHIP_PADDING)?;
        let chip = extract_image_chip(img, &details)?;
        Ok(AlignedFace { landmarks, chip })
    }

    /// The identity descriptor of the face in `rect` (dlib's
    /// `compute_face_descriptor(img, shape_predictor(img, rect))`).
    pub fn embed(&self, img: &RgbImage, rect: FaceRect) -> Result<Embedding> {
        let face = self.align(img, rect)?;
        self.embed_chip(&face.chip)
    }

    /// The descriptor of an aligned 150x150 chip.
    pub fn embed_chip(&self, chip: &RgbImage) -> Result<Embedding> {
        let mut v = self.embed_chips(&[chip])?;
        v.pop()
            .ok_or_else(|| input_err("face chip", "no descriptor came back"))
    }

    /// Descriptors of several chips in one batch.
    pub fn embed_chips(&self, chips: &[&RgbImage]) -> Result<Vec<Embedding>> {
        if chips.is_empty() {
            return Ok(Vec::new());
        }
        let x = self.resnet.input_tensor(chips)?;
        let y = self.resnet.forward(&x)?.to_vec2::<f32>()?;
        y.into_iter()
            .map(|row| {
                let descriptor: [f32; EMBEDDING_DIM] = row.try_into().map_err(|_| {
                    input_err("embedding", "the network returned a wrong-sized descriptor")
                })?;
                if descriptor.iter().any(|v| !v.is_finite()) {
                    return Err(input_err("embedding", "the descriptor is not finite"));
                }
                Ok(Embedding { descriptor })
            })
            .collect()
    }

    /// CSIM of the faces in two images.
    pub fn csim(
        &self,
        a: &RgbImage,
        rect_a: FaceRect,
        b: &RgbImage,
        rect_b: FaceRect,
    ) -> Result<f64> {
        let ea = self.embed(a, rect_a)?;
        let eb = self.embed(b, rect_b)?;
        csim(&ea, &eb)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    /// f32 results of the same arithmetic in another order.
    const TOL: f32 = 1e-5;

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    #[test]
    fn the_pipeline_can_be_shared_across_threads() {
        fn shared<T: Send + Sync>() {}
        shared::<IdentityNet>();
        shared::<Embedding>();
    }

    #[test]
    fn folded_affine_equals_convolution_then_affine() {
        let dev = Device::Cpu;
        let mut t = HashMap::new();
        t.insert(
            "c.weight".to_string(),
            Tensor::randn(0f32, 0.2, (8, 5, 3, 3), &dev).unwrap(),
        );
        t.insert(
            "c.bias".to_string(),
            Tensor::randn(0f32, 1.0, 8, &dev).unwrap(),
        );
        t.insert(
            "a.gamma".to_string(),
            Tensor::randn(0f32, 1.0, 8, &dev).unwrap(),
        );
        t.insert(
            "a.beta".to_string(),
            Tensor::randn(0f32, 1.0, 8, &dev).unwrap(),
        );
        let vb = VarBuilder::from_tensors(t, DType::F32, &dev);
        for stride in [1, 2] {
            let conv = Conv::new(vb.pp("c"), 5, 8, 3, stride).unwrap();
            let affine = Affine::new(vb.pp("a"), 8).unwrap();
            let x = Tensor::randn(0f32, 1.0, (2, 5, 11, 9), &dev).unwrap();
            let want = affine.forward(&conv.forward(&x).unwrap()).unwrap();
            let got = conv.fold_affine(&affine).unwrap().forward(&x).unwrap();
            assert_eq!(got.dims(), want.dims());
            let d = max_diff(&got, &want);
            assert!(d < TOL, "stride {stride}: max |diff| {d}");
        }
    }

    #[test]
    fn zero_extended_addition_matches_dlib() {
        let dev = Device::Cpu;
        // [1, 2, 2, 2] block output + [1, 1, 3, 3] shortcut -> [1, 2, 3, 3].
        let a = Tensor::arange(1f32, 9.0, &dev)
            .unwrap()
            .reshape((1, 2, 2, 2))
            .unwrap();
        let b = Tensor::full(10f32, (1, 1, 3, 3), &dev).unwrap();
        let y = add_zero_extended(&a, &b).unwrap();
        assert_eq!(y.dims(), &[1, 2, 3, 3]);
        let v = y.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        #[rustfmt::skip]
        let want = [
            11.0, 12.0, 10.0,   13.0, 14.0, 10.0,   10.0, 10.0, 10.0,
            5.0, 6.0, 0.0,      7.0, 8.0, 0.0,      0.0, 0.0, 0.0,
        ];
        assert_eq!(v, want);
    }

    #[test]
    fn csim_is_scale_invariant_and_refuses_zero_or_nan() {
        let a = Embedding {
            descriptor: std::array::from_fn(|i| (i as f32 * 0.37).sin()),
        };
        let b = Embedding {
            descriptor: a.descriptor.map(|v| v * 3.5),
        };
        assert!((csim(&a, &b).unwrap() - 1.0).abs() < 1e-12);
        let neg = Embedding {
            descriptor: a.descriptor.map(|v| -v),
        };
        assert!((csim(&a, &neg).unwrap() + 1.0).abs() < 1e-12);
        let unit = a.unit().unwrap();
        let n: f64 = unit.iter().map(|v| (*v as f64).powi(2)).sum();
        assert!((n - 1.0).abs() < 1e-6);
        let zero = Embedding {
            descriptor: [0.0; EMBEDDING_DIM],
        };
        assert!(csim(&a, &zero).is_err());
        assert!(zero.unit().is_err());
        let mut nan = a;
        nan.descriptor[3] = f32::NAN;
        assert!(csim(&a, &nan).is_err());
    }
}
