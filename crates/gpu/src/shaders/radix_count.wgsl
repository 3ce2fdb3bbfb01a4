// Stable LSD radix sort, pass step 1 of 3: each block's histogram of the digit at `shift`,
// stored digit-major (`hist[d * blocks + b]`) so that one exclusive scan gives every
// (digit, block) its first output position.

struct P {
    shift: u32,
    n: u32,
    size_at: u32,
    _p0: u32,
}

const ITEMS: u32 = {{ITEMS}}u;
const BLOCK: u32 = 256u * ITEMS;
const RADIX: u32 = {{RADIX}}u;

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> sizes: array<u32>;
@group(0) @binding(2) var<storage, read> keys: array<u32>;
@group(0) @binding(3) var<storage, read_write> hist: array<u32>;

var<workgroup> counts: array<atomic<u32>, RADIX>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    var n = p.n;
    if (p.size_at != 0xffffffffu) {
        n = sizes[p.size_at];
    }
    let blocks = (n + BLOCK - 1u) / BLOCK;
    for (var d = t; d < RADIX; d = d + 256u) {
        atomicStore(&counts[d], 0u);
    }
    workgroupBarrier();
    let base = wid.x * BLOCK + t * ITEMS;
    for (var i = 0u; i < ITEMS; i = i + 1u) {
        if (base + i < n) {
            let d = (keys[base + i] >> p.shift) & (RADIX - 1u);
            atomicAdd(&counts[d], 1u);
        }
    }
    workgroupBarrier();
    for (var d = t; d < RADIX; d = d + 256u) {
        hist[d * blocks + wid.x] = atomicLoad(&counts[d]);
    }
}
