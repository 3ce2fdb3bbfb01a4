// The gradient of rms_norm.wgsl, y = x / d with d = sqrt(mean(x^2) + 1e-8):
// dx_i = dy_i / d - x_i sum_j(dy_j x_j) / (n d^3). One workgroup.

struct P {
    n: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read> dy: array<f32>;
@group(0) @binding(3) var<storage, read_write> dx: array<f32>;

var<workgroup> sq: array<f32, 256>;
var<workgroup> dot: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32) {
    var s = 0.0;
    var q = 0.0;
    for (var i = t; i < p.n; i = i + 256u) {
        s = s + x[i] * x[i];
        q = q + dy[i] * x[i];
    }
    sq[t] = s;
    dot[t] = q;
    workgroupBarrier();
    for (var w = 128u; w > 0u; w = w >> 1u) {
        if (t < w) {
            sq[t] = sq[t] + sq[t + w];
            dot[t] = dot[t] + dot[t + w];
        }
        workgroupBarrier();
    }
    let d = sqrt(sq[0] / f32(p.n) + 1e-8);
    let c = dot[0] / (f32(p.n) * d * d * d);
    for (var i = t; i < p.n; i = i + 256u) {
        dx[i] = dy[i] / d - x[i] * c;
    }
}
