// The expression generator's rotations (spec 5, a release quirk): each of the four quaternion
// components L2-normalised across the M Gaussians (dim 1 of [B, M, 4]), not across the
// quaternion. One workgroup: per component a strided sum of squares, a tree reduction, then
// every thread writes its share.

const NORMALIZE_EPS: f32 = 1e-12;
const WG: u32 = 256u;

struct P {
    m: u32,
    g0: u32,
    // the first rotation row of the raw output [C + 8, M]
    in_off: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> rotations: array<f32>;

var<workgroup> part: array<f32, WG>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32) {
    for (var k = 0u; k < 4u; k = k + 1u) {
        let row = p.in_off + k * p.m;
        var s = 0.0;
        for (var i = t; i < p.m; i = i + WG) {
            let v = x[row + i];
            s = fma(v, v, s);
        }
        part[t] = s;
        workgroupBarrier();
        for (var w = WG / 2u; w > 0u; w = w >> 1u) {
            if (t < w) {
                part[t] = part[t] + part[t + w];
            }
            workgroupBarrier();
        }
        let inv = 1.0 / max(sqrt(part[0]), NORMALIZE_EPS);
        workgroupBarrier();
        for (var i = t; i < p.m; i = i + WG) {
            rotations[(p.g0 + i) * 4u + k] = x[row + i] * inv;
        }
    }
}
