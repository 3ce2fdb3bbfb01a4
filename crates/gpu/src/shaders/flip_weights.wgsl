// The weight of a stride-1 convolution's input gradient: W'[ci, co, tap'] = W[co, ci, taps - 1
// - tap'] (input and output channels swapped, kernel rotated by 180 degrees), so that the
// forward kernels compute dX = conv(dZ, W') with the same zero padding. One thread per value.

struct P {
    cin: u32,
    cout: u32,
    taps: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
// [cout, cin, taps]
@group(0) @binding(1) var<storage, read> w: array<f32>;
// [cin, cout, taps]
@group(0) @binding(2) var<storage, read_write> wf: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.cin * p.cout * p.taps) {
        return;
    }
    let tap = i % p.taps;
    let co = (i / p.taps) % p.cout;
    let ci = i / (p.taps * p.cout);
    wf[i] = w[(co * p.cin + ci) * p.taps + p.taps - 1u - tap];
}
