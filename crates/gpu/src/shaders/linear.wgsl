// y[o] = sum_i W[o, i] x[i stride] + b[o] (optionally leaky ReLU), one workgroup per output
// row: the renderer's style code, mapping network and the stacked style modulations, and the
// expression generator's identity row (x: a column of a channel-major activation).

struct P {
    n_in: u32,
    n_out: u32,
    x_off: u32,
    y_off: u32,
    lrelu: u32,
    x_stride: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
// [n_out, n_in]
@group(0) @binding(2) var<storage, read> wt: array<f32>;
@group(0) @binding(3) var<storage, read> bias: array<f32>;
@group(0) @binding(4) var<storage, read_write> y: array<f32>;

var<workgroup> part: array<f32, 64>;

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let o = wid.y * 65535u + wid.x;
    if (o >= p.n_out) {
        return;
    }
    var s = 0.0;
    for (var i = t; i < p.n_in; i = i + 64u) {
        s = fma(wt[o * p.n_in + i], x[p.x_off + i * p.x_stride], s);
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
        var v = part[0] + bias[o];
        if (p.lrelu != 0u) {
            v = lrelu(v);
        }
        y[p.y_off + o] = v;
    }
}
