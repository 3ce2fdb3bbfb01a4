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

#[derive(Debug, Clone, Copy, Default, Args)]
pub struct DeviceArgs {
    /// Where frames are rendered: auto (a GPU if one is found, else the CPU), cpu or gpu.
    /// GAGAVATAR_GPU_ADAPTER=<name part> picks among several GPUs.
    #[arg(long, value_enum, default_value_t = DeviceChoice::Auto)]
    pub device: DeviceChoice,
}

impl DeviceArgs {
    /// The GPU to drive frames on, or `None` for the CPU path. Prints one line saying which.
    pub fn open(&self) -> Result<Option<Arc<Gpu>>> {
        let gpu = match self.device {
            DeviceChoice::Cpu => return Ok(None),
            DeviceChoice::Auto => match Gpu::new(AdapterPolicy::RealOnly) {
                Ok(g) => g,
                Err(e) => {
                    eprintln!("{e}; rendering on the CPU");
                    return Ok(None);
                }
            },
            DeviceChoice::Gpu => Gpu::new(AdapterPolicy::AllowCpu)?,
        };
        if gpu.is_cpu() {
            eprintln!(
                "rendering on {}, a CPU-emulated GPU: expect it to be slower than --device cpu",
                gpu.describe()
            );
        } else {
            eprintln!("rendering on the GPU: {}", gpu.describe());
        }
        Ok(Some(Arc::new(gpu)))
    }
}
