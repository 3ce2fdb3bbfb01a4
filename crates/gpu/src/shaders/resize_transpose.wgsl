// The backward of a separable tap-table resize (resize_taps.wgsl) along one axis: each input
// index gathers its outputs' gradients through the transposed table (CSR: `first[i] ..
// first[i + 1]` entries of output index and weight, built on the host from the forward's
// taps). AXIS_X: g [C, R, S] -> t [C, R, IN] (columns). Otherwise t [C, S, Q] -> rows
// `y0 .. y0 + IN`, columns `x0 .. x0 + Q` of the image gradient [C, H, W], added to it.

const AXIS_X: bool = {{AXIS_X}};

struct P {
    c: u32,
    // AXIS_X: rows of g and t, the output width S, the input width IN. Otherwise: S, Q, IN.
    a: u32,
    s: u32,
    n_in: u32,
    // the image gradient: width, height, the crop's origin
    img_w: u32,
    img_h: u32,
    x0: u32,
    y0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read> first: array<u32>;
@group(0) @binding(3) var<storage, read> ent_o: array<u32>;
@group(0) @binding(4) var<storage, read> ent_w: array<f32>;
@group(0) @binding(5) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let idx = lin(gid, 256u);
    if (AXIS_X) {
        // (ch, r, i) over [C, a, n_in]
        if (idx >= p.c * p.a * p.n_in) {
            return;
        }
        let i = idx % p.n_in;
        let row = idx / p.n_in;
        var v = 0.0;
        for (var k = first[i]; k < first[i + 1u]; k = k + 1u) {
            v = fma(ent_w[k], src[row * p.s + ent_o[k]], v);
        }
        dst[idx] = v;
        return;
    }
    // (ch, i, j) over [C, n_in, a]: rows i of the crop, columns j
    if (idx >= p.c * p.n_in * p.a) {
        return;
    }
    let j = idx % p.a;
    let i = (idx / p.a) % p.n_in;
    let ch = idx / (p.a * p.n_in);
    var v = 0.0;
    for (var k = first[i]; k < first[i + 1u]; k = k + 1u) {
        v = fma(ent_w[k], src[(ch * p.s + ent_o[k]) * p.a + j], v);
    }
    let o = (ch * p.img_h + p.y0 + i) * p.img_w + p.x0 + j;
    dst[o] = dst[o] + v;
}
