// Splatting step 3: per depth-sorted Gaussian, the number of tiles its rectangle covers.

struct P {
    n: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> keys: array<u32>;
@group(0) @binding(2) var<storage, read> vals: array<u32>;
@group(0) @binding(3) var<storage, read> rects: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = lin(gid, 256u);
    if (r >= p.n) {
        return;
    }
    var c = 0u;
    if (keys[r] != 0xffffffffu) {
        let rc = rects[vals[r]];
        c = ((rc.x >> 16u) - (rc.x & 0xffffu)) * ((rc.y >> 16u) - (rc.y & 0xffffu));
    }
    counts[r] = c;
}
