//! Which adapters the device may pick (apart from the device, so errors can name it).

/// Which adapters [`Gpu::new`] may pick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterPolicy {
    /// Only real GPUs (not CPU-emulated adapters).
    RealOnly,
    /// Real GPUs first, else a CPU-emulated adapter.
    AllowCpu,
}
