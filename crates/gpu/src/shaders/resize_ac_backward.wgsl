// The backward of resize_ac.wgsl (bilinear, align_corners=True): the input gradient
// [C, H, W] from the output's [C, OH, OW]. One thread per input value gathers the outputs
// whose taps read it, with the forward's own tap arithmetic, so every value is summed in one
// fixed order (no atomics: the gradient does not depend on scheduling).

struct P {
    c: u32,
    h: u32,
    w: u32,
    oh: u32,
    ow: u32,
    dy_off: u32,
    dx_off: u32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> dy: array<f32>;
@group(0) @binding(2) var<storage, read_write> dx: array<f32>;

// resize_ac.wgsl's taps: the two source indices and the second one's weight.
fn taps(o: u32, n_in: u32, n_out: u32) -> vec3<f32> {
    var src = 0.0;
    if (n_out > 1u) {
        src = f32(o) * f32(n_in - 1u) / f32(n_out - 1u);
    }
    let i0 = min(floor(src), f32(n_in - 1u));
    let i1 = min(i0 + 1.0, f32(n_in - 1u));
    return vec3<f32>(i0, i1, src - i0);
}

// The weight output `o` gives input `i` along one axis (0 when it does not read it).
fn weight(o: u32, i: u32, n_in: u32, n_out: u32) -> f32 {
    let t = taps(o, n_in, n_out);
    var w = 0.0;
    if (u32(t.x) == i) {
        w += 1.0 - t.z;
    }
    if (u32(t.y) == i) {
        w += t.z;
    }
    return w;
}

// The outputs that may read input `i`: those whose source lies in (i - 1, i + 1), widened by
// one on each side for rounding; `weight` decides exactly.
fn span(i: u32, n_in: u32, n_out: u32) -> vec2<u32> {
    if (n_in <= 1u || n_out <= 1u) {
        return vec2<u32>(0u, n_out - 1u);
    }
    var lo = 0u;
    if (i >= 1u) {
        lo = (i - 1u) * (n_out - 1u) / (n_in - 1u);
        if (lo > 0u) {
            lo -= 1u;
        }
    }
    let hi = min(((i + 1u) * (n_out - 1u) + n_in - 2u) / (n_in - 1u) + 1u, n_out - 1u);
    return vec2<u32>(lo, hi);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.c * p.h * p.w) {
        return;
    }
    let ch = i / (p.h * p.w);
    let iy = (i / p.w) % p.h;
    let ix = i % p.w;
    let sy = span(iy, p.h, p.oh);
    let sx = span(ix, p.w, p.ow);
    let base = p.dy_off + ch * p.oh * p.ow;
    var acc = 0.0;
    for (var oy = sy.x; oy <= sy.y; oy++) {
        let wy = weight(oy, iy, p.h, p.oh);
        if (wy == 0.0) {
            continue;
        }
        var row = 0.0;
        for (var ox = sx.x; ox <= sx.y; ox++) {
            let wx = weight(ox, ix, p.w, p.ow);
            if (wx != 0.0) {
                row += wx * dy[base + oy * p.ow + ox];
            }
        }
        acc += wy * row;
    }
    dx[p.dx_off + i] = acc;
}
