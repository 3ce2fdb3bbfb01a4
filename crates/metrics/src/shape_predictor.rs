//! dlib's face landmark predictor (Kazemi & Sullivan 2014, "One millisecond face alignment with
//! an ensemble of regression trees"), evaluated as dlib's `shape_predictor::operator()` does,
//! for the public-domain 5-point model `shape_predictor_5_face_landmarks.dat` (converted by
//! `tools/identity/convert_dlib.py`; the 68-point model is not used: its training data forbids
//! commercial use).
//!
//! The shape lives in a normalised frame where the face rectangle's top-left corner is (0, 0)
//! and its bottom-right corner (1, 1). Starting from the mean shape, each of the cascades
//!  1. fits the similarity transform from the mean shape to the current shape (its linear part,
//!     rounded to f32),
//!  2. reads its feature pixels: each is stored as an anchor landmark and an offset from it in
//!     the mean shape; the offset is carried by the transform, added to the anchor's current
//!     position (f32), mapped to the image (f64) and rounded to a pixel (`floor(v + 0.5)`);
//!     the value is the pixel's grey level, `(r + g + b) / 3` in integers for colour images,
//!     and 0 outside the image,
//!  3. adds (f32) the leaf of every tree, a tree going left where `f[idx1] - f[idx2] > thresh`.
//!
//! The landmarks are the final shape mapped to the image and rounded to pixels, as dlib
//! returns them; [`Landmarks5::precise`] keeps the unrounded positions.

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{DType, Tensor};
use image::{GrayImage, RgbImage};

use crate::error::{input_err, Result};
use crate::geometry::{round_px, similarity_transform, Affine2, FaceRect};
use crate::weights::{check_tensors, read_tensors, weights_err};

/// The number of landmarks of the shipped model (and of dlib's face chips for it).
pub const NUM_LANDMARKS: usize = 5;

/// The smallest face rectangle side accepted, in pixels: below it the model's pixel features
/// collapse onto a handful of pixels and its landmarks mean nothing (dlib's HOG detector, by
/// comparison, finds faces down to about 40 pixels).
pub const MIN_FACE_SIDE: i64 = 10;

/// An image the predictor reads grey levels from, as dlib's `get_pixel_intensity`.
pub trait IntensityImage {
    fn size(&self) -> (u32, u32);
    /// The grey level at (x, y); only called inside the image.
    fn intensity(&self, x: u32, y: u32) -> u8;
}

impl IntensityImage for RgbImage {
    fn size(&self) -> (u32, u32) {
        self.dimensions()
    }
    fn intensity(&self, x: u32, y: u32) -> u8 {
        let i = (y as usize * self.width() as usize + x as usize) * 3;
        let p = &self.as_raw()[i..i + 3];
        ((p[0] as u32 + p[1] as u32 + p[2] as u32) / 3) as u8
    }
}

impl IntensityImage for GrayImage {
    fn size(&self) -> (u32, u32) {
        self.dimensions()
    }
    fn intensity(&self, x: u32, y: u32) -> u8 {
        self.as_raw()[y as usize * self.width() as usize + x as usize]
    }
}

/// The 5 landmarks of a face, in image pixels: 0 and 1 the outer and inner corner of the eye on
/// the image's right, 2 and 3 the outer and inner corner of the eye on the image's left, 4 the
/// base of the nose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Landmarks5 {
    /// Rounded to pixels, as dlib returns them (what the face chip is computed from).
    pub points: [[i64; 2]; NUM_LANDMARKS],
    /// The same before rounding.
    pub precise: [[f64; 2]; NUM_LANDMARKS],
}

#[derive(Debug, Clone, Copy)]
struct Split {
    idx1: u32,
    idx2: u32,
    thresh: f32,
}

#[derive(Debug, Clone)]
struct Cascade {
    /// Per feature pixel: the mean-shape landmark it is anchored to and its offset.
    anchor: Vec<u32>,
    deltas: Vec<[f32; 2]>,
    /// `[tree][split]`, each tree a complete binary tree in breadth-first order.
    splits: Vec<Split>,
    /// `[tree][leaf][coordinate]`.
    leaves: Vec<f32>,
}

/// dlib's cascade of regression trees for face landmarks.
#[derive(Debug, Clone)]
pub struct ShapePredictor {
    /// The mean shape, `x0, y0, x1, y1, ...` in the normalised frame.
    initial: Vec<f32>,
    cascades: Vec<Cascade>,
    trees: usize,
    splits_per_tree: usize,
}

fn to_vec<T: candle_core::WithDType>(t: &Tensor) -> Result<Vec<T>> {
    Ok(t.flatten_all()?.to_vec1::<T>()?)
}

impl ShapePredictor {
    /// Loads a converted predictor (`dlib_shape_predictor_5.safetensors`): tensors
    /// `initial_shape` [L, 2] f32, `split_idx1`, `split_idx2` [C, T, S] u32, `split_thresh`
    /// [C, T, S] f32, `leaf_values` [C, T, S + 1, L, 2] f32, `anchor_idx` [C, P] u32 and
    /// `deltas` [C, P, 2] f32, for C cascades of T trees with S splits and P feature pixels.
    pub fn load(path: &Path) -> Result<Self> {
        let t = read_tensors(path)?;
        let dims = |k: &str| t.get(k).map(|v| v.dims().to_vec()).unwrap_or_default();
        let csl = dims("split_idx1");
        let cp = dims("anchor_idx");
        if csl.len() != 3 || cp.len() != 2 {
            return Err(weights_err(
                path,
                format!("split_idx1 {csl:?} / anchor_idx {cp:?} are not [C, T, S] / [C, P]"),
            ));
        }
        let (c, nt, ns, np) = (csl[0], csl[1], csl[2], cp[1]);
        let l = NUM_LANDMARKS;
        if ns == 0 || (ns + 1) & ns != 0 {
            return Err(weights_err(
                path,
                format!("{ns} splits per tree is not a complete binary tree"),
            ));
        }
        let mut expected = BTreeMap::new();
        let mut want = |k: &str, shape: Vec<usize>, d: DType| {
            expected.insert(k.to_string(), (shape, Some(d)));
        };
        want("initial_shape", vec![l, 2], DType::F32);
        want("split_idx1", vec![c, nt, ns], DType::U32);
        want("split_idx2", vec![c, nt, ns], DType::U32);
        want("split_thresh", vec![c, nt, ns], DType::F32);
        want("leaf_values", vec![c, nt, ns + 1, l, 2], DType::F32);
        want("anchor_idx", vec![c, np], DType::U32);
        want("deltas", vec![c, np, 2], DType::F32);
        check_tensors(path, &t, &expected)?;

        let initial = to_vec::<f32>(&t["initial_shape"])?;
        let idx1 = to_vec::<u32>(&t["split_idx1"])?;
        let idx2 = to_vec::<u32>(&t["split_idx2"])?;
        let thresh = to_vec::<f32>(&t["split_thresh"])?;
        let leaves = to_vec::<f32>(&t["leaf_values"])?;
        let anchor = to_vec::<u32>(&t["anchor_idx"])?;
        let deltas = to_vec::<f32>(&t["deltas"])?;
        if idx1.iter().chain(&idx2).any(|&i| i as usize >= np) {
            return Err(weights_err(
                path,
                "a split reads a feature pixel that does not exist",
            ));
        }
        if anchor.iter().any(|&a| a as usize >= l) {
            return Err(weights_err(
                path,
                "a feature pixel is anchored to no landmark",
            ));
        }
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        if !finite(&initial) || !finite(&thresh) || !finite(&leaves) || !finite(&deltas) {
            return Err(weights_err(path, "non-finite values"));
        }
        let per_cascade_splits = nt * ns;
        let per_cascade_leaves = nt * (ns + 1) * 2 * l;
        let cascades = (0..c)
            .map(|ci| Cascade {
                anchor: anchor[ci * np..(ci + 1) * np].to_vec(),
                deltas: deltas[ci * np * 2..(ci + 1) * np * 2]
                    .chunks_exact(2)
                    .map(|d| [d[0], d[1]])
                    .collect(),
                splits: (ci * per_cascade_splits..(ci + 1) * per_cascade_splits)
                    .map(|i| Split {
                        idx1: idx1[i],
                        idx2: idx2[i],
                        thresh: thresh[i],
                    })
                    .collect(),
                leaves: leaves[ci * per_cascade_leaves..(ci + 1) * per_cascade_leaves].to_vec(),
            })
            .collect();
        Ok(Self {
            initial,
            cascades,
            trees: nt,
            splits_per_tree: ns,
        })
    }

    /// The 5 landmarks of the face in `rect` (which may reach outside the image).
    pub fn predict<I: IntensityImage>(&self, img: &I, rect: FaceRect) -> Result<Landmarks5> {
        let (w, h) = img.size();
        if w == 0 || h == 0 {
            return Err(input_err("image", "the image is empty"));
        }
        if rect.width() < MIN_FACE_SIDE || rect.height() < MIN_FACE_SIDE {
            return Err(input_err(
                "face rectangle",
                format!(
                    "{}x{} pixels is below the smallest face side of {MIN_FACE_SIDE}",
                    rect.width(),
                    rect.height()
                ),
            ));
        }
        if rect.right < 0 || rect.bottom < 0 || rect.left >= w as i64 || rect.top >= h as i64 {
            return Err(input_err(
                "face rectangle",
                format!(
                    "({}, {})-({}, {}) does not overlap the {w}x{h} image",
                    rect.left, rect.top, rect.right, rect.bottom
                ),
            ));
        }
        let to_img = unnormalizing(rect);
        let l2 = self.initial.len();
        let mut shape = self.initial.clone();
        let mut features = Vec::new();
        let leaf_len = l2;
        let leaves_per_tree = self.splits_per_tree + 1;
        for cascade in &self.cascades {
            let m = shape_tform(&self.initial, &shape);
            features.clear();
            for (&a, d) in cascade.anchor.iter().zip(&cascade.deltas) {
                let a = a as usize;
                // f32 as dlib: the offset carried by the transform, plus the anchor.
                let x = (m[0][0] * d[0] + m[0][1] * d[1]) + shape[2 * a];
                let y = (m[1][0] * d[0] + m[1][1] * d[1]) + shape[2 * a + 1];
                let p = to_img.apply([x as f64, y as f64]);
                let (px, py) = (round_px(p[0]), round_px(p[1]));
                let v = if px >= 0 && py >= 0 && px < w as i64 && py < h as i64 {
                    img.intensity(px as u32, py as u32) as f32
                } else {
                    0.0
                };
                features.push(v);
            }
            for t in 0..self.trees {
                let splits = &cascade.splits[t * self.splits_per_tree..][..self.splits_per_tree];
                let mut i = 0usize;
                while i < splits.len() {
                    let s = splits[i];
                    i = if features[s.idx1 as usize] - features[s.idx2 as usize] > s.thresh {
                        2 * i + 1
                    } else {
                        2 * i + 2
                    };
                }
                let leaf = i - splits.len();
                let vals = &cascade.leaves[(t * leaves_per_tree + leaf) * leaf_len..][..leaf_len];
                for (s, v) in shape.iter_mut().zip(vals) {
                    *s += v;
                }
            }
        }
        let mut out = Landmarks5 {
            points: [[0; 2]; NUM_LANDMARKS],
            precise: [[0.0; 2]; NUM_LANDMARKS],
        };
        for j in 0..NUM_LANDMARKS {
            let p = to_img.apply([shape[2 * j] as f64, shape[2 * j + 1] as f64]);
            if !(p[0].is_finite() && p[1].is_finite()) {
                return Err(input_err("face rectangle", "the landmarks are not finite"));
            }
            out.precise[j] = p;
            out.points[j] = [round_px(p[0]), round_px(p[1])];
        }
        Ok(out)
    }
}

/// The map from the normalised frame to the image: (0, 0) to the top-left corner, (1, 1) to
/// the bottom-right one (inclusive corners, dlib's `unnormalizing_tform`).
fn unnormalizing(r: FaceRect) -> Affine2 {
    Affine2 {
        m: [
            [(r.right - r.left) as f64, 0.0],
            [0.0, (r.bottom - r.top) as f64],
        ],
        b: [r.left as f64, r.top as f64],
    }
}

/// The linear part of the similarity from the mean shape to the current one, in f32.
fn shape_tform(from: &[f32], to: &[f32]) -> [[f32; 2]; 2] {
    let pts = |v: &[f32]| -> Vec<[f64; 2]> {
        v.chunks_exact(2)
            .map(|p| [p[0] as f64, p[1] as f64])
            .collect()
    };
    let a = similarity_transform(&pts(from), &pts(to));
    [
        [a.m[0][0] as f32, a.m[0][1] as f32],
        [a.m[1][0] as f32, a.m[1][1] as f32],
    ]
}
