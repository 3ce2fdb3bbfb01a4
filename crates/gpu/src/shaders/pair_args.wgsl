// Splatting step 5 (one thread): the pair count for this frame (clamped to the capacity), the
// sizes the pair sort needs and the workgroup counts of the kernels dispatched over pairs.

struct P {
    capacity: u32,
    total_at: u32,
    count_at: u32,
    hist_at: u32,
    sort_block: u32,
    scan_block: u32,
    radix: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read_write> sizes: array<u32>;
// [sort blocks, 1, 1, 0 | hist scan blocks, 1, 1, 0 | pairs / 256, 1, 1, 0]
@group(0) @binding(2) var<storage, read_write> args: array<u32>;

fn put(at: u32, x: u32) {
    args[at] = x;
    args[at + 1u] = 1u;
    args[at + 2u] = 1u;
    args[at + 3u] = 0u;
}

@compute @workgroup_size(1)
fn main() {
    let n = min(sizes[p.total_at], p.capacity);
    sizes[p.count_at] = n;
    let blocks = (n + p.sort_block - 1u) / p.sort_block;
    let hist = blocks * p.radix;
    sizes[p.hist_at] = hist;
    put(0u, blocks);
    put(4u, (hist + p.scan_block - 1u) / p.scan_block);
    put(8u, (n + 255u) / 256u);
}
