//! What every stage builds on: buffers, compute pipelines compiled from the WGSL files with
//! their tuning constants substituted (and cached), and recorded dispatches.
//!
//! A stage is built once (pipelines, buffers, bind groups) and then only recorded, frame after
//! frame, into one command buffer: nothing is allocated per frame.

use std::sync::Arc;

use wgpu::util::DeviceExt;

use crate::device::Gpu;
use crate::error::{GpuError, Result};
pub use crate::pipelines::{Bind, Kernel, KernelCache};

/// WGSL helpers shared by the kernels (prepended to every source).
const COMMON: &str = include_str!("shaders/common.wgsl");

/// Replaces each `{{KEY}}` of `source` by its value; errors on a placeholder left over.
pub fn substitute(name: &str, source: &str, consts: &[(&str, String)]) -> Result<String> {
    let mut s = source.to_string();
    for (k, v) in consts {
        s = s.replace(&format!("{{{{{k}}}}}"), v);
    }
    if let Some(at) = s.find("{{") {
        let end = s[at..].find("}}").map_or(s.len(), |e| at + e + 2);
        return Err(GpuError::Device(format!(
            "kernel {name}: placeholder {} has no value",
            &s[at..end]
        )));
    }
    Ok(s)
}

/// A kernel's whole WGSL module: its `enable` directives first (WGSL wants them before any
/// declaration), then common.wgsl, then the rest of its body.
pub fn module_source(body: &str) -> String {
    let (enables, rest): (Vec<&str>, Vec<&str>) = body
        .lines()
        .partition(|l| l.trim_start().starts_with("enable "));
    format!("{}\n{COMMON}\n{}", enables.join("\n"), rest.join("\n"))
}

impl Gpu {
    /// The kernel `name` from WGSL `source` (entry point `main`) with `consts` substituted;
    /// compiled once per distinct source. Compilation errors become [`GpuError::Device`].
    pub fn kernel(
        &self,
        name: &str,
        source: &str,
        consts: &[(&str, String)],
        binds: &[Bind],
    ) -> Result<Arc<Kernel>> {
        let body = substitute(name, source, consts)?;
        let key = format!("{name}\u{0}{body}");
        let cache = &self.kernels;
        if let Some(k) = cache.map.lock().map_err(poisoned)?.get(&key) {
            if k.binds != binds {
                return Err(GpuError::Device(format!(
                    "kernel {name} requested with two binding lists"
                )));
            }
            return Ok(k.clone());
        }
        let code = module_source(&body);
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(code.into()),
            });
        let entries: Vec<wgpu::BindGroupLayoutEntry> = binds
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupLayoutEntry {
                binding: i as u32,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: match b {
                        Bind::Uniform => wgpu::BufferBindingType::Uniform,
                        Bind::Read => wgpu::BufferBindingType::Storage { read_only: true },
                        Bind::ReadWrite => wgpu::BufferBindingType::Storage { read_only: false },
                    },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            })
            .collect();
        let layout = self
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(name),
                entries: &entries,
            });
        let pl = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(name),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(name),
                layout: Some(&pl),
                module: &module,
                entry_point: Some("main"),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &[],
                    // Every kernel writes its workgroup memory before reading it.
                    zero_initialize_workgroup_memory: false,
                },
                cache: None,
            });
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(format!("compiling kernel {name}: {err}")));
        }
        let k = Arc::new(Kernel {
            name: name.to_string(),
            pipeline,
            layout,
            binds: binds.to_vec(),
        });
        cache.map.lock().map_err(poisoned)?.insert(key, k.clone());
        Ok(k)
    }

    /// A storage buffer of `bytes` bytes (at least 4), zeroed.
    pub fn buffer(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        let size = bytes.max(4).next_multiple_of(4);
        self.count(size);
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_DST
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::INDIRECT,
            mapped_at_creation: false,
        })
    }

    /// A storage buffer holding `data`.
    pub fn buffer_with<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> wgpu::Buffer {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        if bytes.is_empty() {
            return self.buffer(label, 4);
        }
        self.count(bytes.len() as u64);
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_DST
                    | wgpu::BufferUsages::COPY_SRC,
            })
    }

    /// A uniform buffer of parameters (see [`Params`]).
    pub fn uniform(&self, label: &str, p: &Params) -> wgpu::Buffer {
        self.count(4 * p.words().len() as u64);
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(&p.words()),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            })
    }

    fn count(&self, bytes: u64) {
        self.allocated
            .fetch_add(bytes, std::sync::atomic::Ordering::Relaxed);
    }

    /// Binds whole buffers, in order, to a kernel.
    pub fn bind(&self, k: &Kernel, buffers: &[&wgpu::Buffer]) -> Result<wgpu::BindGroup> {
        let views: Vec<wgpu::BufferBinding> = buffers
            .iter()
            .map(|b| b.as_entire_buffer_binding())
            .collect();
        self.bind_ranges(k, &views)
    }

    /// Binds buffer ranges, in order, to a kernel.
    pub fn bind_ranges(
        &self,
        k: &Kernel,
        views: &[wgpu::BufferBinding],
    ) -> Result<wgpu::BindGroup> {
        if views.len() != k.binds.len() {
            return Err(GpuError::Device(format!(
                "kernel {} takes {} bindings, got {}",
                k.name,
                k.binds.len(),
                views.len()
            )));
        }
        let max = self.limits.max_storage_buffer_binding_size;
        for v in views {
            let size = v.size.map_or(v.buffer.size() - v.offset, |s| s.get());
            if size > max {
                return Err(GpuError::Unsupported(format!(
                    "kernel {}: a {size}-byte buffer is over the device's binding limit of {max} \
                     bytes",
                    k.name
                )));
            }
        }
        let entries: Vec<wgpu::BindGroupEntry> = views
            .iter()
            .enumerate()
            .map(|(i, v)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: wgpu::BindingResource::Buffer(v.clone()),
            })
            .collect();
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&k.name),
            layout: &k.layout,
            entries: &entries,
        });
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(format!(
                "binding kernel {}: {err}",
                k.name
            )));
        }
        Ok(group)
    }

    /// Records `steps` in order into one compute pass and submits it (without waiting).
    pub fn submit(&self, steps: &[Step]) {
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            record_all(&mut pass, steps);
        }
        self.queue.submit([enc.finish()]);
    }

    /// Copies a buffer's first `bytes` bytes back to the host (waits for the GPU).
    pub fn read_back(&self, src: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>> {
        let size = bytes.next_multiple_of(4).max(4);
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read back"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, size);
        self.queue.submit([enc.finish()]);
        let out = map_read(self, &staging, size)?;
        Ok(out[..bytes as usize].to_vec())
    }

    /// [`Gpu::read_back`] as `f32` values.
    pub fn read_f32(&self, src: &wgpu::Buffer, n: usize) -> Result<Vec<f32>> {
        let bytes = self.read_back(src, 4 * n as u64)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }

    /// The first `n` floats of each buffer, copied into one staging buffer and mapped once
    /// (one wait for the device instead of one per buffer).
    pub fn read_f32_many(&self, srcs: &[(&wgpu::Buffer, usize)]) -> Result<Vec<Vec<f32>>> {
        let total: u64 = srcs.iter().map(|(_, n)| 4 * *n as u64).sum();
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read back"),
            size: total.max(4),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        let mut at = 0;
        for (src, n) in srcs {
            let bytes = 4 * *n as u64;
            if bytes > src.size() {
                return Err(GpuError::Device(format!(
                    "reading {bytes} bytes of a {}-byte buffer",
                    src.size()
                )));
            }
            if bytes > 0 {
                enc.copy_buffer_to_buffer(src, 0, &staging, at, bytes);
            }
            at += bytes;
        }
        self.queue.submit([enc.finish()]);
        let all: Vec<f32> = bytemuck::pod_collect_to_vec(&map_read(self, &staging, total.max(4))?);
        let mut out = Vec::with_capacity(srcs.len());
        let mut first = 0;
        for (_, n) in srcs {
            out.push(all[first..first + n].to_vec());
            first += n;
        }
        Ok(out)
    }

    /// [`Gpu::read_back`] as `u32` values.
    pub fn read_u32(&self, src: &wgpu::Buffer, n: usize) -> Result<Vec<u32>> {
        let bytes = self.read_back(src, 4 * n as u64)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }
}

/// Maps a MAP_READ buffer (after its copy was submitted) and returns its bytes.
pub fn map_read(gpu: &Gpu, staging: &wgpu::Buffer, size: u64) -> Result<Vec<u8>> {
    let slice = staging.slice(..size);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    gpu.wait()?;
    rx.recv()
        .map_err(|_| GpuError::Device("buffer mapping was dropped".into()))?
        .map_err(|e| GpuError::Device(format!("mapping a buffer: {e}")))?;
    let data = slice
        .get_mapped_range()
        .map_err(|e| GpuError::Device(format!("reading a mapped buffer: {e}")))?
        .to_vec();
    staging.unmap();
    Ok(data)
}

fn poisoned<T>(_: T) -> GpuError {
    GpuError::Device("kernel cache lock poisoned".into())
}

/// A tensor's values as f32, row-major (what every upload of weights or inputs starts from).
pub fn tensor_f32(t: &candle_core::Tensor) -> candle_core::Result<Vec<f32>> {
    t.to_dtype(candle_core::DType::F32)?
        .flatten_all()?
        .to_vec1::<f32>()
}

/// Uniform parameters as 32-bit words, padded to whole 16-byte rows (WGSL's uniform layout
/// for a struct of scalars: declare the fields in the same order, all `u32`/`i32`/`f32`).
#[derive(Debug, Clone, Default)]
pub struct Params(Vec<u32>);

impl Params {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn u(mut self, v: u32) -> Self {
        self.0.push(v);
        self
    }
    pub fn f(mut self, v: f32) -> Self {
        self.0.push(v.to_bits());
        self
    }
    pub fn words(&self) -> Vec<u32> {
        let mut w = self.0.clone();
        w.resize(w.len().next_multiple_of(4).max(4), 0);
        w
    }
}

/// How many workgroups a dispatch launches: a fixed grid, or one read from a buffer (three
/// `u32` at `offset`) that an earlier kernel of the same frame wrote.
#[derive(Debug, Clone)]
pub enum Grid {
    Fixed([u32; 3]),
    Indirect(wgpu::Buffer, u64),
}

/// One recorded dispatch.
#[derive(Debug, Clone)]
pub struct Step {
    pub kernel: Arc<Kernel>,
    pub group: wgpu::BindGroup,
    pub grid: Grid,
    /// What the dispatch computes, for profiles (e.g. a convolution's shape).
    pub note: Option<String>,
}

impl Step {
    pub fn new(kernel: Arc<Kernel>, group: wgpu::BindGroup, grid: Grid) -> Self {
        Self {
            kernel,
            group,
            grid,
            note: None,
        }
    }

    pub fn with_note(mut self, note: String) -> Self {
        self.note = Some(note);
        self
    }

    /// The kernel's name and its grid, e.g. `conv_mma 64x8x1` (for per-dispatch profiles).
    pub fn label(&self) -> String {
        let grid = match &self.grid {
            Grid::Fixed([x, y, z]) => format!("{x}x{y}x{z}"),
            Grid::Indirect(..) => "(indirect)".into(),
        };
        match &self.note {
            Some(n) => format!("{} {n} [{grid}]", self.kernel.name),
            None => format!("{} [{grid}]", self.kernel.name),
        }
    }

    pub fn record(&self, pass: &mut wgpu::ComputePass) {
        pass.set_pipeline(&self.kernel.pipeline);
        pass.set_bind_group(0, &self.group, &[]);
        match &self.grid {
            Grid::Fixed([x, y, z]) => {
                if *x > 0 && *y > 0 && *z > 0 {
                    pass.dispatch_workgroups(*x, *y, *z)
                }
            }
            Grid::Indirect(b, off) => pass.dispatch_workgroups_indirect(b, *off),
        }
    }
}

/// Records steps in order into one compute pass.
pub fn record_all(pass: &mut wgpu::ComputePass, steps: &[Step]) {
    for s in steps {
        s.record(pass);
    }
}

/// A 1-D grid of `n` threads in workgroups of `wg` as (x, y) workgroups, so more than 65535
/// workgroups fit; kernels recover the index as `(id.y * 65535 * wg) + id.x`... see
/// `linear_index` in common.wgsl (the x extent is always `LINEAR_X` workgroups when y > 1).
pub fn linear_grid(n: usize, wg: u32) -> Grid {
    let groups = (n as u64).div_ceil(wg as u64).max(1);
    if groups <= LINEAR_X as u64 {
        Grid::Fixed([groups as u32, 1, 1])
    } else {
        Grid::Fixed([LINEAR_X, groups.div_ceil(LINEAR_X as u64) as u32, 1])
    }
}

/// Workgroups along x of a [`linear_grid`] that needs more than one row.
pub const LINEAR_X: u32 = 32768;

/// Ceiling division for grid sizes.
pub fn groups(n: usize, per: usize) -> u32 {
    n.div_ceil(per.max(1)) as u32
}

/// One dispatch's GPU time ([`time_dispatches`]).
#[derive(Debug, Clone)]
pub struct DispatchTime {
    /// The stage it belongs to.
    pub stage: &'static str,
    /// Kernel name and grid.
    pub label: String,
    pub ms: f64,
}

/// Runs `steps` once, each in a compute pass of its own between two device timestamps, and
/// returns each one's time (in order), or `None` where the adapter has no timestamp queries.
/// The buffers the steps use must hold the inputs of a real run.
pub fn time_dispatches(
    gpu: &Gpu,
    steps: &[(&'static str, &Step)],
) -> Result<Option<Vec<DispatchTime>>> {
    if !gpu.has_timestamps() || steps.is_empty() {
        return Ok(None);
    }
    let n = 2 * steps.len() as u32;
    let set = gpu.device.create_query_set(&wgpu::QuerySetDescriptor {
        label: Some("dispatch timestamps"),
        ty: wgpu::QueryType::Timestamp,
        count: n,
    });
    let bytes = 8 * n as u64;
    let resolve = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("dispatch timestamps"),
        size: bytes,
        usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let read = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("dispatch timestamps read-back"),
        size: bytes,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut enc = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
    for (i, (_, s)) in steps.iter().enumerate() {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: None,
            timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                query_set: &set,
                beginning_of_pass_write_index: Some(2 * i as u32),
                end_of_pass_write_index: Some(2 * i as u32 + 1),
            }),
        });
        s.record(&mut pass);
    }
    enc.resolve_query_set(&set, 0..n, &resolve, 0);
    enc.copy_buffer_to_buffer(&resolve, 0, &read, 0, bytes);
    gpu.queue.submit([enc.finish()]);
    let ticks: Vec<u64> = bytemuck::pod_collect_to_vec(&map_read(gpu, &read, bytes)?);
    let period = gpu.queue.get_timestamp_period() as f64;
    Ok(Some(
        steps
            .iter()
            .enumerate()
            .map(|(i, (stage, s))| DispatchTime {
                stage,
                label: s.label(),
                ms: ticks[2 * i + 1].saturating_sub(ticks[2 * i]) as f64 * period * 1e-6,
            })
            .collect(),
    ))
}
