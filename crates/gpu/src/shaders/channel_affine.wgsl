// `out = a[c] x + b[c]` over a 3-channel image (the perceptual networks' input normalisation),
// and with b = 0 its backward; ACC adds to what `out` holds (two networks' input gradients
// summed into one). One thread per value.

const ACC: bool = {{ACC}};

struct P {
    n: u32,
    in_off: u32,
    out_off: u32,
    _p0: u32,
    a: vec4<f32>,
    b: vec4<f32>,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= 3u * p.n) {
        return;
    }
    let c = i / p.n;
    var v = p.a[c] * x[p.in_off + i] + p.b[c];
    if (ACC) {
        v = v + y[p.out_off + i];
    }
    y[p.out_off + i] = v;
}
