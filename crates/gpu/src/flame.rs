//! FLAME per frame on the GPU (spec section 9): codes -> blendshape coefficients and joint
//! transforms (one small kernel), then blendshapes and skinning per vertex. The identity's
//! shaped template and rest joints are computed once on the CPU (`FlameModel::identity`) and
//! uploaded with the bases.

use std::sync::Arc;

use candle_core::Tensor;
use gagavatar_flame::{FlameIdentity, FlameModel};

use crate::device::Gpu;
use crate::error::{input_err, GpuError, Result};
use crate::kernel::{groups, Bind, Grid, Kernel, Params, Step};

const JOINTS: &str = include_str!("shaders/flame_joints.wgsl");
const VERTICES: &str = include_str!("shaders/flame_vertices.wgsl");

/// Joints of FLAME (global, neck, jaw, two eyes).
const NUM_JOINTS: usize = 5;
/// Pose-corrective coefficients: (R - I) of joints 1..4.
const POSE_BASIS: usize = 36;

/// One frame's codes, padded to the model's component counts.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameCodes {
    /// `[n_exp]`
    pub expression: Vec<f32>,
    /// Global rotation, then jaw (axis-angle).
    pub pose: [f32; 6],
    /// The two eye joints (axis-angle).
    pub eye: [f32; 6],
}

/// FLAME bound to one identity, on the GPU.
pub struct GpuFlame {
    pub n_vertices: usize,
    pub n_exp: usize,
    codes: wgpu::Buffer,
    /// `[V, 3]` f32 scaled vertices, written by [`GpuFlame::steps`].
    pub vertices: wgpu::Buffer,
    steps: Vec<Step>,
}

fn host(t: &Tensor, what: &str) -> Result<Vec<f32>> {
    crate::kernel::tensor_f32(t).map_err(|e| GpuError::Weights(format!("FLAME {what}: {e}")))
}

fn kernels(gpu: &Gpu) -> Result<(Arc<Kernel>, Arc<Kernel>)> {
    let kj = gpu.kernel(
        "flame_joints",
        JOINTS,
        &[],
        &[
            Bind::Uniform,
            Bind::Read,
            Bind::Read,
            Bind::Read,
            Bind::ReadWrite,
            Bind::ReadWrite,
        ],
    )?;
    let kv = gpu.kernel(
        "flame_vertices",
        VERTICES,
        &[],
        &[
            Bind::Uniform,
            Bind::Read,
            Bind::Read,
            Bind::Read,
            Bind::Read,
            Bind::Read,
            Bind::ReadWrite,
        ],
    )?;
    Ok((kj, kv))
}

impl GpuFlame {
    /// Uploads the model's bases and one identity (batch 1).
    pub fn new(gpu: &Gpu, model: &FlameModel, identity: &FlameIdentity) -> Result<Self> {
        if identity.batch() != 1 {
            return Err(input_err(
                "FLAME identity",
                format!("the GPU path drives one identity, got {}", identity.batch()),
            ));
        }
        let nv = model.n_vertices;
        let ne = model.config.n_exp;
        let v_shaped = host(identity.v_shaped(), "identity template")?;
        let j_rest = host(identity.joints(), "identity joints")?;
        let dirs = host(model.exp_pose_dirs(), "blendshapes")?;
        let j_exp = match model.j_exp_dirs() {
            Some(t) => host(t, "joint blendshapes")?,
            None => Vec::new(),
        };
        let weights = host(model.skinning_weights(), "skinning weights")?;
        if v_shaped.len() != 3 * nv
            || j_rest.len() != 3 * NUM_JOINTS
            || dirs.len() != (ne + POSE_BASIS) * 3 * nv
            || j_exp.len() != ne * 3 * NUM_JOINTS
            || weights.len() != NUM_JOINTS * nv
        {
            return Err(GpuError::Weights(
                "FLAME model arrays do not have the sizes of its configuration".into(),
            ));
        }
        let parents = model.parents;
        if parents[1..].iter().enumerate().any(|(i, &p)| p > i) {
            return Err(GpuError::Weights(format!(
                "FLAME kinematic tree {parents:?}: each parent must come before its child"
            )));
        }
        let (kj, kv) = kernels(gpu)?;
        let codes = gpu.buffer("flame codes", 4 * (ne + 12) as u64);
        let coeffs = gpu.buffer("flame coefficients", 4 * (ne + POSE_BASIS) as u64);
        let transforms = gpu.buffer("flame transforms", 4 * 12 * NUM_JOINTS as u64);
        let vertices = gpu.buffer("flame vertices", 4 * 3 * nv as u64);
        let j_rest = gpu.buffer_with("flame rest joints", &j_rest);
        let j_exp = gpu.buffer_with("flame joint blendshapes", &j_exp);
        let v_shaped = gpu.buffer_with("flame shaped template", &v_shaped);
        let dirs = gpu.buffer_with("flame blendshapes", &dirs);
        let weights = gpu.buffer_with("flame weights", &weights);
        let pj = gpu.uniform(
            "flame joints",
            &Params::new()
                .u(ne as u32)
                .u(parents[1] as u32)
                .u(parents[2] as u32)
                .u(parents[3] as u32)
                .u(parents[4] as u32),
        );
        let pv = gpu.uniform(
            "flame vertices",
            &Params::new()
                .u(nv as u32)
                .u((ne + POSE_BASIS) as u32)
                .f(model.config.scale as f32),
        );
        let steps = vec![
            Step::new(
                kj.clone(),
                gpu.bind(&kj, &[&pj, &codes, &j_rest, &j_exp, &coeffs, &transforms])?,
                Grid::Fixed([1, 1, 1]),
            ),
            Step::new(
                kv.clone(),
                gpu.bind(
                    &kv,
                    &[
                        &pv,
                        &v_shaped,
                        &dirs,
                        &coeffs,
                        &weights,
                        &transforms,
                        &vertices,
                    ],
                )?,
                Grid::Fixed([groups(nv, 64), 1, 1]),
            ),
        ];
        Ok(Self {
            n_vertices: nv,
            n_exp: ne,
            codes,
            vertices,
            steps,
        })
    }

    /// Sets the codes of the next frame.
    pub fn set_codes(&self, gpu: &Gpu, codes: &FrameCodes) -> Result<()> {
        if codes.expression.len() != self.n_exp {
            return Err(input_err(
                "expression",
                format!(
                    "{} values, the model takes {}",
                    codes.expression.len(),
                    self.n_exp
                ),
            ));
        }
        let mut v = codes.expression.clone();
        v.extend(codes.pose);
        v.extend(codes.eye);
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(input_err(
                "FLAME codes",
                format!("value {i} is not finite ({})", v[i]),
            ));
        }
        gpu.queue
            .write_buffer(&self.codes, 0, bytemuck::cast_slice(&v));
        Ok(())
    }

    pub fn steps(&self) -> &[Step] {
        &self.steps
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernel::record_all;
    use crate::testutil::{assert_close, gpu};
    use candle_core::{DType, Device};
    use gagavatar_flame::{synthesize, FlameConfig};
    use gagavatar_splat::testscene::Rng;

    /// FLAME vertices reach ~1.5 after the x5 scale; the GPU sums the 136 blendshape terms and
    /// blends the joint transforms in other orders (and may fuse multiply-adds), a few f32
    /// ulps of those magnitudes.
    const VERTEX_TOL: f64 = 1e-5;

    #[test]
    fn vertices_match_the_cpu_forward() {
        let Some(g) = gpu() else { return };
        let asset = synthesize(3);
        let model =
            FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F32).unwrap();
        let mut rng = Rng::new(11);
        let mut randn =
            |n: usize, s: f64| -> Vec<f32> { (0..n).map(|_| (rng.normal() * s) as f32).collect() };
        let shape = Tensor::from_vec(randn(300, 1.0), (1, 300), &Device::Cpu).unwrap();
        let identity = model.identity(&shape).unwrap();
        let gf = GpuFlame::new(g, &model, &identity).unwrap();
        // Zero pose, ordinary poses, and large rotations (angles past pi).
        for (k, pose_scale) in [0.0, 0.2, 2.5].into_iter().enumerate() {
            let codes = FrameCodes {
                expression: randn(100, 1.0),
                pose: randn(6, pose_scale).try_into().unwrap(),
                eye: randn(6, pose_scale).try_into().unwrap(),
            };
            let t = |v: &[f32]| Tensor::from_slice(v, (1, v.len()), &Device::Cpu).unwrap();
            let want: Vec<f32> = model
                .forward_with_identity(
                    &identity,
                    &t(&codes.expression),
                    &t(&codes.pose),
                    &t(&codes.eye),
                )
                .unwrap()
                .vertices
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            gf.set_codes(g, &codes).unwrap();
            let mut enc = g
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
                record_all(&mut pass, gf.steps());
            }
            g.queue.submit([enc.finish()]);
            let got = g.read_f32(&gf.vertices, 3 * model.n_vertices).unwrap();
            assert_close(&format!("FLAME case {k}"), &want, &got, VERTEX_TOL);
        }
        // Wrong sizes and non-finite codes are errors.
        let bad = FrameCodes {
            expression: vec![0.0; 99],
            pose: [0.0; 6],
            eye: [0.0; 6],
        };
        assert!(gf.set_codes(g, &bad).is_err());
        let nan = FrameCodes {
            expression: vec![f32::NAN; 100],
            ..bad
        };
        assert!(gf.set_codes(g, &nan).is_err());
    }
}
