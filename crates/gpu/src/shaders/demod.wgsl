// A modulated convolution's output factor: gain / sqrt(sum_i style[i]^2 E[o, i] + 1e-8),
// with E[o, i] the energy of the weight's kernel (o, i). One workgroup per output channel.

struct P {
    cin: u32,
    cout: u32,
    style_off: u32,
    out_off: u32,
    gain: f32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
// [cout, cin]
@group(0) @binding(1) var<storage, read> energy: array<f32>;
@group(0) @binding(2) var<storage, read_write> vecs: array<f32>;

var<workgroup> part: array<f32, 64>;

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let o = wid.x;
    var s = 0.0;
    for (var i = t; i < p.cin; i = i + 64u) {
        let st = vecs[p.style_off + i];
        s = fma(st * st, energy[o * p.cin + i], s);
    }
    part[t] = s;
    workgroupBarrier();
    for (var w = 32u; w > 0u; w = w >> 1u) {
        if (t < w) {
            part[t] = part[t] + part[t + w];
        }
        workgroupBarrier();
    }
    if (t == 0u) {
        vecs[p.out_off + o] = (1.0 / sqrt(part[0] + 1e-8)) * p.gain;
    }
}
