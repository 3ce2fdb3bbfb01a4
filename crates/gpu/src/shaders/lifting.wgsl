// The lifting loss `w mean_m |target_m - lifted[nn_m]|^2` and its gradient (nearest.wgsl found
// nn). GRAD: one thread per lifted point, summing `2 w / m (lifted_j - target_m)` over the
// targets that chose it, in target order (no atomics). Otherwise one workgroup sums the
// squared distances in a fixed order into out[0].

const GRAD: bool = {{GRAD}};

struct P {
    n: u32,
    m: u32,
    // w / m
    scale: f32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> lifted: array<f32>;
@group(0) @binding(2) var<storage, read> targets: array<f32>;
@group(0) @binding(3) var<storage, read> nn: array<u32>;
@group(0) @binding(4) var<storage, read> d2: array<f32>;
// [loss, then dL/dlifted (n, 3)]
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

var<workgroup> part: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    if (GRAD) {
        let j = (wid.y * 65535u + wid.x) * 256u + t;
        if (j >= p.n) {
            return;
        }
        let l = vec3<f32>(lifted[3u * j], lifted[3u * j + 1u], lifted[3u * j + 2u]);
        var g = vec3<f32>(0.0);
        for (var k = 0u; k < p.m; k = k + 1u) {
            if (nn[k] == j) {
                let q = vec3<f32>(targets[3u * k], targets[3u * k + 1u], targets[3u * k + 2u]);
                g = g + 2.0 * (l - q);
            }
        }
        out[1u + 3u * j] = p.scale * g.x;
        out[2u + 3u * j] = p.scale * g.y;
        out[3u + 3u * j] = p.scale * g.z;
        return;
    }
    var s = 0.0;
    for (var k = t; k < p.m; k = k + 256u) {
        s = s + d2[k];
    }
    part[t] = s;
    workgroupBarrier();
    for (var half = 128u; half > 0u; half = half / 2u) {
        if (t < half) {
            part[t] = part[t] + part[t + half];
        }
        workgroupBarrier();
    }
    if (t == 0u) {
        out[0] = p.scale * part[0];
    }
}
