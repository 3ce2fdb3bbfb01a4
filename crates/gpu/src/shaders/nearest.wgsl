// The lifting loss's search (gagavatar_train::nearest): for each target point, the nearest
// lifted point by `dx*dx + dy*dy + dz*dz` in f32 in that order, ties to the lowest index, by
// brute force over tiles of 256 lifted points in workgroup memory.

struct P {
    n: u32,
    m: u32,
    _p0: u32,
    _p1: u32,
}

@group(0) @binding(0) var<uniform> p: P;
// [n, 3]
@group(0) @binding(1) var<storage, read> lifted: array<f32>;
// [m, 3]
@group(0) @binding(2) var<storage, read> targets: array<f32>;
@group(0) @binding(3) var<storage, read_write> nn: array<u32>;
@group(0) @binding(4) var<storage, read_write> d2: array<f32>;

var<workgroup> pts: array<vec3<f32>, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let i = (wid.y * 65535u + wid.x) * 256u + t;
    let live = i < p.m;
    var q = vec3<f32>(0.0);
    if (live) {
        q = vec3<f32>(targets[3u * i], targets[3u * i + 1u], targets[3u * i + 2u]);
    }
    var best = bitcast<f32>(0x7f800000u);
    var at = 0xffffffffu;
    for (var start = 0u; start < p.n; start = start + 256u) {
        let k = start + t;
        if (k < p.n) {
            pts[t] = vec3<f32>(lifted[3u * k], lifted[3u * k + 1u], lifted[3u * k + 2u]);
        }
        workgroupBarrier();
        let count = min(256u, p.n - start);
        for (var j = 0u; j < count; j = j + 1u) {
            let c = pts[j];
            let dx = q.x - c.x;
            let dy = q.y - c.y;
            let dz = q.z - c.z;
            let d = dx * dx + dy * dy + dz * dz;
            // Strictly less: the lowest index keeps a tie.
            if (d < best) {
                best = d;
                at = start + j;
            }
        }
        workgroupBarrier();
    }
    if (live) {
        nn[i] = at;
        d2[i] = best;
    }
}
