//! The FLAME forward pass (spec section 9): blendshapes, joint regression, Rodrigues, pose
//! correctives, the kinematic chain and linear blend skinning, then the release's x5 scale.
//!
//! Everything is built from candle tensor ops on `[B, ...]` batches, so `Var`s on the codes get
//! gradients, and the same model runs in f32 (inference) or f64 (gradient checks).

use candle_core::{DType, Device, Tensor};

use crate::asset::{FlameAsset, NUM_JOINTS, POSE_BASIS};
use crate::error::{FlameError, Result};
use crate::landmarks::LandmarkEmbedding;
use crate::rodrigues::rodrigues;

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

/// A FLAME model ready to run: bases sliced to the configured counts and laid out for matmuls.
#[derive(Debug, Clone)]
pub struct FlameModel {
    pub config: FlameConfig,
    pub device: Device,
    pub dtype: DType,
    pub n_vertices: usize,
    pub faces: Vec<[u32; 3]>,
    pub parents: [usize; NUM_JOINTS],
    pub landmarks: LandmarkEmbedding,
    /// `[V, 3]`
    v_template: Tensor,
    /// `[K, V*3]` with K = n_shape + n_exp (shape rows first).
    shapedirs: Option<Tensor>,
    /// `[36, V*3]`: the file's `[V, 3, 36]` reshaped to `[V*3, 36]` and transposed, as in FLAME.
    posedirs: Tensor,
    /// `J_regressor v_template`, `[5, 3]`. Regressing joints from the template and from the
    /// bases separately is the same linear map as regressing from `v_shaped`, at 1/1000 the cost.
    j_template: Tensor,
    /// `[K, 15]`: `J_regressor` applied to each blendshape.
    j_shapedirs: Option<Tensor>,
    /// `[V, 5]`
    weights: Tensor,
    /// `[V, 15]`: each joint's weight repeated for x, y, z.
    weights15: Tensor,
    /// `[15, 3]`: sums the per-joint xyz blocks.
    block_sum: Tensor,
}

impl FlameModel {
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
        let columns: Vec<usize> = (0..config.n_shape)
            .chain((0..config.n_exp).map(|e| asset.layout.shape + e))
            .collect();
        let k = columns.len();
        let mut sd = vec![0f32; k * nv * 3];
        for (row, &col) in columns.iter().enumerate() {
            let dst = &mut sd[row * nv * 3..(row + 1) * nv * 3];
            for (i, d) in dst.iter_mut().enumerate() {
                *d = asset.shapedirs[i * k_file + col];
            }
        }
        let mut pd = vec![0f32; POSE_BASIS * nv * 3];
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
        let (shapedirs, j_shapedirs) = if k > 0 {
            (
                Some(to(Tensor::from_vec(sd, (k, nv * 3), &cpu)?)?),
                Some(to(Tensor::from_vec(jsd, (k, NUM_JOINTS * 3), &cpu)?)?),
            )
        } else {
            (None, None)
        };
        Ok(Self {
            config,
            device: device.clone(),
            dtype,
            n_vertices: nv,
            faces: asset.faces.clone(),
            parents: asset.parents,
            landmarks: asset.landmarks.clone(),
            v_template: to(Tensor::from_vec(asset.v_template.clone(), (nv, 3), &cpu)?)?,
            shapedirs,
            posedirs: to(Tensor::from_vec(pd, (POSE_BASIS, nv * 3), &cpu)?)?,
            j_template: to(Tensor::from_vec(jt, (NUM_JOINTS, 3), &cpu)?)?,
            j_shapedirs,
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
        Ok(dims[0])
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

    pub fn forward(&self, p: &FlameParams) -> Result<FlameOutput> {
        let b = self.check("shape", &p.shape, self.config.n_shape, None)?;
        self.check("expression", &p.expression, self.config.n_exp, Some(b))?;
        self.check("pose", &p.pose, 6, Some(b))?;
        self.check("eye", &p.eye, 6, Some(b))?;
        let nv = self.n_vertices;

        // Blendshapes and joints.
        let (v_shaped, joints) = match (&self.shapedirs, &self.j_shapedirs) {
            (Some(sd), Some(jsd)) => {
                let betas = Tensor::cat(&[&p.shape, &p.expression], 1)?;
                let v = betas
                    .matmul(sd)?
                    .reshape((b, nv, 3))?
                    .broadcast_add(&self.v_template)?;
                let j = betas
                    .matmul(jsd)?
                    .reshape((b, NUM_JOINTS, 3))?
                    .broadcast_add(&self.j_template)?;
                (v, j)
            }
            _ => (
                self.v_template.unsqueeze(0)?.repeat((b, 1, 1))?,
                self.j_template.unsqueeze(0)?.repeat((b, 1, 1))?,
            ),
        };

        // Rotations and pose correctives.
        let full_pose = self.full_pose(&p.pose, &p.eye)?;
        let rot =
            rodrigues(&full_pose.reshape((b * NUM_JOINTS, 3))?)?.reshape((b, NUM_JOINTS, 3, 3))?;
        let ident = Tensor::eye(3, self.dtype, &self.device)?;
        let pose_feature = rot
            .narrow(1, 1, NUM_JOINTS - 1)?
            .broadcast_sub(&ident)?
            .reshape((b, POSE_BASIS))?;
        let v_posed = (v_shaped + pose_feature.matmul(&self.posedirs)?.reshape((b, nv, 3))?)?;

        // Kinematic chain: world rotation/translation of each joint, then the skinning transform
        // A_i = [R_i | t_i - R_i J_i] that moves rest-pose points attached to joint i.
        let mut world_r: Vec<Tensor> = Vec::with_capacity(NUM_JOINTS);
        let mut world_t: Vec<Tensor> = Vec::with_capacity(NUM_JOINTS);
        let mut rot_t: Vec<Tensor> = Vec::with_capacity(NUM_JOINTS);
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
            trans.push((&t_w - r_w.matmul(&j_i)?)?.squeeze(2)?); // [B, 3]
            rot_t.push(r_w.t()?);
            world_r.push(r_w);
            world_t.push(t_w);
        }
        // Skinning, sum_j w_vj (R_j v + t_j), arranged as three large matmuls and one
        // leading-dim broadcast (candle's fast paths) rather than per-vertex 3x4 transforms:
        // rotate every vertex by every joint ([B, V, 3] x [B, 3, 15]), weight, sum the joint
        // blocks with a constant [15, 3] matrix, then add the blended translations.
        let rot_all = Tensor::cat(&rot_t, 2)?; // [B, 3, 15]
        let per_joint = v_posed.matmul(&rot_all)?.broadcast_mul(&self.weights15)?; // [B, V, 15]
        let rotated = per_joint
            .reshape((b * nv, NUM_JOINTS * 3))?
            .matmul(&self.block_sum)?;
        let t_blend = self.weights.broadcast_matmul(&Tensor::stack(&trans, 1)?)?; // [B, V, 3]
        let verts = (rotated.reshape((b, nv, 3))? + t_blend)?;

        let posed_joints = Tensor::stack(&world_t, 1)?.squeeze(3)?;
        let s = self.config.scale;
        Ok(FlameOutput {
            vertices: verts.affine(s, 0.0)?,
            joints: posed_joints.affine(s, 0.0)?,
            rotations: rot,
        })
    }
}
