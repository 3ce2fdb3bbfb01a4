//! Exclusive prefix sums and a stable LSD radix sort of (u32 key, u32 value) pairs, for the
//! splatting's depth order and tile binning. Element counts may be written by an earlier kernel
//! of the same frame (`sizes` slots and indirect dispatches), so nothing is read back mid-frame.

use crate::device::Gpu;
use crate::error::Result;
use crate::kernel::{groups, Bind, Grid, Params, Step};
use crate::tuning::Tuning;

const SCAN_REDUCE: &str = include_str!("shaders/scan_reduce.wgsl");
const SCAN_TOP: &str = include_str!("shaders/scan_top.wgsl");
const SCAN_DOWN: &str = include_str!("shaders/scan_down.wgsl");
const RADIX_COUNT: &str = include_str!("shaders/radix_count.wgsl");
const RADIX_SCATTER: &str = include_str!("shaders/radix_scatter.wgsl");

/// "No slot": the count is the static one.
pub const NO_SLOT: u32 = 0xffff_ffff;

/// Where a kernel finds how many elements it works on.
#[derive(Debug, Clone)]
pub struct Count {
    /// Used when `slot` is [`NO_SLOT`].
    pub fixed: u32,
    /// Index into the `sizes` buffer.
    pub slot: u32,
    /// The most elements there can be (buffers and grids are sized for it).
    pub capacity: u32,
    /// Workgroups to launch for the block kernels: fixed for a fixed count, else an indirect
    /// argument written earlier in the frame.
    pub grid: Option<Grid>,
}

impl Count {
    pub fn fixed(n: u32) -> Self {
        Self {
            fixed: n,
            slot: NO_SLOT,
            capacity: n,
            grid: None,
        }
    }
}

/// `out = exclusive_scan(data)` over `count` u32 values (`out` must be another buffer); the
/// total goes to `sizes[total_slot]` unless that is [`NO_SLOT`].
pub fn scan_steps(
    gpu: &Gpu,
    tuning: &Tuning,
    data: &wgpu::Buffer,
    out: &wgpu::Buffer,
    sizes: &wgpu::Buffer,
    count: &Count,
    total_slot: u32,
) -> Result<Vec<Step>> {
    let items = tuning.scan_items;
    let block = 256 * items as usize;
    let max_blocks = (count.capacity as usize).div_ceil(block).max(1);
    let consts = [("ITEMS", items.to_string())];
    let reduce = gpu.kernel(
        "scan_reduce",
        SCAN_REDUCE,
        &consts,
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let top = gpu.kernel(
        "scan_top",
        SCAN_TOP,
        &consts,
        &[Bind::Uniform, Bind::ReadWrite, Bind::ReadWrite],
    )?;
    let down = gpu.kernel(
        "scan_down",
        SCAN_DOWN,
        &consts,
        &[
            Bind::Uniform,
            Bind::Read,
            Bind::Read,
            Bind::Read,
            Bind::ReadWrite,
        ],
    )?;
    let sums = gpu.buffer("scan sums", 4 * max_blocks as u64);
    let pn = gpu.uniform("scan n", &Params::new().u(count.fixed).u(count.slot));
    let pt = gpu.uniform(
        "scan top",
        &Params::new().u(max_blocks as u32).u(total_slot),
    );
    let grid =
        count
            .grid
            .clone()
            .unwrap_or(Grid::Fixed([groups(count.fixed as usize, block), 1, 1]));
    Ok(vec![
        Step::new(
            reduce.clone(),
            gpu.bind(&reduce, &[&pn, sizes, data, &sums])?,
            grid.clone(),
        ),
        Step::new(
            top.clone(),
            gpu.bind(&top, &[&pt, &sums, sizes])?,
            Grid::Fixed([1, 1, 1]),
        ),
        Step::new(
            down.clone(),
            gpu.bind(&down, &[&pn, sizes, &sums, data, out])?,
            grid,
        ),
    ])
}

/// A stable radix sort of `keys[..n]` by their low `key_bits` bits, carrying `vals`.
pub struct RadixSort {
    pub steps: Vec<Step>,
    /// Which of the two buffer pairs holds the result: 0 = the caller's, 1 = the sort's own.
    pub result_in_own: bool,
    pub keys_b: wgpu::Buffer,
    pub vals_b: wgpu::Buffer,
}

/// Block size (elements per workgroup) of the radix kernels.
pub fn radix_block(tuning: &Tuning) -> u32 {
    256 * tuning.radix_items
}

impl RadixSort {
    /// `count`: the element count. For a count written during the frame (`count.slot`), the
    /// histogram length (`radix * blocks`) must be in `sizes[hist_slot]` and `hist_grid` must
    /// launch `ceil(hist_len / (256 * scan_items))` workgroups; for a fixed count both are
    /// derived here.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        gpu: &Gpu,
        tuning: &Tuning,
        keys: &wgpu::Buffer,
        vals: &wgpu::Buffer,
        key_bits: u32,
        sizes: &wgpu::Buffer,
        count: &Count,
        hist_slot: u32,
        hist_grid: Option<Grid>,
    ) -> Result<Self> {
        let bits = tuning.radix_bits;
        let radix = 1u32 << bits;
        let block = radix_block(tuning);
        let cap = count.capacity.max(1) as u64;
        let keys_b = gpu.buffer("sort keys", 4 * cap);
        let vals_b = gpu.buffer("sort vals", 4 * cap);
        let max_blocks = cap.div_ceil(block as u64);
        let hist_cap = (radix as u64 * max_blocks) as u32;
        let hist = gpu.buffer("radix histogram", 4 * hist_cap as u64);
        let offsets = gpu.buffer("radix offsets", 4 * hist_cap as u64);
        let consts = [
            ("ITEMS", tuning.radix_items.to_string()),
            ("RADIX", radix.to_string()),
            ("BITS", bits.to_string()),
        ];
        let kc = gpu.kernel(
            "radix_count",
            RADIX_COUNT,
            &consts,
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let ks = gpu.kernel(
            "radix_scatter",
            RADIX_SCATTER,
            &consts,
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
                Bind::ReadWrite,
            ],
        )?;
        let grid = count.grid.clone().unwrap_or(Grid::Fixed([
            groups(count.fixed as usize, block as usize),
            1,
            1,
        ]));
        let hist_count = if count.slot == NO_SLOT {
            let blocks = (count.fixed as u64).div_ceil(block as u64) as u32;
            Count::fixed(radix * blocks)
        } else {
            Count {
                fixed: 0,
                slot: hist_slot,
                capacity: hist_cap,
                grid: hist_grid,
            }
        };
        let scan = scan_steps(gpu, tuning, &hist, &offsets, sizes, &hist_count, NO_SLOT)?;
        let mut steps = Vec::new();
        let passes = key_bits.div_ceil(bits).max(1);
        let pairs = [(keys, vals), (&keys_b, &vals_b)];
        for pass in 0..passes {
            let (ki, vi) = pairs[(pass % 2) as usize];
            let (ko, vo) = pairs[((pass + 1) % 2) as usize];
            let p = gpu.uniform(
                "radix pass",
                &Params::new().u(pass * bits).u(count.fixed).u(count.slot),
            );
            steps.push(Step::new(
                kc.clone(),
                gpu.bind(&kc, &[&p, sizes, ki, &hist])?,
                grid.clone(),
            ));
            steps.extend(scan.iter().cloned());
            steps.push(Step::new(
                ks.clone(),
                gpu.bind(&ks, &[&p, sizes, ki, vi, &offsets, ko, vo])?,
                grid.clone(),
            ));
        }
        Ok(Self {
            steps,
            result_in_own: passes % 2 == 1,
            keys_b,
            vals_b,
        })
    }

    /// The sorted keys and values (the caller's buffers or the sort's own).
    pub fn result<'a>(
        &'a self,
        keys: &'a wgpu::Buffer,
        vals: &'a wgpu::Buffer,
    ) -> (&'a wgpu::Buffer, &'a wgpu::Buffer) {
        if self.result_in_own {
            (&self.keys_b, &self.vals_b)
        } else {
            (keys, vals)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::gpu;
    use gagavatar_splat::testscene::Rng;

    /// Random keys with many repeats, sorted stably (the values record the input order), with
    /// counts that are not whole blocks, for several tunings.
    #[test]
    fn radix_sort_is_stable_and_matches_std() {
        let Some(g) = gpu() else { return };
        let mut rng = Rng::new(5);
        for (n, bits, tune) in [
            (1usize, 32u32, "radix_bits=4"),
            (1000, 10, "radix_bits=4"),
            (5000, 32, "radix_bits=4"),
            (70_001, 13, "radix_bits=5,radix_items=2,scan_items=1"),
            (3001, 7, "radix_bits=3,radix_items=8,scan_items=8"),
        ] {
            let mut t = Tuning::default();
            t.apply(tune).unwrap();
            let keys: Vec<u32> = (0..n)
                .map(|_| {
                    let k = rng.next_u64() as u32;
                    // Few distinct values, so ties are everywhere.
                    let k = k % 97 * 0x0101_0101;
                    if bits == 32 {
                        k
                    } else {
                        k & ((1 << bits) - 1)
                    }
                })
                .collect();
            let vals: Vec<u32> = (0..n as u32).collect();
            let kb = g.buffer_with("k", &keys);
            let vb = g.buffer_with("v", &vals);
            let sizes = g.buffer("sizes", 16);
            let sort = RadixSort::new(
                g,
                &t,
                &kb,
                &vb,
                bits,
                &sizes,
                &Count::fixed(n as u32),
                NO_SLOT,
                None,
            )
            .unwrap();
            g.submit(&sort.steps);
            let (ko, vo) = sort.result(&kb, &vb);
            let got_k = g.read_u32(ko, n).unwrap();
            let got_v = g.read_u32(vo, n).unwrap();
            let mut want: Vec<(u32, u32)> = keys.iter().copied().zip(vals).collect();
            want.sort_by_key(|e| e.0);
            for i in 0..n {
                assert_eq!(
                    (got_k[i], got_v[i]),
                    want[i],
                    "n {n}, bits {bits}, {tune}: element {i}"
                );
            }
        }
    }

    #[test]
    fn exclusive_scan_matches_std() {
        let Some(g) = gpu() else { return };
        let mut rng = Rng::new(9);
        for (n, tune) in [
            (1usize, ""),
            (1023, ""),
            (1024, ""),
            (300_001, "scan_items=3"),
        ] {
            let mut t = Tuning::default();
            t.apply(tune).unwrap();
            let data: Vec<u32> = (0..n).map(|_| (rng.next_u64() % 17) as u32).collect();
            let db = g.buffer_with("d", &data);
            let out = g.buffer("o", 4 * n as u64);
            let sizes = g.buffer("sizes", 16);
            let steps = scan_steps(g, &t, &db, &out, &sizes, &Count::fixed(n as u32), 2).unwrap();
            g.submit(&steps);
            let got = g.read_u32(&out, n).unwrap();
            let mut acc = 0u32;
            for i in 0..n {
                assert_eq!(got[i], acc, "n {n}: element {i}");
                acc += data[i];
            }
            assert_eq!(g.read_u32(&sizes, 3).unwrap()[2], acc, "n {n}: total");
        }
    }
}
