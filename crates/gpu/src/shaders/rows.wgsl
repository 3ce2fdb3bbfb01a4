// y[r, c] = a[r, c] + b[r] over a [rows, cols] block, optionally without `a` (a per-row fill)
// and with a ReLU: the expression generator's first layer (vertex term + identity row) and the
// view-direction encoding broadcast over the lifting generators' input.

const HAS_A: bool = {{HAS_A}};
const RELU: bool = {{RELU}};

struct P {
    rows: u32,
    cols: u32,
    a_off: u32,
    b_off: u32,
    out_off: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.rows * p.cols) {
        return;
    }
    var v = b[p.b_off + i / p.cols];
    if (HAS_A) {
        v = a[p.a_off + i] + v;
    }
    if (RELU) {
        v = max(v, 0.0);
    }
    y[p.out_off + i] = v;
}
