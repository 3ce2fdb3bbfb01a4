// Bilinear x2 up- or x0.5 downsampling, align_corners=False (PyTorch interpolate), of
// [C, H, W]; for x0.5 each output is the mean of a 2x2 block. One thread per output value.

struct P {
    c: u32,
    h_in: u32,
    w_in: u32,
    in_off: u32,
    out_off: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

const UP: bool = {{UP}};

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

// Source taps and the weight of the second along one axis for output `o` of a x2 upsampling.
fn taps(o: u32, n: u32) -> vec3<f32> {
    let src = max((f32(o) + 0.5) * 0.5 - 0.5, 0.0);
    let i0 = floor(src);
    let i1 = min(i0 + 1.0, f32(n - 1u));
    return vec3<f32>(i0, i1, src - i0);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    var ho = p.h_in / 2u;
    var wo = p.w_in / 2u;
    if (UP) {
        ho = p.h_in * 2u;
        wo = p.w_in * 2u;
    }
    if (i >= p.c * ho * wo) {
        return;
    }
    let c = i / (ho * wo);
    let oy = (i / wo) % ho;
    let ox = i % wo;
    let base = p.in_off + c * p.h_in * p.w_in;
    var v: f32;
    if (UP) {
        let ty = taps(oy, p.h_in);
        let tx = taps(ox, p.w_in);
        let r0 = base + u32(ty.x) * p.w_in;
        let r1 = base + u32(ty.y) * p.w_in;
        let top = x[r0 + u32(tx.x)] * (1.0 - tx.z) + x[r0 + u32(tx.y)] * tx.z;
        let bot = x[r1 + u32(tx.x)] * (1.0 - tx.z) + x[r1 + u32(tx.y)] * tx.z;
        v = top * (1.0 - ty.z) + bot * ty.z;
    } else {
        let r0 = base + 2u * oy * p.w_in + 2u * ox;
        let r1 = r0 + p.w_in;
        v = 0.5 * (0.5 * (x[r0] + x[r0 + 1u]) + 0.5 * (x[r1] + x[r1 + 1u]));
    }
    y[p.out_off + i] = v;
}
