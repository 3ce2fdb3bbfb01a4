// Bilinear resizing of [C, H, W] to [C, OH, OW] with align_corners=True (DPT's fusion blocks):
// source = o (in - 1) / (out - 1). One thread per output value.

struct P {
    c: u32,
    h: u32,
    w: u32,
    oh: u32,
    ow: u32,
    in_off: u32,
    out_off: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

// The two source taps and the second one's weight along one axis.
fn taps(o: u32, n_in: u32, n_out: u32) -> vec3<f32> {
    var src = 0.0;
    if (n_out > 1u) {
        src = f32(o) * f32(n_in - 1u) / f32(n_out - 1u);
    }
    let i0 = min(floor(src), f32(n_in - 1u));
    let i1 = min(i0 + 1.0, f32(n_in - 1u));
    return vec3<f32>(i0, i1, src - i0);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.c * p.oh * p.ow) {
        return;
    }
    let ch = i / (p.oh * p.ow);
    let ty = taps((i / p.ow) % p.oh, p.h, p.oh);
    let tx = taps(i % p.ow, p.w, p.ow);
    let base = p.in_off + ch * p.h * p.w;
    let r0 = base + u32(ty.x) * p.w;
    let r1 = base + u32(ty.y) * p.w;
    let top = x[r0 + u32(tx.x)] * (1.0 - tx.z) + x[r0 + u32(tx.y)] * tx.z;
    let bottom = x[r1 + u32(tx.x)] * (1.0 - tx.z) + x[r1 + u32(tx.y)] * tx.z;
    y[p.out_off + i] = top * (1.0 - ty.z) + bottom * ty.z;
}
