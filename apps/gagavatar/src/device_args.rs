//! `--device auto|cpu|gpu`: where the per-frame drive (FLAME, splatting, neural renderer)
//! runs. Commands flatten [`DeviceArgs`] into their arguments and call [`DeviceArgs::open`].

use std::sync::Arc;

use anyhow::Result;
use clap::{Args, ValueEnum};
use gagavatar_gpu::{AdapterPolicy, Gpu};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ValueEnum)]
pub enum DeviceChoice {
    /// A GPU when one is found (CPU-emulated adapters such as lavapipe do not count), else
    /// the CPU.
    #[default]
    Auto,
    /// The CPU path.
    Cpu,
    /// A GPU (Vulkan, Metal or D3D12; a CPU-emulated one only if nothing else), or an error.
    Gpu,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ValueEnum)]
pub enum GpuPrecisionArg {
    /// f32 convolutions.
    F32,
    /// f16 inputs, f32 sums, on the tensor cores (an error on a GPU without them).
    F16,
    /// f16 on a GPU with tensor cores, f32 on others.
    #[default]
    Auto,
}

#[derive(Debug, Clone, Copy, Default, Args)]
pub struct DeviceArgs {
    /// Where frames are rendered: auto (a GPU if one is found, else the CPU), cpu or gpu.
    /// GAGAVATAR_GPU_ADAPTER=<name part> picks among several GPUs.
    #[arg(long, value_enum, default_value_t = DeviceChoice::Auto)]
    pub device: DeviceChoice,
    /// Precision of the neural renderer's convolutions on a GPU: f32, f16 (tensor cores: on an
    /// H200 the fine image stays within 3.6e-3 of f32, under one 8-bit step) or auto (f16
    /// where the GPU has tensor cores).
    #[arg(long, value_enum, default_value_t = GpuPrecisionArg::Auto)]
    pub gpu_precision: GpuPrecisionArg,
}

impl DeviceArgs {
    /// The GPU to drive frames on, or `None` for the CPU path. Prints one line saying which.
    pub fn open(&self) -> Result<Option<Arc<Gpu>>> {
        self.open_for("rendering")
    }

    /// [`DeviceArgs::open`], the line saying `what` runs there ("rendering", "reconstructing
    /// and rendering", ...).
    pub fn open_for(&self, what: &str) -> Result<Option<Arc<Gpu>>> {
        self.open_as(what, false, 0)
    }

    /// [`DeviceArgs::open_for`] for the training kernels, which run f32 convolutions whatever
    /// the adapter offers (the f16 tensor-core path is forward only): f16 asked for is an
    /// error, and the line says f32.
    pub fn open_for_training(&self, what: &str) -> Result<Option<Arc<Gpu>>> {
        self.open_for_training_nth(what, 0)
    }

    /// [`DeviceArgs::open_for_training`] on the `index`-th of several equal GPUs (a
    /// data-parallel rank's on its machine; see [`Gpu::nth`]).
    pub fn open_for_training_nth(&self, what: &str, index: usize) -> Result<Option<Arc<Gpu>>> {
        if self.gpu_precision == GpuPrecisionArg::F16 {
            anyhow::bail!(
                "--gpu-precision f16 is for rendering: {what} runs f32 convolutions (use f32 or auto)"
            );
        }
        self.open_as(what, true, index)
    }

    fn open_as(&self, what: &str, f32_only: bool, index: usize) -> Result<Option<Arc<Gpu>>> {
        let gpu = match self.device {
            DeviceChoice::Cpu => return Ok(None),
            DeviceChoice::Auto => match Gpu::nth(AdapterPolicy::RealOnly, index) {
                Ok(g) => g,
                Err(e) => {
                    eprintln!("{e}; {what} on the CPU");
                    return Ok(None);
                }
            },
            DeviceChoice::Gpu => Gpu::nth(AdapterPolicy::AllowCpu, index)?,
        };
        // Checked here so a bad combination fails before any work.
        let mma = !f32_only
            && gagavatar_gpu::Tuning::default()
                .with_precision(self.precision(), &gpu)?
                .mma;
        let convs = if mma {
            "f16 convolutions on the tensor cores"
        } else {
            "f32 convolutions"
        };
        if gpu.is_cpu() {
            eprintln!(
                "{what} on {} ({convs}), a CPU-emulated GPU: expect it to be slower than \
                 --device cpu",
                gpu.describe()
            );
        } else {
            eprintln!("{what} on the GPU: {} ({convs})", gpu.describe());
        }
        Ok(Some(Arc::new(gpu)))
    }

    pub fn precision(&self) -> gagavatar_gpu::GpuPrecision {
        match self.gpu_precision {
            GpuPrecisionArg::F32 => gagavatar_gpu::GpuPrecision::F32,
            GpuPrecisionArg::F16 => gagavatar_gpu::GpuPrecision::F16,
            GpuPrecisionArg::Auto => gagavatar_gpu::GpuPrecision::Auto,
        }
    }

    /// The kernels' knobs (`GAGAVATAR_GPU_TUNE`) with this precision on `gpu`.
    pub fn tuning(&self, gpu: &Gpu) -> Result<gagavatar_gpu::Tuning> {
        Ok(gagavatar_gpu::Tuning::from_env()?.with_precision(self.precision(), gpu)?)
    }
}
