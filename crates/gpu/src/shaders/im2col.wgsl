// The patches of a strided convolution as a matrix: rows (input channel, tap y, tap x), columns
// output pixels, zero outside the image, so that the convolution is a 1x1 one over it (the
// ViT's 14x14 patch embedding, DPT's 3x3 stride-2 resize). One thread per value.

struct P {
    c: u32,
    h: u32,
    w: u32,
    k: u32,
    stride: u32,
    pad: u32,
    oh: u32,
    ow: u32,
    in_off: u32,
    out_off: u32,
    _p0: u32,
    _p1: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    let cols = p.oh * p.ow;
    let rows = p.c * p.k * p.k;
    if (i >= rows * cols) {
        return;
    }
    let row = i / cols;
    let col = i % cols;
    let ci = row / (p.k * p.k);
    let tap = row % (p.k * p.k);
    let yy = i32((col / p.ow) * p.stride + tap / p.k) - i32(p.pad);
    let xx = i32((col % p.ow) * p.stride + tap % p.k) - i32(p.pad);
    var v = 0.0;
    if (yy >= 0 && yy < i32(p.h) && xx >= 0 && xx < i32(p.w)) {
        v = x[p.in_off + (ci * p.h + u32(yy)) * p.w + u32(xx)];
    }
    y[p.out_off + i] = v;
}
