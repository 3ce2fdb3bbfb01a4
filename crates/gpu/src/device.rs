//! Adapter selection and the device every kernel runs on.
//!
//! wgpu sees Vulkan, Metal and D3D12 adapters. Real GPUs (discrete, integrated, virtual) are
//! preferred; CPU-emulated adapters (Mesa's lavapipe/llvmpipe, WARP) are slower than the CPU path
//! for this workload and are used only when the caller allows them (`--device gpu` said
//! explicitly, or the tests).

use std::fmt;

use crate::error::{GpuError, Result};
pub use crate::policy::AdapterPolicy;

/// Environment variable: a case-insensitive substring of the adapter name to use (when a
/// machine has several), e.g. `GAGAVATAR_GPU_ADAPTER=h200`.
pub const ADAPTER_ENV: &str = "GAGAVATAR_GPU_ADAPTER";

/// Environment variable: `0` keeps the device from enabling cooperative matrices (and so the
/// f16 tensor-core convolutions) even where the adapter has them.
pub const MMA_ENV: &str = "GAGAVATAR_GPU_MMA";

/// The device, its queue and what it supports.
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    /// Features enabled on the device (a subset of [`Gpu::adapter_features`]).
    pub features: wgpu::Features,
    /// Everything the adapter offers (reported by the bench, for the tuning notes).
    pub adapter_features: wgpu::Features,
    /// Cooperative-matrix (tensor core) shapes the adapter reports; empty when none.
    pub cooperative_matrices: Vec<wgpu::CooperativeMatrixProperties>,
    /// Whether the f16 tensor-core convolutions (`conv_mma.wgsl`) can run here: the adapter
    /// has 16x16x16 f16 x f16 -> f32 cooperative matrices, f16 in shaders and subgroups of
    /// exactly 32 lanes (the kernel maps one subgroup to each 32 invocations).
    pub mma_f16: bool,
    pub(crate) kernels: crate::pipelines::KernelCache,
    /// Bytes of the buffers created through [`Gpu::buffer`] and its siblings.
    pub(crate) allocated: std::sync::atomic::AtomicU64,
}

impl fmt::Debug for Gpu {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Gpu").field("info", &self.info).finish()
    }
}

/// Whether an adapter emulates a GPU on the CPU.
pub fn is_cpu_adapter(info: &wgpu::AdapterInfo) -> bool {
    info.device_type == wgpu::DeviceType::Cpu
}

fn rank(info: &wgpu::AdapterInfo) -> u8 {
    match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

/// A one-line description of an adapter.
pub fn describe(info: &wgpu::AdapterInfo) -> String {
    let driver = if info.driver.is_empty() {
        String::new()
    } else {
        format!(", driver {} {}", info.driver, info.driver_info)
    };
    format!(
        "{} ({:?}, {:?}{driver})",
        info.name, info.backend, info.device_type
    )
}

/// Mesa's Vulkan drivers try a Wayland connection while wgpu probes adapters, and libwayland
/// prints `error: XDG_RUNTIME_DIR is invalid or not set in the environment.` when the variable
/// is unset (a container, a cron job, CI): twice per probe, in runs that succeed. A private,
/// empty runtime folder (as a login session would provide) makes the attempt fail quietly.
/// Call it before any thread starts (it sets an environment variable): the CLI's `main` and
/// the Python module's import do.
pub fn quiet_probe_env() {
    if std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|v| !v.is_empty()) {
        return;
    }
    let dir = std::env::temp_dir().join(format!("gagavatar-runtime-{}", whoami_uid()));
    if std::fs::create_dir_all(&dir).is_err() {
        return;
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::{MetadataExt, PermissionsExt};
        let _ = std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o700));
        // Only a folder of ours that no one else can write (another user may have made one
        // of that name in a shared temp folder).
        match std::fs::symlink_metadata(&dir) {
            Ok(m) if m.is_dir() && m.uid() == whoami_uid() && m.mode() & 0o077 == 0 => {}
            _ => return,
        }
    }
    std::env::set_var("XDG_RUNTIME_DIR", dir);
}

/// The user's id on Unix (one runtime folder per user), 0 elsewhere.
fn whoami_uid() -> u32 {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let Ok(m) = std::fs::metadata("/proc/self") {
            return m.uid();
        }
    }
    0
}

fn instance() -> wgpu::Instance {
    // WGPU_BACKEND (e.g. `vulkan`) narrows the backends, as in every wgpu program.
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
    desc.backends &= wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
    wgpu::Instance::new(desc)
}

/// Every adapter wgpu can see (for messages and `bench`).
pub fn list_adapters() -> Vec<wgpu::AdapterInfo> {
    let inst = instance();
    pollster::block_on(inst.enumerate_adapters(wgpu::Backends::all()))
        .iter()
        .map(|a| a.get_info())
        .collect()
}

impl Gpu {
    /// Opens the best adapter the policy allows: discrete before integrated before virtual
    /// before CPU-emulated, Vulkan before the other backends on ties; [`ADAPTER_ENV`] narrows the
    /// choice by name.
    pub fn new(policy: AdapterPolicy) -> Result<Self> {
        Self::nth(policy, 0)
    }

    /// [`Gpu::new`]'s choice among several equal adapters: the `index`-th (modulo their
    /// number) of those that tie with the best, so that the ranks of a data-parallel job on a
    /// machine with eight GPUs take one each (`index` = the rank on its machine).
    pub fn nth(policy: AdapterPolicy, index: usize) -> Result<Self> {
        let inst = instance();
        let adapters = pollster::block_on(inst.enumerate_adapters(wgpu::Backends::all()));
        let seen: Vec<String> = adapters.iter().map(|a| describe(&a.get_info())).collect();
        let wanted = std::env::var(ADAPTER_ENV).ok().map(|s| s.to_lowercase());
        let mut candidates: Vec<wgpu::Adapter> = adapters
            .into_iter()
            .filter(|a| {
                let info = a.get_info();
                (policy == AdapterPolicy::AllowCpu || !is_cpu_adapter(&info))
                    && wanted
                        .as_ref()
                        .is_none_or(|w| info.name.to_lowercase().contains(w))
                    && a.get_downlevel_capabilities()
                        .flags
                        .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
            })
            .collect();
        let class = |a: &wgpu::Adapter| {
            let info = a.get_info();
            (rank(&info), info.backend != wgpu::Backend::Vulkan)
        };
        // Stable: equal adapters keep the order the driver lists them in.
        candidates.sort_by_key(class);
        let best = candidates.first().map(class);
        candidates.retain(|a| Some(class(a)) == best);
        let n = candidates.len().max(1);
        let Some(adapter) = candidates.into_iter().nth(index % n) else {
            return Err(GpuError::NoAdapter {
                policy,
                wanted,
                seen: if seen.is_empty() {
                    "none".into()
                } else {
                    seen.join("; ")
                },
            });
        };
        Self::open(adapter)
    }

    fn open(adapter: wgpu::Adapter) -> Result<Self> {
        let info = adapter.get_info();
        let adapter_features = adapter.features();
        // Only what the kernels can use: f16 and subgroups for tuned kernels, timestamps for
        // the per-stage profile. None is required.
        let wanted = wgpu::Features::SHADER_F16
            | wgpu::Features::SUBGROUP
            | wgpu::Features::TIMESTAMP_QUERY
            | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS;
        let cooperative_matrices = adapter.cooperative_matrix_properties();
        let mma_f16 = std::env::var(MMA_ENV).map_or(true, |v| v != "0")
            && adapter_features.contains(wgpu::Features::SHADER_F16)
            && adapter_features.contains(wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX)
            && info.subgroup_min_size == 32
            && info.subgroup_max_size == 32
            && cooperative_matrices.iter().any(|c| {
                (c.m_size, c.n_size, c.k_size) == (16, 16, 16)
                    && c.ab_type == wgpu::CooperativeScalarType::F16
                    && c.cr_type == wgpu::CooperativeScalarType::F32
            });
        let mut features = adapter_features & wanted;
        let mut experimental = wgpu::ExperimentalFeatures::disabled();
        if mma_f16 {
            features |= wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX;
            // SAFETY: wgpu marks cooperative matrices experimental (its implementation may
            // still have bugs); only conv_mma.wgsl uses them, and only where the adapter lists
            // the one shape it uses. Its results are checked against the CPU on a real GPU by
            // the mma tests (tools/device/gpu_check.sh); GAGAVATAR_GPU_MMA=0 turns it off.
            experimental = unsafe { wgpu::ExperimentalFeatures::enabled() };
        }
        // The adapter's own limits: the renderer's largest buffers (32 channels at 512x512) and
        // bindings exceed WebGPU's defaults on some adapters, never on a real one.
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("gagavatar"),
            required_features: features,
            required_limits: limits.clone(),
            experimental_features: experimental,
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| GpuError::Device(format!("{}: {e}", describe(&info))))?;
        Ok(Self {
            device,
            queue,
            info,
            limits,
            features,
            adapter_features,
            cooperative_matrices,
            mma_f16,
            kernels: Default::default(),
            allocated: Default::default(),
        })
    }

    pub fn is_cpu(&self) -> bool {
        is_cpu_adapter(&self.info)
    }

    pub fn describe(&self) -> String {
        describe(&self.info)
    }

    /// Bytes of GPU buffers this process created through this device (weights, activations,
    /// scratch; not the driver's own memory).
    pub fn allocated_bytes(&self) -> u64 {
        self.allocated.load(std::sync::atomic::Ordering::Relaxed)
    }

    pub fn has_timestamps(&self) -> bool {
        self.features.contains(wgpu::Features::TIMESTAMP_QUERY)
    }

    /// Blocks until every submitted command has finished.
    pub fn wait(&self) -> Result<()> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Device(format!("waiting for the GPU: {e}")))
    }
}
