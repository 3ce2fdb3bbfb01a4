// One Adam step of one parameter tensor, torch.optim.Adam's update without weight decay or
// amsgrad (crates/train/src/adam.rs): m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2,
// p -= step_size * m / (sqrt(v) / bc2_sqrt + eps), where the host computes
// step_size = lr / (1 - b1^t) and bc2_sqrt = sqrt(1 - b2^t) in f64. The parameter and its
// gradient sit at `off` in their buffers (shared vector buffers), the moments at 0 in their own.
// One thread per value.

struct P {
    n: u32,
    b1: f32,
    // 1 - b1 and 1 - b2, rounded from f64 as the CPU path's scalars are
    c1: f32,
    b2: f32,
    c2: f32,
    eps: f32,
    step_size: f32,
    bc2_sqrt: f32,
    off: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> g: array<f32>;
@group(0) @binding(2) var<storage, read_write> param: array<f32>;
@group(0) @binding(3) var<storage, read_write> m: array<f32>;
@group(0) @binding(4) var<storage, read_write> v: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    let gi = g[p.off + i];
    let mi = p.b1 * m[i] + p.c1 * gi;
    let vi = p.b2 * v[i] + p.c2 * (gi * gi);
    m[i] = mi;
    v[i] = vi;
    param[p.off + i] = param[p.off + i] - p.step_size * (mi / (sqrt(vi) / p.bc2_sqrt + p.eps));
}
