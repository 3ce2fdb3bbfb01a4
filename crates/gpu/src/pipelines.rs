//! Compiled compute pipelines and their cache; the device owns the cache, the kernels fill it.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// How a kernel sees one binding (bindings are numbered in order, all in group 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Bind {
    Uniform,
    Read,
    ReadWrite,
}

/// A compute pipeline and its bind-group layout.
#[derive(Debug)]
pub struct Kernel {
    pub name: String,
    pub pipeline: wgpu::ComputePipeline,
    pub layout: wgpu::BindGroupLayout,
    pub(crate) binds: Vec<Bind>,
}

/// Pipelines by (name, constants), so layers of the same shape share one compilation.
#[derive(Debug, Default)]
pub struct KernelCache {
    pub(crate) map: Mutex<HashMap<String, Arc<Kernel>>>,
}
