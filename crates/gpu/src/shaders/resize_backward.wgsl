// The gradient of resize.wgsl (bilinear x2 up, align_corners=False, or 2x2 mean down) with
// respect to its input [C, H, W], given the output's gradient: one thread per input value,
// gathering from the outputs that read it with the forward's own weights (no atomics, so the
// sums are reproducible).

struct P {
    c: u32,
    h_in: u32,
    w_in: u32,
    dy_off: u32,
    dx_off: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

const UP: bool = {{UP}};

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> dy: array<f32>;
@group(0) @binding(2) var<storage, read_write> dx: array<f32>;

// The forward's weight of input index `i` in output `o` of a x2 upsampling along an axis of
// `n` inputs (resize.wgsl's `taps`).
fn weight(o: u32, i: u32, n: u32) -> f32 {
    let src = max((f32(o) + 0.5) * 0.5 - 0.5, 0.0);
    let i0 = floor(src);
    let i1 = min(i0 + 1.0, f32(n - 1u));
    let f = src - i0;
    var w = 0.0;
    if (u32(i0) == i) {
        w = w + (1.0 - f);
    }
    if (u32(i1) == i) {
        w = w + f;
    }
    return w;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    let hw = p.h_in * p.w_in;
    if (i >= p.c * hw) {
        return;
    }
    let c = i / hw;
    let iy = (i / p.w_in) % p.h_in;
    let ix = i % p.w_in;
    var v = 0.0;
    if (UP) {
        let ho = 2u * p.h_in;
        let wo = 2u * p.w_in;
        let base = p.dy_off + c * ho * wo;
        // Outputs 2i - 1 .. 2i + 2 read input i (the ends clamp onto the edge inputs).
        let y_lo = max(2 * i32(iy) - 1, 0);
        let y_hi = min(2u * iy + 2u, ho - 1u);
        let x_lo = max(2 * i32(ix) - 1, 0);
        let x_hi = min(2u * ix + 2u, wo - 1u);
        for (var oy = u32(y_lo); oy <= y_hi; oy = oy + 1u) {
            let wy = weight(oy, iy, p.h_in);
            var row = 0.0;
            for (var ox = u32(x_lo); ox <= x_hi; ox = ox + 1u) {
                row = row + weight(ox, ix, p.w_in) * dy[base + oy * wo + ox];
            }
            v = v + wy * row;
        }
    } else {
        let ho = p.h_in / 2u;
        let wo = p.w_in / 2u;
        if (iy / 2u < ho && ix / 2u < wo) {
            v = 0.25 * dy[p.dy_off + c * ho * wo + (iy / 2u) * wo + ix / 2u];
        }
    }
    dx[p.dx_off + i] = v;
}
