//! Splatting steps 2-7: depth sort, (tile, Gaussian) pairs in depth order, the stable sort of
//! the pairs by tile (so each tile lists its Gaussians front to back, ties by index, as the
//! release's stable sort does) and each tile's range in that list.

use crate::device::Gpu;
use crate::error::Result;
use crate::kernel::{linear_grid, Bind, Grid, Params, Step};
use crate::sort::{radix_block, scan_steps, Count, RadixSort, NO_SLOT};
use crate::splat::project::Projected;
use crate::tuning::Tuning;

const PAIR_COUNT: &str = include_str!("../shaders/pair_count.wgsl");
const PAIR_EMIT: &str = include_str!("../shaders/pair_emit.wgsl");
const PAIR_ARGS: &str = include_str!("../shaders/pair_args.wgsl");
const TILE_RANGES: &str = include_str!("../shaders/tile_ranges.wgsl");
const FILL: &str = include_str!("../shaders/fill.wgsl");

/// Slots of the `sizes` buffer.
pub const SLOT_PAIRS_TOTAL: u32 = 0;
pub const SLOT_PAIRS: u32 = 1;
pub const SLOT_PAIR_HIST: u32 = 2;
pub const SIZES_LEN: u32 = 4;

/// Byte offsets of the indirect arguments written by `pair_args.wgsl`.
const ARGS_SORT: u64 = 0;
const ARGS_HIST_SCAN: u64 = 16;
const ARGS_PAIRS: u64 = 32;

/// What the binning leaves for the rasterizer.
pub struct Bins {
    pub steps: Vec<Step>,
    /// Tile ranges `vec2<u32>` per tile.
    pub ranges: wgpu::Buffer,
    /// Gaussian ids of the tile-sorted pairs (which buffer depends on the pass count).
    pub pair_vals: wgpu::Buffer,
    /// `sizes[SLOT_PAIRS_TOTAL]` is the frame's pair count before clamping to the capacity.
    pub sizes: wgpu::Buffer,
    pub capacity: usize,
    /// Gaussian ids in depth order (culled ones last).
    pub depth_vals: wgpu::Buffer,
    /// Per depth rank: tiles covered, and where its pairs start before the sort by tile (the
    /// backward finds each pair's slot from them).
    pub counts: wgpu::Buffer,
    pub offsets: wgpu::Buffer,
}

/// Builds the binning for `n` Gaussians, a `grid_x x grid_y` tile grid and room for
/// `capacity` pairs.
pub fn build(
    gpu: &Gpu,
    tuning: &Tuning,
    proj: &Projected,
    n: usize,
    grid_x: usize,
    grid_y: usize,
    capacity: usize,
) -> Result<Bins> {
    let tiles = grid_x * grid_y;
    let n32 = n as u32;
    let mut steps = Vec::new();
    let sizes = gpu.buffer("splat sizes", 4 * SIZES_LEN as u64);
    let args = gpu.buffer("splat args", 48);

    // Depth sort of all Gaussians (culled ones carry the largest key and come last).
    let depth = RadixSort::new(
        gpu,
        tuning,
        &proj.keys,
        &proj.vals,
        32,
        &sizes,
        &Count::fixed(n32),
        NO_SLOT,
        None,
    )?;
    steps.extend(depth.steps.iter().cloned());
    let (dkeys, dvals) = depth.result(&proj.keys, &proj.vals);

    // Tiles per sorted Gaussian, their exclusive scan (total -> SLOT_PAIRS_TOTAL), the pairs.
    let counts = gpu.buffer("pair counts", 4 * n as u64);
    let offsets = gpu.buffer("pair offsets", 4 * n as u64);
    let kc = gpu.kernel(
        "pair_count",
        PAIR_COUNT,
        &[],
        &[
            Bind::Uniform,
            Bind::Read,
            Bind::Read,
            Bind::Read,
            Bind::ReadWrite,
        ],
    )?;
    let pn = gpu.uniform("pair n", &Params::new().u(n32));
    steps.push(Step::new(
        kc.clone(),
        gpu.bind(&kc, &[&pn, dkeys, dvals, &proj.rects, &counts])?,
        linear_grid(n, 256),
    ));
    steps.extend(scan_steps(
        gpu,
        tuning,
        &counts,
        &offsets,
        &sizes,
        &Count::fixed(n32),
        SLOT_PAIRS_TOTAL,
    )?);
    let cap = capacity.max(1);
    let pair_keys = gpu.buffer("pair keys", 4 * cap as u64);
    let pair_vals = gpu.buffer("pair vals", 4 * cap as u64);
    let ke = gpu.kernel(
        "pair_emit",
        PAIR_EMIT,
        &[],
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
    let pe = gpu.uniform(
        "pair emit",
        &Params::new().u(n32).u(cap as u32).u(grid_x as u32),
    );
    steps.push(Step::new(
        ke.clone(),
        gpu.bind(
            &ke,
            &[
                &pe,
                dkeys,
                dvals,
                &proj.rects,
                &offsets,
                &pair_keys,
                &pair_vals,
            ],
        )?,
        linear_grid(n, 256),
    ));

    // This frame's pair count and the grids of the kernels over pairs.
    let radix = 1u32 << tuning.radix_bits;
    let ka = gpu.kernel(
        "pair_args",
        PAIR_ARGS,
        &[],
        &[Bind::Uniform, Bind::ReadWrite, Bind::ReadWrite],
    )?;
    let pa = gpu.uniform(
        "pair args",
        &Params::new()
            .u(cap as u32)
            .u(SLOT_PAIRS_TOTAL)
            .u(SLOT_PAIRS)
            .u(SLOT_PAIR_HIST)
            .u(radix_block(tuning))
            .u(256 * tuning.scan_items)
            .u(radix),
    );
    steps.push(Step::new(
        ka.clone(),
        gpu.bind(&ka, &[&pa, &sizes, &args])?,
        Grid::Fixed([1, 1, 1]),
    ));

    // Stable sort of the pairs by tile.
    let tile_bits = (usize::BITS - (tiles.max(2) - 1).leading_zeros()).max(1);
    let pair_count = Count {
        fixed: 0,
        slot: SLOT_PAIRS,
        capacity: cap as u32,
        grid: Some(Grid::Indirect(args.clone(), ARGS_SORT)),
    };
    let tile_sort = RadixSort::new(
        gpu,
        tuning,
        &pair_keys,
        &pair_vals,
        tile_bits,
        &sizes,
        &pair_count,
        SLOT_PAIR_HIST,
        Some(Grid::Indirect(args.clone(), ARGS_HIST_SCAN)),
    )?;
    steps.extend(tile_sort.steps.iter().cloned());
    let (tkeys, tvals) = tile_sort.result(&pair_keys, &pair_vals);

    // Tile ranges: cleared, then set from the sorted keys.
    let ranges = gpu.buffer("tile ranges", 8 * tiles as u64);
    let kf = gpu.kernel("fill", FILL, &[], &[Bind::Uniform, Bind::ReadWrite])?;
    let pf = gpu.uniform("fill ranges", &Params::new().u(2 * tiles as u32).u(0));
    steps.push(Step::new(
        kf.clone(),
        gpu.bind(&kf, &[&pf, &ranges])?,
        linear_grid(2 * tiles, 256),
    ));
    let kr = gpu.kernel(
        "tile_ranges",
        TILE_RANGES,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let pr = gpu.uniform("tile ranges", &Params::new().u(SLOT_PAIRS));
    steps.push(Step::new(
        kr.clone(),
        gpu.bind(&kr, &[&pr, &sizes, tkeys, &ranges])?,
        Grid::Indirect(args.clone(), ARGS_PAIRS),
    ));
    Ok(Bins {
        steps,
        ranges,
        pair_vals: tvals.clone(),
        sizes,
        capacity: cap,
        depth_vals: dvals.clone(),
        counts,
        offsets,
    })
}
