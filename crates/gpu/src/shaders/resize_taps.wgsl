// Resampling of [C, H, W] to [C, OH, OW] with precomputed tap tables, the CPU path's own
// (`gagavatar_ops::resample::Taps`: per output row / column a first input index and NY / NX
// weights, zero-padded), then optionally the ImageNet normalisation (v - mean[c]) * inv_std[c]:
// the photo's antialiased resizes to the ViT's input and to DPT's level sizes. One thread per
// output value.

const NORMALIZE: bool = {{NORMALIZE}};

struct P {
    c: u32,
    h: u32,
    w: u32,
    oh: u32,
    ow: u32,
    ny: u32,
    nx: u32,
    // offsets into `starts` (row starts, then column starts) and `weights`
    sy_off: u32,
    sx_off: u32,
    wy_off: u32,
    wx_off: u32,
    in_off: u32,
    out_off: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
    mean: vec4<f32>,
    inv_std: vec4<f32>,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read> starts: array<u32>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.c * p.oh * p.ow) {
        return;
    }
    let ch = i / (p.oh * p.ow);
    let oy = (i / p.ow) % p.oh;
    let ox = i % p.ow;
    let y0 = starts[p.sy_off + oy];
    let x0 = starts[p.sx_off + ox];
    let base = p.in_off + ch * p.h * p.w;
    var v = 0.0;
    for (var a = 0u; a < p.ny; a = a + 1u) {
        let wy = weights[p.wy_off + oy * p.ny + a];
        let row = base + (y0 + a) * p.w + x0;
        var r = 0.0;
        for (var b = 0u; b < p.nx; b = b + 1u) {
            r = fma(weights[p.wx_off + ox * p.nx + b], x[row + b], r);
        }
        v = fma(wy, r, v);
    }
    if (NORMALIZE) {
        v = (v - p.mean[ch]) * p.inv_std[ch];
    }
    y[p.out_off + i] = v;
}
