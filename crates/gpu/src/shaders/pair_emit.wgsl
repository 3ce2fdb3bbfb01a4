// Splatting step 4: each depth-sorted Gaussian writes (tile, Gaussian) pairs for the tiles
// it covers at its scanned offset, so the pairs come in depth order (ties by index); pairs
// past the capacity are dropped and the frame is redone with more room.

struct P {
    n: u32,
    capacity: u32,
    grid_x: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> keys: array<u32>;
@group(0) @binding(2) var<storage, read> vals: array<u32>;
@group(0) @binding(3) var<storage, read> rects: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> offsets: array<u32>;
@group(0) @binding(5) var<storage, read_write> pair_keys: array<u32>;
@group(0) @binding(6) var<storage, read_write> pair_vals: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = lin(gid, 256u);
    if (r >= p.n || keys[r] == 0xffffffffu) {
        return;
    }
    let g = vals[r];
    let rc = rects[g];
    var at = offsets[r];
    for (var ty = rc.y & 0xffffu; ty < (rc.y >> 16u); ty = ty + 1u) {
        for (var tx = rc.x & 0xffffu; tx < (rc.x >> 16u); tx = tx + 1u) {
            if (at < p.capacity) {
                pair_keys[at] = ty * p.grid_x + tx;
                pair_vals[at] = g;
            }
            at = at + 1u;
        }
    }
}
