//! The FLAME forward pass (spec section 9): blendshapes, joint regression, Rodrigues, pose
//! correctives, the kinematic chain and linear blend skinning, then the release's x5 scale.
//!
//! Everything is built from candle tensor ops on `[B, ...]` batches, so `Var`s on the codes get
//! gradients, and the same model runs in f32 (inference) or f64 (gradient checks).

use candle_core::{DType, Device, Tensor};

use crate::asset::{FlameAsset, NUM_JOINTS, POSE_BASIS};
use crate::embedding::LandmarkEmbedding;
use crate::error::{FlameError, Result};
use crate::rodrigues::rodrigues;
use crate::skinning::{SharedSkinning, Skinning, TRANSFORM_LEN};

/// The release multiplies FLAME vertices by 5 before anything else sees them (spec section 2).
pub const FLAME_SCALE: f64 = 5.0;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlameConfig {
    /// Identity components used (the first `n_shape` of the asset's shape basis).
    pub n_shape: usize,
    /// Expression components used (the first `n_exp` of the asset's expression basis).
    pub n_exp: usize,
    pub scale: f64,
}

impl Default for FlameConfig {
    fn default() -> Self {
        Self {
            n_shape: 300,
            n_exp: 100,
            scale: FLAME_SCALE,
        }
    }
}

/// Codes for a batch of B heads, all in the model's dtype and on its device.
#[derive(Debug, Clone)]
pub struct FlameParams {
    /// `[B, n_shape]`
    pub shape: Tensor,
    /// `[B, n_exp]`
    pub expression: Tensor,
    /// `[B, 6]`: global rotation (usually zero: tracked data puts it in the camera), then jaw.
    pub pose: Tensor,
    /// `[B, 6]`: first eye joint (index 3), then second (index 4), axis-angle.
    pub eye: Tensor,
}

impl FlameParams {
    pub fn zeros(model: &FlameModel, batch: usize) -> Result<Self> {
        let z = |n: usize| Tensor::zeros((batch, n), model.dtype, &model.device);
        Ok(Self {
            shape: z(model.config.n_shape)?,
            expression: z(model.config.n_exp)?,
            pose: z(6)?,
            eye: z(6)?,
        })
    }
}

#[derive(Debug, Clone)]
pub struct FlameOutput {
    /// `[B, V, 3]`, scaled.
    pub vertices: Tensor,
    /// `[B, 5, 3]` posed joint positions, scaled.
    pub joints: Tensor,
    /// `[B, 5, 3, 3]` local joint rotations (global, neck, jaw, eye, eye).
    pub rotations: Tensor,
}

/// The identity part of FLAME for one or more shape codes: the rest-pose vertices with the
/// shape blendshapes applied, and the joints regressed from them (both unscaled).
///
/// When a whole sequence is driven with one source shape code (spec section 10), computing this
/// once removes the 300-component shape basis (three quarters of the blendshape data) from every
/// frame. It stays attached to the autograd graph of the shape code it came from.
#[derive(Debug, Clone)]
pub struct FlameIdentity {
    /// `[Bi, V, 3]`
    v_shaped: Tensor,
    /// `[Bi, 5, 3]`
    joints: Tensor,
}

impl FlameIdentity {
    /// Number of shape codes held; 1 broadcasts over any batch of frames.
    pub fn batch(&self) -> usize {
        self.v_shaped.dims()[0]
    }

    /// `[Bi, V, 3]` template plus shape blendshapes, unscaled.
    pub fn v_shaped(&self) -> &Tensor {
        &self.v_shaped
    }

    /// `[Bi, 5, 3]` rest-pose joints of `v_shaped`, unscaled.
    pub fn joints(&self) -> &Tensor {
        &self.joints
    }
}

/// A FLAME model ready to run: bases sliced to the configured counts and laid out for matmuls.
#[derive(Debug, Clone)]
pub struct FlameModel {
    pub config: FlameConfig,
    /// [`FlameAsset::fingerprint`] of the asset this model was built from.
    pub asset_fingerprint: u64,
    pub device: Device,
    pub dtype: DType,
    pub n_vertices: usize,
    pub faces: Vec<[u32; 3]>,
    pub parents: [usize; NUM_JOINTS],
    pub landmarks: LandmarkEmbedding,
    /// `[V, 3]`
    v_template: Tensor,
    /// `[n_shape, V*3]`; `None` when `n_shape` is 0.
    shape_dirs: Option<Tensor>,
    /// `[n_exp + 36, V*3]`: expression blendshapes, then the pose correctives (the file's
    /// `[V, 3, 36]` reshaped to `[V*3, 36]` and transposed, as in FLAME). Per frame both are
    /// linear in a small code, so one stacked matmul serves them.
    exp_pose_dirs: Tensor,
    /// `J_regressor v_template`, `[5, 3]`. Regressing joints from the template and from the
    /// bases separately is the same linear map as regressing from `v_shaped`, at 1/1000 the cost.
    j_template: Tensor,
    /// `[n_shape, 15]`: `J_regressor` applied to each shape blendshape.
    j_shape_dirs: Option<Tensor>,
    /// `[n_exp, 15]`: the same for the expression blendshapes.
    j_exp_dirs: Option<Tensor>,
    /// `[3, 3]`, subtracted from the joint rotations for the pose feature.
    eye3: Tensor,
    /// The fused CPU skinning kernel (shared, so cloning the model does not copy the weights).
    skinning: SharedSkinning,
    /// `[V, 5]` (tensor-op skinning, non-CPU devices)
    weights: Tensor,
    /// `[V, 15]`: each joint's weight repeated for x, y, z (tensor-op skinning).
    weights15: Tensor,
    /// `[15, 3]`: sums the per-joint xyz blocks (tensor-op skinning).
    block_sum: Tensor,
}

impl FlameModel {
    /// The model with all of the asset's shape and expression components and the release's
    /// x5 scale: what every command and the dataset tools use.
    pub fn from_asset(asset: &FlameAsset, device: &Device, dtype: DType) -> Result<Self> {
        let config = FlameConfig {
            n_shape: asset.layout.shape,
            n_exp: asset.layout.expression,
            scale: FLAME_SCALE,
        };
        Self::new(asset, config, device, dtype)
    }

    pub fn new(
        asset: &FlameAsset,
        config: FlameConfig,
        device: &Device,
        dtype: DType,
    ) -> Result<Self> {
        if config.n_shape > asset.layout.shape {
            return Err(FlameError::Components {
                what: "shape",
                available: asset.layout.shape,
                requested: config.n_shape,
            });
        }
        if config.n_exp > asset.layout.expression {
            return Err(FlameError::Components {
                what: "expression",
                available: asset.layout.expression,
                requested: config.n_exp,
            });
        }
        if !matches!(dtype, DType::F32 | DType::F64) {
            return Err(FlameError::Input {
                name: "dtype",
                reason: format!("FLAME runs in f32 or f64, not {dtype:?}"),
            });
        }
        let nv = asset.n_vertices;
        let k_file = asset.n_components();
        // Shape rows first, then expression rows, then the 36 pose-corrective rows.
        let columns: Vec<usize> = (0..config.n_shape)
            .chain((0..config.n_exp).map(|e| asset.layout.shape + e))
            .collect();
        let k = columns.len();
        let mut sd = vec![0f32; (k + POSE_BASIS) * nv * 3];
        for (row, &col) in columns.iter().enumerate() {
            let dst = &mut sd[row * nv * 3..(row + 1) * nv * 3];
            for (i, d) in dst.iter_mut().enumerate() {
                *d = asset.shapedirs[i * k_file + col];
            }
        }
        let pd = &mut sd[k * nv * 3..];
        for i in 0..nv * 3 {
            for p in 0..POSE_BASIS {
                pd[p * nv * 3 + i] = asset.posedirs[i * POSE_BASIS + p];
            }
        }
        let regress = |field: &dyn Fn(usize) -> f64| -> Vec<f64> {
            let mut out = vec![0f64; NUM_JOINTS * 3];
            for j in 0..NUM_JOINTS {
                let row = &asset.j_regressor[j * nv..(j + 1) * nv];
                for (v, &w) in row.iter().enumerate() {
                    if w != 0.0 {
                        for c in 0..3 {
                            out[j * 3 + c] += w as f64 * field(v * 3 + c);
                        }
                    }
                }
            }
            out
        };
        let jt = regress(&|i| asset.v_template[i] as f64);
        let mut jsd = Vec::with_capacity(k * NUM_JOINTS * 3);
        for row in 0..k {
            let base = &sd[row * nv * 3..(row + 1) * nv * 3];
            jsd.extend(regress(&|i| base[i] as f64));
        }

        let weights15: Vec<f32> = asset.weights.iter().flat_map(|&w| [w, w, w]).collect();
        let block_sum: Vec<f32> = (0..NUM_JOINTS * 3)
            .flat_map(|r| (0..3).map(move |c| if r % 3 == c { 1.0 } else { 0.0 }))
            .collect();
        let cpu = Device::Cpu;
        let to = |t: Tensor| -> Result<Tensor> { Ok(t.to_dtype(dtype)?.to_device(device)?) };
        let (ns, ne, v3, j3) = (config.n_shape, config.n_exp, nv * 3, NUM_JOINTS * 3);
        let basis = |rows: std::ops::Range<usize>| -> Result<Tensor> {
            let n = rows.len();
            let data = sd[rows.start * v3..rows.end * v3].to_vec();
            to(Tensor::from_vec(data, (n, v3), &cpu)?)
        };
        let j_basis = |rows: std::ops::Range<usize>| -> Result<Option<Tensor>> {
            if rows.is_empty() {
                return Ok(None);
            }
            let n = rows.len();
            let data = jsd[rows.start * j3..rows.end * j3].to_vec();
            Ok(Some(to(Tensor::from_vec(data, (n, j3), &cpu)?)?))
        };
        Ok(Self {
            config,
            asset_fingerprint: asset.fingerprint(),
            device: device.clone(),
            dtype,
            n_vertices: nv,
            faces: asset.faces.clone(),
            parents: asset.parents,
            landmarks: asset.landmarks.clone(),
            v_template: to(Tensor::from_vec(asset.v_template.clone(), (nv, 3), &cpu)?)?,
            shape_dirs: if ns > 0 { Some(basis(0..ns)?) } else { None },
            exp_pose_dirs: basis(ns..ns + ne + POSE_BASIS)?,
            j_template: to(Tensor::from_vec(jt, (NUM_JOINTS, 3), &cpu)?)?,
            j_shape_dirs: j_basis(0..ns)?,
            j_exp_dirs: j_basis(ns..ns + ne)?,
            eye3: Tensor::eye(3, dtype, device)?,
            skinning: SharedSkinning::new(Skinning::new(&asset.weights, config.scale)),
            weights: to(Tensor::from_vec(
                asset.weights.clone(),
                (nv, NUM_JOINTS),
                &cpu,
            )?)?,
            weights15: to(Tensor::from_vec(weights15, (nv, NUM_JOINTS * 3), &cpu)?)?,
            block_sum: to(Tensor::from_vec(block_sum, (NUM_JOINTS * 3, 3), &cpu)?)?,
        })
    }

    fn check(
        &self,
        name: &'static str,
        t: &Tensor,
        cols: usize,
        batch: Option<usize>,
    ) -> Result<usize> {
        let dims = t.dims();
        if dims.len() != 2 || dims[1] != cols || batch.is_some_and(|b| b != dims[0]) {
            let b = batch.map_or("B".to_string(), |b| b.to_string());
            return Err(FlameError::Input {
                name,
                reason: format!("shape {dims:?}, expected [{b}, {cols}]"),
            });
        }
        if t.dtype() != self.dtype {
            return Err(FlameError::Input {
                name,
                reason: format!("dtype {:?}, model runs in {:?}", t.dtype(), self.dtype),
            });
        }
        if !t.device().same_device(&self.device) {
            return Err(FlameError::Input {
                name,
                reason: format!("on {:?}, model runs on {:?}", t.device(), self.device),
            });
        }
        Ok(dims[0])
    }

    /// `[n_exp + 36, V * 3]`: the expression blendshapes, then the pose correctives (for other
    /// backends of the forward pass, e.g. the GPU drive path).
    pub fn exp_pose_dirs(&self) -> &Tensor {
        &self.exp_pose_dirs
    }

    /// `[n_exp, 15]`: the joint regressor applied to each expression blendshape; `None` when
    /// the model uses no expression components.
    pub fn j_exp_dirs(&self) -> Option<&Tensor> {
        self.j_exp_dirs.as_ref()
    }

    /// `[V, 5]` linear-blend-skinning weights.
    pub fn skinning_weights(&self) -> &Tensor {
        &self.weights
    }

    /// The full 15-value pose `[global, neck = 0, jaw, eye, eye]`, `[B, 15]`.
    pub fn full_pose(&self, pose: &Tensor, eye: &Tensor) -> Result<Tensor> {
        let b = pose.dim(0)?;
        let neck = Tensor::zeros((b, 3), self.dtype, &self.device)?;
        Ok(Tensor::cat(
            &[&pose.narrow(1, 0, 3)?, &neck, &pose.narrow(1, 3, 3)?, eye],
            1,
        )?)
    }

    /// The identity part for `[Bi, n_shape]` shape codes (see [`FlameIdentity`]).
    pub fn identity(&self, shape: &Tensor) -> Result<FlameIdentity> {
        let b = self.check("shape", shape, self.config.n_shape, None)?;
        let nv = self.n_vertices;
        let (v_shaped, joints) = match (&self.shape_dirs, &self.j_shape_dirs) {
            (Some(sd), Some(jsd)) => (
                shape
                    .matmul(sd)?
                    .reshape((b, nv, 3))?
                    .broadcast_add(&self.v_template)?,
                shape
                    .matmul(jsd)?
                    .reshape((b, NUM_JOINTS, 3))?
                    .broadcast_add(&self.j_template)?,
            ),
            // No shape components: one template serves every code.
            _ => (self.v_template.unsqueeze(0)?, self.j_template.unsqueeze(0)?),
        };
        Ok(FlameIdentity { v_shaped, joints })
    }

    pub fn forward(&self, p: &FlameParams) -> Result<FlameOutput> {
        let b = self.check("shape", &p.shape, self.config.n_shape, None)?;
        self.check("expression", &p.expression, self.config.n_exp, Some(b))?;
        let identity = self.identity(&p.shape)?;
        self.forward_with_identity(&identity, &p.expression, &p.pose, &p.eye)
    }

    /// The forward pass for a precomputed identity: `expression` `[B, n_exp]`, `pose` and `eye`
    /// `[B, 6]`. The identity holds one shape (used for all B frames) or B. Same result as
    /// [`FlameModel::forward`] with the identity's shape codes, and differentiable in all inputs.
    pub fn forward_with_identity(
        &self,
        identity: &FlameIdentity,
        expression: &Tensor,
        pose: &Tensor,
        eye: &Tensor,
    ) -> Result<FlameOutput> {
        let b = self.check("expression", expression, self.config.n_exp, None)?;
        self.check("pose", pose, 6, Some(b))?;
        self.check("eye", eye, 6, Some(b))?;
        let bi = identity.batch();
        let id_dims = [bi, self.n_vertices, 3];
        if (bi != 1 && bi != b)
            || identity.v_shaped.dims() != id_dims
            || identity.joints.dims() != [bi, NUM_JOINTS, 3]
            || identity.v_shaped.dtype() != self.dtype
            || !identity.v_shaped.device().same_device(&self.device)
        {
            return Err(FlameError::Input {
                name: "identity",
                reason: format!(
                    "{:?} {:?} on {:?}, expected [1 or {b}, {}, 3] {:?} on {:?} (built by this \
                     model's `identity`)",
                    identity.v_shaped.dims(),
                    identity.v_shaped.dtype(),
                    identity.v_shaped.device(),
                    self.n_vertices,
                    self.dtype,
                    self.device
                ),
            });
        }
        let nv = self.n_vertices;

        // Rotations; the pose feature drives the correctives together with the expression.
        let full_pose = self.full_pose(pose, eye)?;
        let rot =
            rodrigues(&full_pose.reshape((b * NUM_JOINTS, 3))?)?.reshape((b, NUM_JOINTS, 3, 3))?;
        let pose_feature = rot
            .narrow(1, 1, NUM_JOINTS - 1)?
            .broadcast_sub(&self.eye3)?
            .reshape((b, POSE_BASIS))?;
        let coeffs = if self.config.n_exp > 0 {
            Tensor::cat(&[expression, &pose_feature], 1)?
        } else {
            pose_feature
        };
        let v_posed = coeffs
            .matmul(&self.exp_pose_dirs)?
            .reshape((b, nv, 3))?
            .broadcast_add(&identity.v_shaped)?;
        let joints = match &self.j_exp_dirs {
            Some(jed) => expression
                .matmul(jed)?
                .reshape((b, NUM_JOINTS, 3))?
                .broadcast_add(&identity.joints)?,
            None => identity
                .joints
                .broadcast_as((b, NUM_JOINTS, 3))?
                .contiguous()?,
        };

        // Kinematic chain: world rotation/translation of each joint, then the skinning transform
        // A_i = [R_i | t_i - R_i J_i] that moves rest-pose points attached to joint i.
        let mut world_r: Vec<Tensor> = Vec::with_capacity(NUM_JOINTS);
        let mut world_t: Vec<Tensor> = Vec::with_capacity(NUM_JOINTS);
        let mut trans: Vec<Tensor> = Vec::with_capacity(NUM_JOINTS);
        for i in 0..NUM_JOINTS {
            let r_i = rot.narrow(1, i, 1)?.squeeze(1)?; // [B, 3, 3]
            let j_i = joints.narrow(1, i, 1)?.squeeze(1)?.unsqueeze(2)?; // [B, 3, 1]
            let (r_w, t_w) = if i == 0 {
                (r_i, j_i.clone())
            } else {
                let par = self.parents[i];
                let j_p = joints.narrow(1, par, 1)?.squeeze(1)?.unsqueeze(2)?;
                let rel = (&j_i - j_p)?;
                let r_w = world_r[par].matmul(&r_i)?;
                let t_w = (world_r[par].matmul(&rel)? + &world_t[par])?;
                (r_w, t_w)
            };
            trans.push((&t_w - r_w.matmul(&j_i)?)?); // [B, 3, 1]
            world_r.push(r_w);
            world_t.push(t_w);
        }

        let verts = if self.device.is_cpu() {
            let blocks = world_r
                .iter()
                .zip(&trans)
                .map(|(r, t)| Tensor::cat(&[r, t], 2))
                .collect::<candle_core::Result<Vec<_>>>()?;
            let transforms = Tensor::stack(&blocks, 1)?.reshape((b, NUM_JOINTS, TRANSFORM_LEN))?;
            v_posed
                .contiguous()?
                .apply_op2_arc(&transforms, self.skinning.op())?
        } else {
            self.skin_with_tensor_ops(&v_posed, &world_r, &trans)?
                .affine(self.config.scale, 0.0)?
        };

        let posed_joints = Tensor::stack(&world_t, 1)?.squeeze(3)?;
        Ok(FlameOutput {
            vertices: verts,
            joints: posed_joints.affine(self.config.scale, 0.0)?,
            rotations: rot,
        })
    }

    /// Skinning, sum_j w_vj (R_j v + t_j), for devices without the fused kernel: three large
    /// matmuls and one leading-dim broadcast (candle's fast paths) rather than per-vertex 3x4
    /// transforms: rotate every vertex by every joint ([B, V, 3] x [B, 3, 15]), weight, sum the
    /// joint blocks with a constant [15, 3] matrix, then add the blended translations.
    fn skin_with_tensor_ops(
        &self,
        v_posed: &Tensor,
        world_r: &[Tensor],
        trans: &[Tensor],
    ) -> Result<Tensor> {
        let (b, nv, _) = v_posed.dims3()?;
        let rot_t = world_r
            .iter()
            .map(|r| r.t())
            .collect::<candle_core::Result<Vec<_>>>()?;
        let rot_all = Tensor::cat(&rot_t, 2)?; // [B, 3, 15]
        let per_joint = v_posed.matmul(&rot_all)?.broadcast_mul(&self.weights15)?; // [B, V, 15]
        let rotated = per_joint
            .reshape((b * nv, NUM_JOINTS * 3))?
            .matmul(&self.block_sum)?;
        let t_blend = self
            .weights
            .broadcast_matmul(&Tensor::stack(trans, 1)?.squeeze(3)?)?; // [B, V, 3]
        Ok((rotated.reshape((b, nv, 3))? + t_blend)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::synthesize;

    /// The fused CPU kernel against the tensor-op skinning used on other devices, on arbitrary
    /// (not even rigid) transforms, in both dtypes.
    #[test]
    fn fused_skinning_matches_tensor_op_skinning() {
        let asset = synthesize(1);
        // Outputs reach ~30 here (random unit transforms, x5), so f32 rounding is a few 1e-6.
        for (dtype, tol) in [(DType::F32, 1e-5), (DType::F64, 1e-13)] {
            let m = FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, dtype).unwrap();
            let b = 3;
            let rand = |shape: &[usize]| {
                Tensor::randn(0f64, 1f64, shape, &Device::Cpu)
                    .unwrap()
                    .to_dtype(dtype)
                    .unwrap()
            };
            let v_posed = (rand(&[b, m.n_vertices, 3]) * 0.3).unwrap();
            let rs: Vec<Tensor> = (0..NUM_JOINTS).map(|_| rand(&[b, 3, 3])).collect();
            let ts: Vec<Tensor> = (0..NUM_JOINTS).map(|_| rand(&[b, 3, 1])).collect();
            let want = m
                .skin_with_tensor_ops(&v_posed, &rs, &ts)
                .unwrap()
                .affine(m.config.scale, 0.0)
                .unwrap();
            let blocks: Vec<Tensor> = rs
                .iter()
                .zip(&ts)
                .map(|(r, t)| Tensor::cat(&[r, t], 2).unwrap())
                .collect();
            let transforms = Tensor::stack(&blocks, 1)
                .unwrap()
                .reshape((b, NUM_JOINTS, TRANSFORM_LEN))
                .unwrap();
            let got = v_posed.apply_op2_arc(&transforms, m.skinning.op()).unwrap();
            let d = (got - want)
                .unwrap()
                .abs()
                .unwrap()
                .flatten_all()
                .unwrap()
                .max(0)
                .unwrap()
                .to_dtype(DType::F64)
                .unwrap()
                .to_scalar::<f64>()
                .unwrap();
            assert!(
                d <= tol,
                "{dtype:?}: fused and tensor-op skinning differ by {d:e}"
            );
        }
    }

    /// Zero weights are skipped only for finite transforms: a NaN joint poisons every vertex, as
    /// `W A` does in the matrix formulation and in the reference.
    #[test]
    fn non_finite_transforms_spread_like_the_matrix_form() {
        let asset = synthesize(1);
        let m = FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F32).unwrap();
        let v = Tensor::ones((1, m.n_vertices, 3), DType::F32, &Device::Cpu).unwrap();
        let mut a = vec![0f32; NUM_JOINTS * TRANSFORM_LEN];
        a[4 * TRANSFORM_LEN + 3] = f32::NAN; // the last eye's x translation
        let a = Tensor::from_vec(a, (1, NUM_JOINTS, TRANSFORM_LEN), &Device::Cpu).unwrap();
        let out = v.apply_op2_arc(&a, m.skinning.op()).unwrap();
        let out = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        // Rows x of every vertex are NaN, including the many that the eye does not move.
        assert!(out.chunks(3).all(|p| p[0].is_nan()));
        assert!(asset.weights.chunks(NUM_JOINTS).any(|w| w[4] == 0.0));
    }

    #[test]
    fn skinning_rejects_mismatched_operands() {
        let asset = synthesize(1);
        let m = FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F32).unwrap();
        let v = Tensor::zeros((2, m.n_vertices, 3), DType::F32, &Device::Cpu).unwrap();
        let a1 = Tensor::zeros((1, NUM_JOINTS, TRANSFORM_LEN), DType::F32, &Device::Cpu).unwrap();
        assert!(v.apply_op2_arc(&a1, m.skinning.op()).is_err());
        let a2 = Tensor::zeros((2, NUM_JOINTS, TRANSFORM_LEN), DType::F64, &Device::Cpu).unwrap();
        assert!(v.apply_op2_arc(&a2, m.skinning.op()).is_err());
    }
}
