//! Where a trained module keeps its parameters and their gradients on the GPU.

use crate::device::Gpu;
use crate::error::{GpuError, Result};

/// A parameter's new values by key (`None`: the caller has no such parameter).
pub type ParamSource<'a> = dyn Fn(&str) -> Option<&'a [f32]> + 'a;

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

/// Several parameters' values packed into one buffer (a vector buffer of biases, a stacked
/// layer), with untrained values allowed between them; [`Store::packed`] uploads it.
#[derive(Default)]
pub(crate) struct Packed {
    pub host: Vec<f32>,
    keys: Vec<(String, usize, usize)>,
}

impl Packed {
    /// Appends the values of the parameter `key`; returns their offset.
    pub fn push(&mut self, key: String, v: &[f32]) -> usize {
        let at = self.host.len();
        self.host.extend_from_slice(v);
        self.keys.push((key, at, v.len()));
        at
    }

    /// Appends `n` zeros that no parameter owns (values kernels write); returns their offset.
    pub fn reserve(&mut self, n: usize) -> usize {
        let at = self.host.len();
        self.host.resize(at + n, 0.0);
        at
    }
}

impl<'g> Store<'g> {
    pub fn new(gpu: &'g Gpu) -> Self {
        Self {
            gpu,
            buffers: Vec::new(),
            params: Vec::new(),
        }
    }

    /// Uploads `p` and a zeroed gradient buffer of its size; its parameters point into both at
    /// the same offsets. Returns the two buffers' indices.
    pub fn packed(&mut self, label: &str, p: Packed) -> (usize, usize) {
        let value = self.add(label, &p.host);
        let grad = self.zeros(label, p.host.len());
        for (key, offset, len) in p.keys {
            self.params.push(Param {
                key,
                value,
                grad,
                offset,
                len,
            });
        }
        (value, grad)
    }

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

/// A copy of the `len` values of `key` in `weights` (a module's weights by checkpoint key).
pub(crate) fn host_weight(
    weights: &std::collections::HashMap<String, Vec<f32>>,
    key: &str,
    len: usize,
) -> Result<Vec<f32>> {
    let v = weights
        .get(key)
        .ok_or_else(|| GpuError::Weights(format!("no {key}")))?;
    if v.len() != len {
        return Err(GpuError::Weights(format!(
            "{key} has {} values, expected {len}",
            v.len()
        )));
    }
    Ok(v.clone())
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

/// Writes every parameter's values from `value` into its buffer, at its offset; a key
/// `value` lacks or of another length is an error (nothing keeps a stale value silently).
pub(crate) fn write_params(
    gpu: &Gpu,
    buffers: &[wgpu::Buffer],
    params: &[Param],
    value: &ParamSource,
) -> Result<()> {
    for p in params {
        let v = value(&p.key).ok_or_else(|| GpuError::Weights(format!("no {}", p.key)))?;
        if v.len() != p.len {
            return Err(GpuError::Weights(format!(
                "{}: {} values, expected {}",
                p.key,
                v.len(),
                p.len
            )));
        }
        gpu.queue.write_buffer(
            &buffers[p.value],
            4 * p.offset as u64,
            bytemuck::cast_slice(v),
        );
    }
    Ok(())
}
