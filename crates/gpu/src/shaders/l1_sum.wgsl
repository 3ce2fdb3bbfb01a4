// `scale * sum |a - b|` over n values into out[slot], by one workgroup in a fixed order (each
// thread a strided partial sum, then a tree): the training losses' L1 values.

struct P {
    n: u32,
    a_off: u32,
    b_off: u32,
    slot: u32,
    scale: f32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;

var<workgroup> part: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32) {
    var s = 0.0;
    for (var i = t; i < p.n; i = i + 256u) {
        s = s + abs(a[p.a_off + i] - b[p.b_off + i]);
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
        out[p.slot] = p.scale * part[0];
    }
}
