//! Where a trained module keeps its parameters and their gradients on the GPU.

use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::renderer::WeightFn;

/// Where a parameter's values and gradient live: `len` floats at `offset` of buffer
/// `value` / `grad` (indices into the module's buffers).
#[derive(Debug, Clone)]
pub struct Param {
    /// The checkpoint key relative to `upsampler.`.
    pub key: String,
    pub value: usize,
    pub grad: usize,
    pub offset: usize,
    pub len: usize,
}

/// Buffers in creation order, so that [`Param`] can name them by index.
pub(crate) struct Store<'g> {
    pub gpu: &'g Gpu,
    pub buffers: Vec<wgpu::Buffer>,
    pub params: Vec<Param>,
}

impl Store<'_> {
    pub fn add(&mut self, label: &str, data: &[f32]) -> usize {
        self.buffers.push(self.gpu.buffer_with(label, data));
        self.buffers.len() - 1
    }
    pub fn zeros(&mut self, label: &str, n: usize) -> usize {
        self.buffers.push(self.gpu.buffer(label, 4 * n as u64));
        self.buffers.len() - 1
    }
    /// A parameter in its own buffer, with a gradient buffer beside it.
    pub fn param(&mut self, key: &str, data: Vec<f32>) -> (usize, usize) {
        let v = self.add(key, &data);
        let g = self.zeros(key, data.len());
        self.params.push(Param {
            key: key.to_string(),
            value: v,
            grad: g,
            offset: 0,
            len: data.len(),
        });
        (v, g)
    }
}

pub(crate) fn get(weights: &WeightFn, key: &str, len: usize) -> Result<Vec<f32>> {
    let v = weights(key)?;
    if v.len() != len {
        return Err(GpuError::Weights(format!(
            "upsampler.{key} has {} values, expected {len}",
            v.len()
        )));
    }
    Ok(v)
}

/// Every parameter's gradient, read back, by key.
pub(crate) fn read_grads(
    gpu: &Gpu,
    buffers: &[wgpu::Buffer],
    params: &[Param],
) -> Result<Vec<(String, Vec<f32>)>> {
    params
        .iter()
        .map(|p| {
            let all = gpu.read_f32(&buffers[p.grad], p.offset + p.len)?;
            Ok((p.key.clone(), all[p.offset..].to_vec()))
        })
        .collect()
}
