// The transpose of im2col.wgsl: the input gradient `[c, h, w]` of a `k x k`, `stride`, `pad`
// convolution from the gradient of its patch matrix `[c k k, oh ow]`. One thread per input
// value gathers the patch entries that read it.

struct P {
    c: u32,
    h: u32,
    w: u32,
    k: u32,
    stride: u32,
    pad: u32,
    oh: u32,
    ow: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> cols: array<f32>;
@group(0) @binding(2) var<storage, read_write> dx: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.c * p.h * p.w) {
        return;
    }
    let ci = i / (p.h * p.w);
    let y = i32((i / p.w) % p.h) + i32(p.pad);
    let x = i32(i % p.w) + i32(p.pad);
    let n = p.oh * p.ow;
    var g = 0.0;
    for (var ky = 0u; ky < p.k; ky++) {
        let ty = y - i32(ky);
        if (ty < 0 || ty % i32(p.stride) != 0 || ty / i32(p.stride) >= i32(p.oh)) {
            continue;
        }
        for (var kx = 0u; kx < p.k; kx++) {
            let tx = x - i32(kx);
            if (tx < 0 || tx % i32(p.stride) != 0 || tx / i32(p.stride) >= i32(p.ow)) {
                continue;
            }
            let col = u32(ty / i32(p.stride)) * p.ow + u32(tx / i32(p.stride));
            g = g + cols[((ci * p.k + ky) * p.k + kx) * n + col];
        }
    }
    dx[i] = g;
}
