//! What the reconstruct stages share: the avatar's buffers, a layer's uploaded weight, the
//! weight loader, the recording context and the plain convolution.

use std::cell::Cell;
use std::collections::HashMap;

use candle_core::Tensor;
use gagavatar_net::model::Avatar;
use gagavatar_net::ModelConfig;

pub use crate::conv::At;
use crate::conv::{Conv, ConvWeights, Ops};
use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::Step;
use crate::tuning::Tuning;

/// The avatar's Gaussians on the GPU, in the splatting's layouts (Gaussian-major, activated):
/// `n` Gaussians, the first `n_vertices` of them the expression ones (their positions come from
/// FLAME each frame), then the lifted ones, whose positions `means` holds.
pub struct GpuAvatar {
    pub n: usize,
    pub n_vertices: usize,
    pub channels: usize,
    /// `[n - n_vertices, 3]`
    pub means: wgpu::Buffer,
    /// `[n, channels]`
    pub features: wgpu::Buffer,
    /// `[n]`
    pub opacities: wgpu::Buffer,
    /// `[n, 3]`
    pub scales: wgpu::Buffer,
    /// `[n, 4]`, unit length
    pub rotations: wgpu::Buffer,
}

impl GpuAvatar {
    pub(crate) fn new(gpu: &Gpu, cfg: &ModelConfig) -> Self {
        let lifted = cfg.n_gaussians() - cfg.n_vertices;
        let n = cfg.n_gaussians();
        let f = |label: &str, len: usize| gpu.buffer(label, 4 * len as u64);
        Self {
            n,
            n_vertices: cfg.n_vertices,
            channels: cfg.color_dim,
            means: f("avatar means", 3 * lifted),
            features: f("avatar features", n * cfg.color_dim),
            opacities: f("avatar opacities", n),
            scales: f("avatar scales", 3 * n),
            rotations: f("avatar rotations", 4 * n),
        }
    }

    /// A copy on the same device (the reconstruct pass overwrites its own avatar each run;
    /// a copy belongs to one source photo).
    pub fn duplicate(&self, gpu: &Gpu) -> Self {
        let copy = |src: &wgpu::Buffer, label: &str| {
            let dst = gpu.buffer(label, src.size());
            (src.clone(), dst)
        };
        let pairs = [
            copy(&self.means, "avatar means"),
            copy(&self.features, "avatar features"),
            copy(&self.opacities, "avatar opacities"),
            copy(&self.scales, "avatar scales"),
            copy(&self.rotations, "avatar rotations"),
        ];
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("avatar copy"),
            });
        for (src, dst) in &pairs {
            enc.copy_buffer_to_buffer(src, 0, dst, 0, src.size());
        }
        gpu.queue.submit([enc.finish()]);
        let [means, features, opacities, scales, rotations] = pairs.map(|(_, d)| d);
        Self {
            n: self.n,
            n_vertices: self.n_vertices,
            channels: self.channels,
            means,
            features,
            opacities,
            scales,
            rotations,
        }
    }

    /// The buffers as the splatting takes them (shared, not copied).
    pub fn splat_buffers(&self) -> crate::splat::SplatBuffers {
        crate::splat::SplatBuffers {
            n: self.n,
            channels: self.channels,
            means: self.means.clone(),
            features: self.features.clone(),
            opacities: self.opacities.clone(),
            scales: self.scales.clone(),
            rotations: self.rotations.clone(),
        }
    }

    /// Reads the Gaussians back as the CPU path's [`Avatar`] (batch 1).
    pub fn download(&self, gpu: &Gpu) -> Result<Avatar> {
        let lifted = self.n - self.n_vertices;
        let dev = candle_core::Device::Cpu;
        let t = |buf: &wgpu::Buffer, k: usize, rows: usize| -> Result<Tensor> {
            let v = gpu.read_f32(buf, rows * k)?;
            Tensor::from_vec(v, (1, rows, k), &dev)
                .map_err(|e| GpuError::Device(format!("avatar read-back: {e}")))
        };
        Ok(Avatar {
            lifted_xyz: t(&self.means, 3, lifted)?,
            colors: t(&self.features, self.channels, self.n)?,
            opacities: t(&self.opacities, 1, self.n)?,
            scales: t(&self.scales, 3, self.n)?,
            rotations: t(&self.rotations, 4, self.n)?,
        })
    }
}

/// Uploads the weights (by checkpoint key) and builds the shared vector buffer's contents.
pub(crate) struct Loader<'a> {
    pub gpu: &'a Gpu,
    pub weights: &'a HashMap<String, Tensor>,
    pub vecs: Vec<f32>,
}

impl Loader<'_> {
    pub fn tensor(&self, key: &str) -> Result<&Tensor> {
        self.weights
            .get(key)
            .ok_or_else(|| GpuError::Weights(format!("{key} is missing")))
    }

    /// The values of `key`, which must hold `len` of them.
    pub fn get(&self, key: &str, len: usize) -> Result<Vec<f32>> {
        let v = crate::kernel::tensor_f32(self.tensor(key)?)
            .map_err(|e| GpuError::Weights(format!("{key}: {e}")))?;
        if v.len() != len {
            return Err(GpuError::Weights(format!(
                "{key} has {} values, expected {len}",
                v.len()
            )));
        }
        Ok(v)
    }

    pub fn push(&mut self, v: &[f32]) -> u32 {
        let at = self.vecs.len();
        self.vecs.extend_from_slice(v);
        at as u32
    }

    /// A convolution (or linear layer: `k` = 1) stored `[cout, cin k k]`, with its bias
    /// (`key.bias`) in the vector buffer when `bias`.
    pub fn conv(
        &mut self,
        key: &str,
        cin: usize,
        cout: usize,
        k: usize,
        bias: bool,
    ) -> Result<ConvWeights> {
        let w = self.get(&format!("{key}.weight"), cout * cin * k * k)?;
        let bias = if bias {
            let b = self.get(&format!("{key}.bias"), cout)?;
            Some(self.push(&b))
        } else {
            None
        };
        Ok(ConvWeights {
            weight: self.gpu.buffer_with(key, &w),
            bias,
            cin,
            cout,
            k,
        })
    }
}

/// What every stage's recording shares. In the measuring pass (`measure` set) convolutions
/// only report the split-K scratch they need.
pub(crate) struct Ctx<'a> {
    pub gpu: &'a Gpu,
    pub tuning: &'a Tuning,
    pub vecs: &'a wgpu::Buffer,
    pub dummy: &'a wgpu::Buffer,
    pub spare: &'a wgpu::Buffer,
    pub scratch: &'a wgpu::Buffer,
    pub measure: Option<&'a Cell<usize>>,
}

impl<'a> Ctx<'a> {
    pub fn ops(&self) -> Ops<'a> {
        Ops {
            gpu: self.gpu,
            tuning: self.tuning,
            vecs: self.vecs,
            dummy: self.dummy,
            split_scratch: self.scratch,
        }
    }

    /// [`Ops::conv`] (or, measuring, only the split-K scratch sized).
    pub fn conv(&self, c: &Conv) -> Result<Vec<Step>> {
        self.conv_with(c, self.vecs)
    }

    /// [`Ctx::conv`] reading biases and scales from `vecs` instead of the shared buffer.
    pub fn conv_with(&self, c: &Conv, vecs: &wgpu::Buffer) -> Result<Vec<Step>> {
        let need = Ops::split_need(self.tuning, c.cin, c.cout, c.h, c.w, c.k);
        if let Some(m) = self.measure {
            m.set(m.get().max(need));
            return Ok(Vec::new());
        }
        // `Ops::conv` checks the scratch's size.
        Ops { vecs, ..self.ops() }.conv(c)
    }
}
