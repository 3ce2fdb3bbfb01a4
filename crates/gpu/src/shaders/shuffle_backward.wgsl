// The backward of shuffle.wgsl: the gradient of the 1x1 product [C K K, G, G] from the spread
// output's [C, G K, G K] (each product value went to exactly one output value). The bias's
// gradient is the output gradient's row sums (row_sum.wgsl). One thread per product value.

struct P {
    c: u32,
    g: u32,
    k: u32,
    dy_off: u32,
    dx_off: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> dy: array<f32>;
@group(0) @binding(2) var<storage, read_write> dx: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    let kk = p.k * p.k;
    if (i >= p.c * kk * p.g * p.g) {
        return;
    }
    let row = i / (p.g * p.g);
    let co = row / kk;
    let tap = row % kk;
    let gy = (i / p.g) % p.g;
    let gx = i % p.g;
    let side = p.g * p.k;
    let oy = gy * p.k + tap / p.k;
    let ox = gx * p.k + tap % p.k;
    dx[p.dx_off + i] = dy[p.dy_off + (co * side + oy) * side + ox];
}
