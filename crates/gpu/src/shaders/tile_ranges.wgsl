// Splatting step 7: each tile's range [start, end) in the tile-sorted pairs (ranges were
// cleared to zero before).

struct P {
    count_at: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> sizes: array<u32>;
@group(0) @binding(2) var<storage, read> pair_keys: array<u32>;
@group(0) @binding(3) var<storage, read_write> ranges: array<vec2<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    let n = sizes[p.count_at];
    if (i >= n) {
        return;
    }
    let t = pair_keys[i];
    if (i == 0u || pair_keys[i - 1u] != t) {
        ranges[t].x = i;
    }
    if (i + 1u == n || pair_keys[i + 1u] != t) {
        ranges[t].y = i + 1u;
    }
}
