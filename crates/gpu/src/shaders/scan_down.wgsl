// Exclusive scan, step 3 of 3: each block scans its values and adds its block offset.

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
@group(0) @binding(2) var<storage, read> sums: array<u32>;
@group(0) @binding(3) var<storage, read> data: array<u32>;
@group(0) @binding(4) var<storage, read_write> out: array<u32>;

var<workgroup> part: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    var n = p.n;
    if (p.size_at != 0xffffffffu) {
        n = sizes[p.size_at];
    }
    let base = wid.x * BLOCK + t * ITEMS;
    var v: array<u32, ITEMS>;
    var s = 0u;
    for (var i = 0u; i < ITEMS; i = i + 1u) {
        var x = 0u;
        if (base + i < n) {
            x = data[base + i];
        }
        v[i] = s;
        s = s + x;
    }
    part[t] = s;
    workgroupBarrier();
    for (var w = 1u; w < 256u; w = w << 1u) {
        var add = 0u;
        if (t >= w) {
            add = part[t - w];
        }
        workgroupBarrier();
        part[t] = part[t] + add;
        workgroupBarrier();
    }
    var before = sums[wid.x];
    if (t > 0u) {
        before = before + part[t - 1u];
    }
    for (var i = 0u; i < ITEMS; i = i + 1u) {
        if (base + i < n) {
            out[base + i] = before + v[i];
        }
    }
}
