//! The FLAME asset (`FLAME_with_eye.pt`, spec section 9): loading from the release's torch
//! pickle or from a safetensors file with the same keys flattened by `.`, validation, and saving.
//!
//! Accepted keys (the names used by the release and by the usual FLAME fitters):
//!
//! | key | shape | dtype |
//! |---|---|---|
//! | `flame_model.v_template` | `[V, 3]` | float |
//! | `flame_model.f` | `[F, 3]` | integer |
//! | `flame_model.shapedirs` | `[V, 3, K]` (release: K = 300 shape + 100 expression) | float |
//! | `flame_model.posedirs` | `[V, 3, 36]` | float |
//! | `flame_model.J_regressor` | `[5, V]` | float |
//! | `flame_model.weights` | `[V, 5]` | float |
//! | `flame_model.kintree_table` | `[2, 5]` (row 0: parents; entry 0 ignored) | integer |
//! | `lmk_embeddings.static_lmk_faces_idx` | `[Ls]` (release: 51) | integer |
//! | `lmk_embeddings.static_lmk_bary_coords` | `[Ls, 3]` | float |
//! | `lmk_embeddings.dynamic_lmk_faces_idx` | `[79, Ld]` (release: Ld = 17) | integer |
//! | `lmk_embeddings.dynamic_lmk_bary_coords` | `[79, Ld, 3]` | float |
//! | `lmk_embeddings.full_lmk_faces_idx_with_eye` | `[1, Lf]` or `[Lf]` (release: 70) | integer |
//! | `lmk_embeddings.full_lmk_bary_coords_with_eye` | `[1, Lf, 3]` or `[Lf, 3]` | float |
//!
//! Floats of any width are converted to f32 (the release stores f32); integers to i64. Other
//! keys in the file are ignored, among them a plain `full_lmk_faces_idx` /
//! `full_lmk_bary_coords` (68 points without the pupils): the release's FLAME reads only the
//! `_with_eye` pair (TRACKING.md section 4), so that is the 70-point set fitted and returned.

use std::path::Path;

use gagavatar_formats::FormatError;

use crate::embedding::{LandmarkEmbedding, DYNAMIC_ROWS};
use crate::error::{FlameError, Result};

pub const NUM_JOINTS: usize = 5;
/// Pose-corrective inputs: 9 entries of `R - I` for each of the 4 non-root joints.
pub const POSE_BASIS: usize = 36;
pub const RELEASE_SHAPE_COMPONENTS: usize = 300;
pub const RELEASE_EXPRESSION_COMPONENTS: usize = 100;

pub mod keys {
    pub const V_TEMPLATE: &str = "flame_model.v_template";
    pub const FACES: &str = "flame_model.f";
    pub const SHAPEDIRS: &str = "flame_model.shapedirs";
    pub const POSEDIRS: &str = "flame_model.posedirs";
    pub const J_REGRESSOR: &str = "flame_model.J_regressor";
    pub const WEIGHTS: &str = "flame_model.weights";
    pub const KINTREE: &str = "flame_model.kintree_table";
    pub const STATIC_FACES: &str = "lmk_embeddings.static_lmk_faces_idx";
    pub const STATIC_BARY: &str = "lmk_embeddings.static_lmk_bary_coords";
    pub const DYNAMIC_FACES: &str = "lmk_embeddings.dynamic_lmk_faces_idx";
    pub const DYNAMIC_BARY: &str = "lmk_embeddings.dynamic_lmk_bary_coords";
    /// The 70-point set (iBUG 68 with a static contour, then the two pupils).
    pub const FULL_FACES: &str = "lmk_embeddings.full_lmk_faces_idx_with_eye";
    pub const FULL_BARY: &str = "lmk_embeddings.full_lmk_bary_coords_with_eye";
}

/// The generic tensor values the file readers return (defined with the readers in
/// `gagavatar-formats`).
pub use gagavatar_formats::tensor::{RawData, RawTensor, TensorMap};

/// How the columns of `shapedirs` split into identity and expression bases.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BasisLayout {
    pub shape: usize,
    pub expression: usize,
}

impl BasisLayout {
    pub const RELEASE: Self = Self {
        shape: RELEASE_SHAPE_COMPONENTS,
        expression: RELEASE_EXPRESSION_COMPONENTS,
    };
}

#[derive(Debug, Clone, Default)]
pub struct LoadOptions {
    /// Needed only for files whose `shapedirs` does not have the release's 400 columns (reduced
    /// test assets): the split cannot be guessed from the column count alone.
    pub layout: Option<BasisLayout>,
}

/// A validated FLAME asset, host-side. Every index in it is known to be in range, so the forward
/// pass and landmark code can index without checks.
#[derive(Debug, Clone, PartialEq)]
pub struct FlameAsset {
    pub n_vertices: usize,
    /// `[V, 3]` row-major.
    pub v_template: Vec<f32>,
    pub faces: Vec<[u32; 3]>,
    /// `[V, 3, K]` row-major, exactly as in the file; K = layout.shape + layout.expression.
    pub shapedirs: Vec<f32>,
    pub layout: BasisLayout,
    /// `[V, 3, 36]` row-major, as in the file.
    pub posedirs: Vec<f32>,
    /// `[5, V]`.
    pub j_regressor: Vec<f32>,
    /// `[V, 5]`.
    pub weights: Vec<f32>,
    /// `[2, 5]` as stored (the root's parent entry is arbitrary in real files: 4294967295).
    pub kintree_table: Vec<i64>,
    /// `parents[i]` for joints 1..5 (`parents[0]` is unused: the root).
    pub parents: [usize; NUM_JOINTS],
    pub landmarks: LandmarkEmbedding,
}

fn get<'a>(map: &'a TensorMap, key: &str) -> Result<&'a RawTensor> {
    map.get(key).ok_or_else(|| FlameError::MissingKey {
        key: key.to_owned(),
    })
}

fn shape_err(key: &str, expected: impl Into<String>, t: &RawTensor) -> FlameError {
    FlameError::Shape {
        key: key.to_owned(),
        expected: expected.into(),
        found: t.shape.clone(),
    }
}

fn floats<'a>(key: &str, t: &'a RawTensor) -> Result<&'a [f32]> {
    match &t.data {
        RawData::Float(v) => {
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(FlameError::Invalid {
                    key: key.to_owned(),
                    reason: format!("element {i} is not finite ({})", v[i]),
                });
            }
            Ok(v)
        }
        RawData::Int(_) => Err(FlameError::DType {
            key: key.to_owned(),
            expected: "a float dtype",
            found: t.file_dtype.clone(),
        }),
    }
}

fn ints<'a>(key: &str, t: &'a RawTensor) -> Result<&'a [i64]> {
    match &t.data {
        RawData::Int(v) => Ok(v),
        RawData::Float(_) => Err(FlameError::DType {
            key: key.to_owned(),
            expected: "an integer dtype",
            found: t.file_dtype.clone(),
        }),
    }
}

/// Integer indices checked against `0..bound`.
fn indices(key: &str, t: &RawTensor, bound: usize, what: &str) -> Result<Vec<u32>> {
    ints(key, t)?
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            if x >= 0 && (x as u64) < bound as u64 {
                Ok(x as u32)
            } else {
                Err(FlameError::Invalid {
                    key: key.to_owned(),
                    reason: format!("element {i} = {x} is not a valid {what} index (< {bound})"),
                })
            }
        })
        .collect()
}

fn bary(key: &str, t: &RawTensor) -> Result<Vec<[f32; 3]>> {
    Ok(floats(key, t)?
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect())
}

impl FlameAsset {
    /// Loads a `.pt` torch zip checkpoint or a `.safetensors` file, told apart by content.
    pub fn load(path: &Path, options: &LoadOptions) -> Result<Self> {
        let map = read_tensor_file(path)?;
        Self::from_tensor_map(&map, options)
    }

    pub fn from_tensor_map(map: &TensorMap, options: &LoadOptions) -> Result<Self> {
        use keys::*;
        let vt = get(map, V_TEMPLATE)?;
        if vt.shape.len() != 2 || vt.shape[1] != 3 || vt.shape[0] == 0 {
            return Err(shape_err(V_TEMPLATE, "[V, 3]", vt));
        }
        let nv = vt.shape[0];
        let v_template = floats(V_TEMPLATE, vt)?.to_vec();

        let f = get(map, FACES)?;
        if f.shape.len() != 2 || f.shape[1] != 3 {
            return Err(shape_err(FACES, "[F, 3]", f));
        }
        let faces: Vec<[u32; 3]> = indices(FACES, f, nv, "vertex")?
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let nf = faces.len();

        let sd = get(map, SHAPEDIRS)?;
        if sd.shape.len() != 3 || sd.shape[0] != nv || sd.shape[1] != 3 {
            return Err(shape_err(SHAPEDIRS, format!("[{nv}, 3, K]"), sd));
        }
        let k = sd.shape[2];
        let layout = match options.layout {
            Some(l) if l.shape + l.expression == k => l,
            Some(l) => {
                return Err(FlameError::Invalid {
                    key: SHAPEDIRS.into(),
                    reason: format!(
                        "has {k} components but the requested layout is {} shape + {} expression",
                        l.shape, l.expression
                    ),
                })
            }
            None if k == RELEASE_SHAPE_COMPONENTS + RELEASE_EXPRESSION_COMPONENTS => {
                BasisLayout::RELEASE
            }
            None => {
                return Err(FlameError::Invalid {
                    key: SHAPEDIRS.into(),
                    reason: format!(
                        "has {k} components, not the release's 400 (300 shape + 100 expression); \
                         give the split explicitly (LoadOptions::layout)"
                    ),
                })
            }
        };
        let shapedirs = floats(SHAPEDIRS, sd)?.to_vec();

        let pd = get(map, POSEDIRS)?;
        if pd.shape != [nv, 3, POSE_BASIS] {
            return Err(shape_err(POSEDIRS, format!("[{nv}, 3, {POSE_BASIS}]"), pd));
        }
        let posedirs = floats(POSEDIRS, pd)?.to_vec();

        let jr = get(map, J_REGRESSOR)?;
        if jr.shape != [NUM_JOINTS, nv] {
            return Err(shape_err(J_REGRESSOR, format!("[{NUM_JOINTS}, {nv}]"), jr));
        }
        let j_regressor = floats(J_REGRESSOR, jr)?.to_vec();

        let w = get(map, WEIGHTS)?;
        if w.shape != [nv, NUM_JOINTS] {
            return Err(shape_err(WEIGHTS, format!("[{nv}, {NUM_JOINTS}]"), w));
        }
        let weights = floats(WEIGHTS, w)?.to_vec();

        let kt = get(map, KINTREE)?;
        if kt.shape != [2, NUM_JOINTS] {
            return Err(shape_err(KINTREE, format!("[2, {NUM_JOINTS}]"), kt));
        }
        let kintree_table = ints(KINTREE, kt)?.to_vec();
        let mut parents = [0usize; NUM_JOINTS];
        for (i, parent) in parents.iter_mut().enumerate().skip(1) {
            let p = kintree_table[i];
            // The chain is walked in index order, so a parent must come first.
            if p < 0 || p as usize >= i {
                return Err(FlameError::Invalid {
                    key: KINTREE.into(),
                    reason: format!(
                        "joint {i} has parent {p}; parents must precede their children"
                    ),
                });
            }
            *parent = p as usize;
        }

        let landmarks = Self::landmarks_from_map(map, nf)?;
        Ok(Self {
            n_vertices: nv,
            v_template,
            faces,
            shapedirs,
            layout,
            posedirs,
            j_regressor,
            weights,
            kintree_table,
            parents,
            landmarks,
        })
    }

    fn landmarks_from_map(map: &TensorMap, nf: usize) -> Result<LandmarkEmbedding> {
        use keys::*;
        let sf = get(map, STATIC_FACES)?;
        if sf.shape.len() != 1 {
            return Err(shape_err(STATIC_FACES, "[L]", sf));
        }
        let ls = sf.shape[0];
        let sb = get(map, STATIC_BARY)?;
        if sb.shape != [ls, 3] {
            return Err(shape_err(STATIC_BARY, format!("[{ls}, 3]"), sb));
        }
        let df = get(map, DYNAMIC_FACES)?;
        if df.shape.len() != 2 || df.shape[0] != DYNAMIC_ROWS {
            return Err(shape_err(DYNAMIC_FACES, format!("[{DYNAMIC_ROWS}, L]"), df));
        }
        let ld = df.shape[1];
        let db = get(map, DYNAMIC_BARY)?;
        if db.shape != [DYNAMIC_ROWS, ld, 3] {
            return Err(shape_err(
                DYNAMIC_BARY,
                format!("[{DYNAMIC_ROWS}, {ld}, 3]"),
                db,
            ));
        }
        let ff = get(map, FULL_FACES)?;
        let lf = match ff.shape.as_slice() {
            [1, l] | [l] => *l,
            _ => return Err(shape_err(FULL_FACES, "[1, L] or [L]", ff)),
        };
        let fb = get(map, FULL_BARY)?;
        if fb.shape != [1, lf, 3] && fb.shape != [lf, 3] {
            return Err(shape_err(
                FULL_BARY,
                format!("[1, {lf}, 3] or [{lf}, 3]"),
                fb,
            ));
        }
        Ok(LandmarkEmbedding {
            static_faces: indices(STATIC_FACES, sf, nf, "face")?,
            static_bary: bary(STATIC_BARY, sb)?,
            dynamic_faces: indices(DYNAMIC_FACES, df, nf, "face")?,
            dynamic_bary: bary(DYNAMIC_BARY, db)?,
            dynamic_count: ld,
            full_faces: indices(FULL_FACES, ff, nf, "face")?,
            full_bary: bary(FULL_BARY, fb)?,
        })
    }

    pub fn n_faces(&self) -> usize {
        self.faces.len()
    }

    /// A 64-bit fingerprint of the model (template, faces, blendshapes, skinning; FNV-1a over
    /// 32-bit words): equal for the same asset, different for another one (the synthetic
    /// stand-in, another seed of it, the release's FLAME). Weights record the fingerprint of the
    /// asset they were trained with, so a mismatch can be reported.
    pub fn fingerprint(&self) -> u64 {
        const PRIME: u64 = 0x0000_0100_0000_01b3;
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        let mut eat = |word: u32| {
            h ^= u64::from(word);
            h = h.wrapping_mul(PRIME);
        };
        eat(self.n_vertices as u32);
        eat(self.layout.shape as u32);
        eat(self.layout.expression as u32);
        for v in self
            .v_template
            .iter()
            .chain(&self.shapedirs)
            .chain(&self.posedirs)
            .chain(&self.j_regressor)
            .chain(&self.weights)
        {
            eat(v.to_bits());
        }
        for f in &self.faces {
            f.iter().for_each(|&i| eat(i));
        }
        h
    }

    pub fn n_components(&self) -> usize {
        self.layout.shape + self.layout.expression
    }

    /// The release layout: f32 floats, i64 integers, `[1, L]` full-landmark tables.
    pub fn to_tensor_map(&self) -> TensorMap {
        use keys::*;
        let nv = self.n_vertices;
        let k = self.n_components();
        let lm = &self.landmarks;
        let idx = |v: &[u32]| v.iter().map(|&x| x as i64).collect::<Vec<_>>();
        let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<_>>();
        let faces: Vec<i64> = self.faces.iter().flatten().map(|&x| x as i64).collect();
        let mut m = TensorMap::new();
        m.insert(
            V_TEMPLATE.into(),
            RawTensor::float(vec![nv, 3], self.v_template.clone()),
        );
        m.insert(
            FACES.into(),
            RawTensor::int(vec![self.faces.len(), 3], faces),
        );
        m.insert(
            SHAPEDIRS.into(),
            RawTensor::float(vec![nv, 3, k], self.shapedirs.clone()),
        );
        m.insert(
            POSEDIRS.into(),
            RawTensor::float(vec![nv, 3, POSE_BASIS], self.posedirs.clone()),
        );
        m.insert(
            J_REGRESSOR.into(),
            RawTensor::float(vec![NUM_JOINTS, nv], self.j_regressor.clone()),
        );
        m.insert(
            WEIGHTS.into(),
            RawTensor::float(vec![nv, NUM_JOINTS], self.weights.clone()),
        );
        m.insert(
            KINTREE.into(),
            RawTensor::int(vec![2, NUM_JOINTS], self.kintree_table.clone()),
        );
        let ls = lm.static_faces.len();
        let ld = lm.dynamic_count;
        let lf = lm.full_faces.len();
        m.insert(
            STATIC_FACES.into(),
            RawTensor::int(vec![ls], idx(&lm.static_faces)),
        );
        m.insert(
            STATIC_BARY.into(),
            RawTensor::float(vec![ls, 3], flat(&lm.static_bary)),
        );
        m.insert(
            DYNAMIC_FACES.into(),
            RawTensor::int(vec![DYNAMIC_ROWS, ld], idx(&lm.dynamic_faces)),
        );
        m.insert(
            DYNAMIC_BARY.into(),
            RawTensor::float(vec![DYNAMIC_ROWS, ld, 3], flat(&lm.dynamic_bary)),
        );
        m.insert(
            FULL_FACES.into(),
            RawTensor::int(vec![1, lf], idx(&lm.full_faces)),
        );
        m.insert(
            FULL_BARY.into(),
            RawTensor::float(vec![1, lf, 3], flat(&lm.full_bary)),
        );
        m
    }

    pub fn to_safetensors_bytes(&self) -> Result<Vec<u8>> {
        write_safetensors(&self.to_tensor_map())
    }
}

/// Reads a whole tensor file, dispatching on its first bytes (a zip is a torch checkpoint,
/// anything else must be safetensors).
pub fn read_tensor_file(path: &Path) -> Result<TensorMap> {
    use std::io::Read;
    let mut head = [0u8; 4];
    let n = std::fs::File::open(path)
        .and_then(|mut f| f.read(&mut head))
        .map_err(FormatError::io(path, "cannot read"))?;
    if n == 4 && &head == b"PK\x03\x04" {
        return Ok(gagavatar_formats::torch_zip::read_torch_zip(path)?);
    }
    match gagavatar_formats::safetensors::read_safetensors(path) {
        Ok(file) => Ok(file.tensors),
        Err(FormatError::Safetensors { label, reason }) => Err(FormatError::Safetensors {
            label,
            reason: format!("{reason} (and it is not a torch zip either)"),
        }
        .into()),
        Err(other) => Err(other.into()),
    }
}

/// Parses safetensors bytes (keys already flat).
pub fn read_safetensors(bytes: &[u8]) -> Result<TensorMap> {
    Ok(gagavatar_formats::safetensors::parse_safetensors(bytes, "safetensors data")?.tensors)
}

/// Serialises f32/i64 tensors to safetensors bytes.
pub fn write_safetensors(map: &TensorMap) -> Result<Vec<u8>> {
    use gagavatar_formats::safetensors::{to_safetensors_bytes, TensorOut};
    let tensors: Vec<TensorOut> = map
        .iter()
        .map(|(k, t)| match &t.data {
            RawData::Float(v) => TensorOut::f32(k.clone(), t.shape.clone(), v.as_slice()),
            RawData::Int(v) => TensorOut::i64(k.clone(), t.shape.clone(), v.as_slice()),
        })
        .collect();
    Ok(to_safetensors_bytes(&tensors, &Default::default())?)
}
