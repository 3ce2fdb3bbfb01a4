// Exclusive scan, step 1 of 3: the sum of each block of BLOCK = 256 * ITEMS values.
// The element count is `n` from the uniform, or `sizes[size_at]` when size_at != 0xffffffff
// (a count an earlier kernel of the same frame wrote).

struct P {
    n: u32,
    size_at: u32,
    _p0: u32,
    _p1: u32,
}

const ITEMS: u32 = {{ITEMS}}u;
const BLOCK: u32 = 256u * ITEMS;

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> sizes: array<u32>;
@group(0) @binding(2) var<storage, read> data: array<u32>;
@group(0) @binding(3) var<storage, read_write> sums: array<u32>;

var<workgroup> part: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    var n = p.n;
    if (p.size_at != 0xffffffffu) {
        n = sizes[p.size_at];
    }
    let base = wid.x * BLOCK + t * ITEMS;
    var s = 0u;
    for (var i = 0u; i < ITEMS; i = i + 1u) {
        if (base + i < n) {
            s = s + data[base + i];
        }
    }
    part[t] = s;
    workgroupBarrier();
    for (var w = 128u; w > 0u; w = w >> 1u) {
        if (t < w) {
            part[t] = part[t] + part[t + w];
        }
        workgroupBarrier();
    }
    if (t == 0u) {
        sums[wid.x] = part[0];
    }
}
