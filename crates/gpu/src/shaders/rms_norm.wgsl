// The mapping network's input normalisation: y = x / sqrt(mean(x^2) + 1e-8), one workgroup.

struct P {
    n: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

var<workgroup> part: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32) {
    var s = 0.0;
    for (var i = t; i < p.n; i = i + 256u) {
        s = s + x[i] * x[i];
    }
    part[t] = s;
    workgroupBarrier();
    for (var w = 128u; w > 0u; w = w >> 1u) {
        if (t < w) {
            part[t] = part[t] + part[t + w];
        }
        workgroupBarrier();
    }
    let d = sqrt(part[0] / f32(p.n) + 1e-8);
    for (var i = t; i < p.n; i = i + 256u) {
        y[i] = x[i] / d;
    }
}
