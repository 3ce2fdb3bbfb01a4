// Weight (or bias) gradient, second step: adds the `slices` partial sums of each value in slice
// order and writes it, or adds it to what is there (ACCUMULATE: gradients summed over the
// images of a batch). One thread per value.

const ACCUMULATE: bool = {{ACCUMULATE}};

struct P {
    n: u32,
    slices: u32,
    out_off: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
// [slices, n]
@group(0) @binding(1) var<storage, read> part: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    var v = 0.0;
    for (var s = 0u; s < p.slices; s = s + 1u) {
        v = v + part[s * p.n + i];
    }
    if (ACCUMULATE) {
        v = out[p.out_off + i] + v;
    }
    out[p.out_off + i] = v;
}
