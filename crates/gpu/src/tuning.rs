//! The kernels' tuning knobs (tile sizes, items per thread, sort digit width). Every value is
//! substituted into the WGSL source when a pipeline is built, so trying another value needs no
//! rebuild of the binary: set `GAGAVATAR_GPU_TUNE`, e.g.
//! `GAGAVATAR_GPU_TUNE=conv_bn=128,conv_tn=8,radix_bits=5`. crates/gpu/README.md lists what to try.

use crate::device::Gpu;
use crate::error::{GpuError, Result};

/// Environment variable holding `key=value` pairs separated by commas.
pub const TUNE_ENV: &str = "GAGAVATAR_GPU_TUNE";

/// Output tile of the convolution kernel (an implicit GEMM: rows = output channels, columns =
/// pixels, depth = input channels x kernel taps). A workgroup computes `bm x bn` outputs with
/// `(bm / tm) * (bn / tn)` threads, each `tm x tn` of them, stepping `bk` along the depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvTile {
    pub bm: u32,
    pub bn: u32,
    pub bk: u32,
    pub tm: u32,
    pub tn: u32,
}

impl ConvTile {
    pub fn threads(&self) -> u32 {
        (self.bm / self.tm) * (self.bn / self.tn)
    }

    fn check(&self, name: &str, max_threads: u32, max_shared: u32) -> Result<()> {
        let ok = self.bm > 0
            && self.bn > 0
            && self.bk > 0
            && self.tm > 0
            && self.tn > 0
            && self.bm.is_multiple_of(self.tm)
            && self.bn.is_multiple_of(self.tn)
            && self.threads() <= max_threads;
        if !ok {
            return Err(GpuError::Unsupported(format!(
                "{name} tile {self:?}: bm, bn must be multiples of tm, tn, with at most \
                 {max_threads} threads (bm/tm)(bn/tn)"
            )));
        }
        let shared = 4 * self.bk * (self.bm + self.bn);
        if shared > max_shared {
            return Err(GpuError::Unsupported(format!(
                "{name} tile {self:?} needs {shared} bytes of workgroup memory, the device has \
                 {max_shared}"
            )));
        }
        Ok(())
    }
}

/// Output tile of the tensor-core convolution (`conv_mma.wgsl`): a workgroup computes
/// `bm x bn` outputs with one 32-lane subgroup per `16 fm x 16 fn` block of them (each holding
/// `fm x fn` 16x16 f32 accumulators), stepping `bk` (a multiple of 16) along the depth; with
/// `prefetch` the next step's tiles are read from memory while this step's multiply-adds run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MmaTile {
    pub bm: u32,
    pub bn: u32,
    pub bk: u32,
    pub fm: u32,
    pub fn_: u32,
    pub prefetch: bool,
}

impl MmaTile {
    /// The tile for a layer of `cout` output channels with `fit`: where `cout` fills only 16 or
    /// 32 of the tile's rows (and `fm` is 1), that many rows and proportionally more pixels,
    /// so no subgroup multiplies padding; the same threads and subgroups.
    pub fn fitted(&self, cout: usize, fit: bool) -> MmaTile {
        if !fit || self.fm != 1 {
            return *self;
        }
        for rows in [16u32, 32] {
            if cout <= rows as usize
                && rows < self.bm
                && self.bm.is_multiple_of(rows)
                && (self.bn * (self.bm / rows)).is_multiple_of(16 * self.fn_)
            {
                return MmaTile {
                    bm: rows,
                    bn: self.bn * (self.bm / rows),
                    ..*self
                };
            }
        }
        *self
    }

    pub fn warps(&self) -> u32 {
        (self.bm / (16 * self.fm.max(1))) * (self.bn / (16 * self.fn_.max(1)))
    }

    pub fn threads(&self) -> u32 {
        32 * self.warps()
    }

    /// Workgroup memory: f16 weight and input tiles and a 16x16 f32 block per subgroup.
    pub fn shared_bytes(&self) -> u32 {
        2 * self.bk * (self.bm + self.bn) + 4 * 256 * self.warps()
    }

    fn check(&self, name: &str, max_threads: u32, max_shared: u32) -> Result<()> {
        let ok = self.fm > 0
            && self.fn_ > 0
            && self.bk > 0
            && self.bk.is_multiple_of(16)
            && self.bm > 0
            && self.bn > 0
            && self.bm.is_multiple_of(16 * self.fm)
            && self.bn.is_multiple_of(16 * self.fn_)
            && self.threads() <= max_threads;
        if !ok {
            return Err(GpuError::Unsupported(format!(
                "{name} tile {self:?}: bm, bn must be multiples of 16 fm, 16 fn, bk of 16, with \
                 at most {max_threads} threads (32 per 16fm x 16fn block)"
            )));
        }
        if self.shared_bytes() > max_shared {
            return Err(GpuError::Unsupported(format!(
                "{name} tile {self:?} needs {} bytes of workgroup memory, the device has \
                 {max_shared}",
                self.shared_bytes()
            )));
        }
        Ok(())
    }
}

/// The renderer's convolution precision on a GPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GpuPrecision {
    /// f32 everywhere (conv.wgsl).
    F32,
    /// f16 inputs and f32 sums on the tensor cores (conv_mma.wgsl); an error on a GPU without
    /// them.
    F16,
    /// f16 where the GPU has tensor cores ([`Gpu::mma_f16`]), f32 elsewhere.
    #[default]
    Auto,
}

impl GpuPrecision {
    pub fn name(self) -> &'static str {
        match self {
            GpuPrecision::F32 => "f32",
            GpuPrecision::F16 => "f16",
            GpuPrecision::Auto => "auto",
        }
    }
}

impl std::str::FromStr for GpuPrecision {
    type Err = GpuError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "f32" => Ok(GpuPrecision::F32),
            "f16" => Ok(GpuPrecision::F16),
            "auto" => Ok(GpuPrecision::Auto),
            _ => Err(GpuError::Unsupported(format!(
                "GPU precision `{s}`: expected f32, f16 or auto"
            ))),
        }
    }
}

/// All knobs; [`Tuning::default`] is what runs unless `GAGAVATAR_GPU_TUNE` says otherwise.
#[derive(Debug, Clone, PartialEq)]
pub struct Tuning {
    /// Values per thread of the prefix-sum kernels (blocks of 256 x this).
    pub scan_items: u32,
    /// Keys per thread of the radix-sort kernels (blocks of 256 x this).
    pub radix_items: u32,
    /// Bits per radix-sort pass.
    pub radix_bits: u32,
    /// Initial room for (tile, Gaussian) pairs, per Gaussian; grown when a frame needs more.
    pub pairs_per_gaussian: f64,
    /// Convolution tile for layers with many output pixels per output channel.
    pub conv: ConvTile,
    /// Convolution tile for layers with few pixels (16x16 and below): more channels per
    /// workgroup, fewer pixels.
    pub conv_small: ConvTile,
    /// Depth (input channels x taps) per workgroup of the split-K convolution used where one
    /// layer alone would not fill the device (low resolutions, many channels); 0 = never.
    pub conv_split_k: u32,
    /// Convolutions on the tensor cores (f16 inputs, f32 sums) where the device has them
    /// ([`crate::Gpu::mma_f16`]); the f32 kernels otherwise.
    pub mma: bool,
    /// Tensor-core tile for layers of 32x32 pixels and more.
    pub mma_tile: MmaTile,
    /// Tensor-core tile for smaller layers.
    pub mma_small: MmaTile,
    /// Split-K depth for the tensor-core convolutions (0 = never).
    pub mma_split_k: u32,
    /// Tensor-core tiles fitted to layers of at most 32 output channels
    /// ([`MmaTile::fitted`]).
    pub mma_fit: bool,
    /// Threads per token of the ViT's LayerNorm (a power of two, 1..=256).
    pub ln_slices: u32,
}

impl Default for Tuning {
    fn default() -> Self {
        Self {
            scan_items: 4,
            radix_items: 4,
            radix_bits: 4,
            pairs_per_gaussian: 4.0,
            // Measured on an H200 (bench drive, release, 40 frames; tools/device/gpu_check.sh):
            // 32x128 / 8x8 per thread ran the renderer's convs in 37.6 ms (23.5 frames/s),
            // these in 19.1 ms (42.0 frames/s). 256-thread tiles of 4x4 did better than 64- or
            // 128-thread tiles of 8x8, and split-K of 144 better than 576 or 1152.
            conv: ConvTile {
                bm: 64,
                bn: 64,
                bk: 16,
                tm: 4,
                tn: 4,
            },
            conv_small: ConvTile {
                bm: 32,
                bn: 32,
                bk: 16,
                tm: 2,
                tn: 4,
            },
            conv_split_k: 144,
            mma: false,
            // Measured on an H200 (40-frame sweeps, crates/gpu/README.md): the kernel is bound
            // by staging its tiles, not by the multiply-adds, so one 16x16 block per subgroup
            // (more threads staging) beat 2x2 and 2x1 blocks per subgroup, and prefetching the
            // next step took the renderer's convs from 13.9 to 10.0 ms. bk 16 rendered 4%
            // faster but reconstructed 9% slower.
            mma_tile: MmaTile {
                bm: 64,
                bn: 64,
                bk: 32,
                fm: 1,
                fn_: 1,
                prefetch: true,
            },
            mma_small: MmaTile {
                bm: 64,
                bn: 64,
                bk: 32,
                fm: 1,
                fn_: 1,
                prefetch: true,
            },
            mma_split_k: 144,
            mma_fit: true,
            ln_slices: 16,
        }
    }
}

impl Tuning {
    /// The defaults with `GAGAVATAR_GPU_TUNE` applied.
    pub fn from_env() -> Result<Self> {
        let mut t = Self::default();
        if let Ok(spec) = std::env::var(TUNE_ENV) {
            t.apply(&spec)?;
        }
        Ok(t)
    }

    /// Applies `key=value,...` (keys as the field names, `conv_bm` .. `conv_tn` and
    /// `conv_small_bm` .. for the tiles).
    pub fn apply(&mut self, spec: &str) -> Result<()> {
        for item in spec.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let bad = |why: &str| GpuError::Unsupported(format!("{TUNE_ENV}: `{item}`: {why}"));
            let (k, v) = item
                .split_once('=')
                .ok_or_else(|| bad("expected key=value"))?;
            let int = || {
                v.trim()
                    .parse::<u32>()
                    .map_err(|_| bad("not a whole number"))
            };
            match k.trim() {
                "scan_items" => self.scan_items = int()?,
                "radix_items" => self.radix_items = int()?,
                "radix_bits" => self.radix_bits = int()?,
                "pairs_per_gaussian" => {
                    self.pairs_per_gaussian = v.trim().parse().map_err(|_| bad("not a number"))?
                }
                "conv_split_k" => self.conv_split_k = int()?,
                "mma" => self.mma = int()? != 0,
                "mma_split_k" => self.mma_split_k = int()?,
                "mma_fit" => self.mma_fit = int()? != 0,
                "ln_slices" => self.ln_slices = int()?,
                key if key.starts_with("mma_") => {
                    let (tile, field) = if let Some(f) = key.strip_prefix("mma_small_") {
                        (&mut self.mma_small, f)
                    } else {
                        (&mut self.mma_tile, &key[4..])
                    };
                    let slot = match field {
                        "bm" => &mut tile.bm,
                        "bn" => &mut tile.bn,
                        "bk" => &mut tile.bk,
                        "fm" => &mut tile.fm,
                        "fn" => &mut tile.fn_,
                        "prefetch" => {
                            tile.prefetch = int()? != 0;
                            continue;
                        }
                        _ => return Err(bad("unknown key")),
                    };
                    *slot = int()?;
                }
                key => {
                    let (tile, field) = if let Some(f) = key.strip_prefix("conv_small_") {
                        (&mut self.conv_small, f)
                    } else if let Some(f) = key.strip_prefix("conv_") {
                        (&mut self.conv, f)
                    } else {
                        return Err(bad("unknown key"));
                    };
                    let slot = match field {
                        "bm" => &mut tile.bm,
                        "bn" => &mut tile.bn,
                        "bk" => &mut tile.bk,
                        "tm" => &mut tile.tm,
                        "tn" => &mut tile.tn,
                        _ => return Err(bad("unknown key")),
                    };
                    *slot = int()?;
                }
            }
        }
        Ok(())
    }

    /// These knobs with the convolutions of `precision` on `gpu`.
    pub fn with_precision(&self, precision: GpuPrecision, gpu: &Gpu) -> Result<Self> {
        let mma = match precision {
            GpuPrecision::F32 => false,
            GpuPrecision::Auto => gpu.mma_f16,
            GpuPrecision::F16 if gpu.mma_f16 => true,
            GpuPrecision::F16 => {
                return Err(GpuError::Unsupported(format!(
                    "f16 convolutions need 16x16x16 f16 cooperative matrices (tensor cores), \
                     which {} does not offer; use f32 or auto",
                    gpu.describe()
                )))
            }
        };
        Ok(Self {
            mma,
            ..self.clone()
        })
    }

    /// These knobs as they apply on `gpu`: the tensor-core convolutions only where it has
    /// them ([`Gpu::mma_f16`]).
    pub fn for_device(&self, gpu: &Gpu) -> Self {
        Self {
            mma: self.mma && gpu.mma_f16,
            ..self.clone()
        }
    }

    /// Checks the values against the rules the kernels rely on and the device's limits.
    pub fn check(&self, limits: &wgpu::Limits) -> Result<()> {
        let bad = |m: String| Err(GpuError::Unsupported(format!("{TUNE_ENV}: {m}")));
        if !(1..=16).contains(&self.scan_items) || !(1..=16).contains(&self.radix_items) {
            return bad("scan_items and radix_items must be 1..=16".into());
        }
        if !(self.ln_slices.is_power_of_two() && self.ln_slices <= 256) {
            return bad("ln_slices must be a power of two up to 256".into());
        }
        if !(1..=8).contains(&self.radix_bits) {
            return bad("radix_bits must be 1..=8".into());
        }
        // The radix scatter keeps a block of keys and values in workgroup memory.
        let radix_shared = 8 * 256 * self.radix_items + 1024 + 4 * (1 << self.radix_bits);
        if radix_shared > limits.max_compute_workgroup_storage_size {
            return bad(format!(
                "radix_items {} needs {radix_shared} bytes of workgroup memory",
                self.radix_items
            ));
        }
        if !(self.pairs_per_gaussian > 0.0 && self.pairs_per_gaussian <= 1024.0) {
            return bad("pairs_per_gaussian must be in (0, 1024]".into());
        }
        let threads = limits.max_compute_invocations_per_workgroup;
        let shared = limits.max_compute_workgroup_storage_size;
        self.conv.check("conv", threads, shared)?;
        self.conv_small.check("conv_small", threads, shared)?;
        if self.mma {
            self.mma_tile.check("mma", threads, shared)?;
            self.mma_small.check("mma_small", threads, shared)?;
            for cout in [16, 32] {
                self.mma_tile.fitted(cout, self.mma_fit).check(
                    "mma (fitted to 16 or 32 output channels)",
                    threads,
                    shared,
                )?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Fitted tiles keep the threads and subgroups and shrink only where the channels leave
    /// rows empty; without `fit`, or with several blocks per subgroup, the tile is as given.
    #[test]
    fn tiles_fit_few_output_channels() {
        let t = Tuning::default().mma_tile;
        for (cout, bm) in [(1, 16), (16, 16), (17, 32), (32, 32), (33, 64), (512, 64)] {
            let f = t.fitted(cout, true);
            assert_eq!(f.bm, bm, "cout {cout}");
            assert_eq!(f.bm * f.bn, t.bm * t.bn, "cout {cout}");
            assert_eq!(f.threads(), t.threads(), "cout {cout}");
        }
        assert_eq!(t.fitted(3, false), t);
        let wide = MmaTile { fm: 2, ..t };
        assert_eq!(wide.fitted(3, true), wide);
        let mut off = Tuning::default();
        off.apply("mma_fit=0,mma_prefetch=0").unwrap();
        assert!(!off.mma_fit && !off.mma_tile.prefetch && off.mma_small.prefetch);
    }

    #[test]
    fn parses_and_rejects() {
        let mut t = Tuning::default();
        t.apply("conv_bn=128, conv_small_tm=8,radix_bits=5,pairs_per_gaussian=2.5")
            .unwrap();
        assert_eq!(t.conv.bn, 128);
        assert_eq!(t.conv_small.tm, 8);
        assert_eq!(t.radix_bits, 5);
        assert_eq!(t.pairs_per_gaussian, 2.5);
        t.apply("mma=1,mma_bn=64,mma_small_fn=2,mma_split_k=0")
            .unwrap();
        assert!(t.mma);
        assert_eq!((t.mma_tile.bn, t.mma_small.fn_, t.mma_split_k), (64, 2, 0));
        let mut m = Tuning {
            mma: true,
            ..Default::default()
        };
        let big = wgpu::Limits {
            max_compute_workgroup_storage_size: 49152,
            max_compute_invocations_per_workgroup: 1024,
            ..Default::default()
        };
        m.check(&big).unwrap();
        m.mma_tile.bk = 24;
        assert!(m.check(&big).is_err());
        assert!(Tuning::default().apply("mma_xx=1").is_err());
        for bad in ["conv_bn", "conv_xx=1", "nope=2", "radix_bits=x"] {
            assert!(Tuning::default().apply(bad).is_err(), "{bad}");
        }
        let lim = wgpu::Limits::default();
        Tuning::default().check(&lim).unwrap();
        let mut t = Tuning::default();
        t.conv.tm = 3;
        assert!(t.check(&lim).is_err());
        let t = Tuning {
            radix_bits: 9,
            ..Default::default()
        };
        assert!(t.check(&lim).is_err());
    }
}
