// A modulated convolution's kernel energies E[co, ci] = sum_tap W[co, ci, tap]^2, recomputed on
// the device after each update of a trained weight. One thread per (co, ci).

struct P {
    n: u32,
    taps: u32,
    _p0: u32,
    _p1: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> w: array<f32>;
@group(0) @binding(2) var<storage, read_write> e: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    var s = 0.0;
    for (var t = 0u; t < p.taps; t = t + 1u) {
        let v = w[i * p.taps + t];
        s = s + v * v;
    }
    e[i] = s;
}
