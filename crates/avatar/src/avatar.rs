//! A reconstructed avatar: its Gaussians, the source identity's FLAME shape and the source
//! record, ready to be driven on the CPU or a GPU.

use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use gagavatar_flame::{FlameIdentity, FlameModel, TrackedFrame};
use gagavatar_gpu::flame::FrameCodes;
use gagavatar_gpu::reconstruct::GpuAvatar;
use gagavatar_gpu::Gpu;
use gagavatar_net::model::{Avatar as Gaussians, GagAvatar};
use gagavatar_net::style_unet::Noise;
use gagavatar_splat::GaussianScene;

use crate::drive::{CpuDrive, GpuDrive};
use crate::error::{input_err, Result};

/// An avatar made by [`crate::Engine::avatar`]. Cheap to keep: the model and FLAME are shared
/// with the engine, the Gaussians are tensors.
pub struct Avatar {
    pub(crate) model: Arc<GagAvatar>,
    pub(crate) flame: Arc<FlameModel>,
    pub(crate) gaussians: Gaussians,
    pub(crate) identity: FlameIdentity,
    pub(crate) source: TrackedFrame,
    pub(crate) noise: Noise,
    /// The Gaussians where [`crate::Engine::avatar_on_gpu`] made them, on that device.
    pub(crate) on_gpu: Option<(Arc<Gpu>, Arc<GpuAvatar>)>,
}

impl Avatar {
    pub(crate) fn new(
        model: Arc<GagAvatar>,
        flame: Arc<FlameModel>,
        gaussians: Gaussians,
        identity: FlameIdentity,
        source: TrackedFrame,
        noise: Noise,
    ) -> Self {
        Avatar {
            model,
            flame,
            gaussians,
            identity,
            source,
            noise,
            on_gpu: None,
        }
    }

    /// Whether the Gaussians were made on a GPU (and a GPU drive on that device reads them
    /// there).
    pub fn is_on_gpu(&self) -> bool {
        self.on_gpu.is_some()
    }

    /// The tracked record the avatar was made from (its identity and its camera).
    pub fn source(&self) -> &TrackedFrame {
        &self.source
    }

    /// The source camera: orbits and "same view" renders start from it.
    pub fn source_camera(&self) -> Result<[[f64; 4]; 3]> {
        self.source
            .transform_matrix
            .ok_or_else(|| input_err("the source record", "no transform_matrix"))
    }

    /// Every Gaussian attribute except the per-frame FLAME vertex positions (for `.ply` export).
    pub fn gaussians(&self) -> &Gaussians {
        &self.gaussians
    }

    pub fn model(&self) -> &GagAvatar {
        &self.model
    }

    pub fn flame(&self) -> &FlameModel {
        &self.flame
    }

    /// Bytes this avatar holds of its own (its Gaussians; the model and FLAME are the engine's),
    /// for a cache's memory budget.
    pub fn memory_bytes(&self) -> usize {
        let g = &self.gaussians;
        [
            &g.lifted_xyz,
            &g.colors,
            &g.opacities,
            &g.scales,
            &g.rotations,
        ]
        .iter()
        .map(|t| t.elem_count() * t.dtype().size_in_bytes())
        .sum()
    }

    /// The side of the square frames it renders.
    pub fn image_size(&self) -> usize {
        self.model.cfg.image_size
    }

    /// A driver record's codes (expression, jaw and global pose, eyes), checked against this
    /// FLAME's component counts; `what` names the record in errors.
    pub fn codes(&self, record: &TrackedFrame, what: &str) -> Result<FrameCodes> {
        FrameCodes::from_record(record, &self.flame).map_err(|e| input_err(what, e.to_string()))
    }

    /// The FLAME vertices `[1, V, 3]` of the source identity with `codes`' expression, jaw and
    /// eyes: the positions of the expression Gaussians for that frame.
    pub fn vertices(&self, codes: &FrameCodes) -> Result<Tensor> {
        let n_exp = self.flame.config.n_exp;
        if codes.expression.len() != n_exp {
            return Err(input_err(
                "codes",
                format!(
                    "{} expression values, this FLAME has {n_exp}",
                    codes.expression.len()
                ),
            ));
        }
        let dev = Device::Cpu;
        let t = |v: &[f32]| Tensor::from_slice(v, (1, v.len()), &dev);
        Ok(self
            .flame
            .forward_with_identity(
                &self.identity,
                &t(&codes.expression)?,
                &t(&codes.pose)?,
                &t(&codes.eye)?,
            )?
            .vertices)
    }

    /// Every Gaussian with the expression ones placed for `codes`, as a scene for `.ply` export
    /// (rotations as unit quaternions, so viewers that normalise them show the same shapes).
    pub fn scene(&self, codes: &FrameCodes) -> Result<GaussianScene> {
        let verts = self.vertices(codes)?;
        let g = &self.gaussians;
        let flat = |t: &Tensor| -> Result<Vec<f32>> {
            Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?)
        };
        let raw = GaussianScene {
            means: flat(&g.positions(&verts)?)?,
            features: flat(&g.colors)?,
            channels: g.colors.dim(2)?,
            opacities: flat(&g.opacities)?,
            scales: flat(&g.scales)?,
            rotations: flat(&g.rotations)?,
        };
        Ok(raw.with_unit_quaternions())
    }

    /// The avatar's drive on the CPU.
    pub fn cpu_drive(&self) -> CpuDrive {
        CpuDrive::from_parts(
            self.model.cfg.clone(),
            self.model.renderer.clone(),
            self.flame.clone(),
            self.gaussians.clone(),
            self.identity.clone(),
            self.noise,
        )
    }

    /// The avatar's drive on `gpu`: uploads FLAME and the renderer once, and the Gaussians
    /// unless they were made on this device.
    pub fn gpu_drive(&self, gpu: Arc<Gpu>, tuning: &gagavatar_gpu::Tuning) -> Result<GpuDrive> {
        if let Some((made_on, avatar)) = &self.on_gpu {
            if Arc::ptr_eq(made_on, &gpu) {
                return GpuDrive::from_gpu_avatar(
                    gpu,
                    tuning,
                    &self.model,
                    avatar,
                    &self.flame,
                    &self.identity,
                    self.noise,
                );
            }
        }
        GpuDrive::from_parts(
            gpu,
            tuning,
            &self.model,
            &self.gaussians,
            &self.flame,
            &self.identity,
            self.noise,
        )
    }
}
