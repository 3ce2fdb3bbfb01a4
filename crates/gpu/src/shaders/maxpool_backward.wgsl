// The input gradient of maxpool.wgsl: each window's gradient goes to its first maximum in
// row-major order (PyTorch's rule, and the CPU op's); one thread per input value gathers from
// the windows that hold it, finding each window's first maximum again from the forward's input.

struct P {
    c: u32,
    h: u32,
    w: u32,
    k: u32,
    s: u32,
    oh: u32,
    ow: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read> dy: array<f32>;
@group(0) @binding(3) var<storage, read_write> dx: array<f32>;

// Flat offset within the plane of the first maximum of window (oy, ox).
fn first_max(base: u32, oy: u32, ox: u32) -> u32 {
    var at = oy * p.s * p.w + ox * p.s;
    var best = x[base + at];
    for (var ky = 0u; ky < p.k; ky++) {
        for (var kx = 0u; kx < p.k; kx++) {
            let o = (oy * p.s + ky) * p.w + ox * p.s + kx;
            let v = x[base + o];
            if (v > best) {
                best = v;
                at = o;
            }
        }
    }
    return at;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.c * p.h * p.w) {
        return;
    }
    let c = i / (p.h * p.w);
    let y = (i / p.w) % p.h;
    let xx = i % p.w;
    let base = c * p.h * p.w;
    let me = y * p.w + xx;
    // Windows oy with oy s <= y < oy s + k.
    let oy0 = select(0u, (y + 1u - p.k + p.s - 1u) / p.s, y + 1u > p.k);
    let ox0 = select(0u, (xx + 1u - p.k + p.s - 1u) / p.s, xx + 1u > p.k);
    var g = 0.0;
    for (var oy = oy0; oy <= y / p.s && oy < p.oh; oy++) {
        for (var ox = ox0; ox <= xx / p.s && ox < p.ow; ox++) {
            if (first_max(base, oy, ox) == me) {
                g = g + dy[(c * p.oh + oy) * p.ow + ox];
            }
        }
    }
    dx[i] = g;
}
