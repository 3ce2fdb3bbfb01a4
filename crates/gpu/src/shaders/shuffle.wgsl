// The rest of a transposed convolution whose stride equals its kernel (DPT's resize layers):
// the 1x1 product [Cout K K, G, G] spread into [Cout, G K, G K] plus the bias. One thread per
// output value.

struct P {
    c: u32,
    g: u32,
    k: u32,
    in_off: u32,
    out_off: u32,
    bias_off: u32,
    _p0: u32,
    _p1: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read> vecs: array<f32>;
@group(0) @binding(3) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    let side = p.g * p.k;
    if (i >= p.c * side * side) {
        return;
    }
    let co = i / (side * side);
    let oy = (i / side) % side;
    let ox = i % side;
    let tap = (oy % p.k) * p.k + ox % p.k;
    let src = ((co * p.k * p.k + tap) * p.g + oy / p.k) * p.g + ox / p.k;
    y[p.out_off + i] = x[p.in_off + src] + vecs[p.bias_off + co];
}
