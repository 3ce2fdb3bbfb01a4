// The gradient of an L1 loss `scale * sum |pred - target|` with respect to `pred`:
// scale * sign(pred - target), with sign(0) = 0 (PyTorch's rule). One thread per value.

struct P {
    n: u32,
    pred_off: u32,
    target_off: u32,
    out_off: u32,
    scale: f32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> pred: array<f32>;
@group(0) @binding(2) var<storage, read> tgt: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    let d = pred[p.pred_off + i] - tgt[p.target_off + i];
    grad[p.out_off + i] = p.scale * sign(d);
}
