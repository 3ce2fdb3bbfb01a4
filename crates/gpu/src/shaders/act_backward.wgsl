// The gradient through an activation, dZ = dY * act'(.), one thread per value, from the value
// the backward keeps: the activation's output for leaky ReLU (0.2) and ReLU (whose sign is the
// input's; 0 counts as negative, PyTorch's rule) and for the sigmoid, its input for GELU (erf).

// 1 leaky ReLU (0.2), 2 ReLU, 3 GELU, 4 sigmoid
const ACT: u32 = {{ACT}}u;

struct P {
    n: u32,
    kept_off: u32,
    dy_off: u32,
    out_off: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> kept: array<f32>;
@group(0) @binding(2) var<storage, read> dy: array<f32>;
@group(0) @binding(3) var<storage, read_write> dz: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    let v = kept[p.kept_off + i];
    let g = dy[p.dy_off + i];
    var d = 0.0;
    if (ACT == 1u) {
        d = select(0.2, 1.0, v > 0.0);
    } else if (ACT == 2u) {
        d = select(0.0, 1.0, v > 0.0);
    } else if (ACT == 4u) {
        d = v * (1.0 - v);
    } else {
        // d/dv [v Phi(v)] = Phi(v) + v phi(v), Phi through the forward's erf.
        let cdf = 0.5 * (1.0 + erf_as(v * 0.70710678118654752));
        d = cdf + v * 0.3989422804014327 * exp(-0.5 * v * v);
    }
    dz[p.out_off + i] = g * d;
}
