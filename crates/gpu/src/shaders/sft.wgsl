// SFT, y = x * scale + shift over [C, H, W] (scale and shift in one buffer, the shift `n`
// values after the scale), and its gradients: MODE 0 the forward; MODE 1, from dY, the
// gradients dx = dY scale, dscale = dY x and dshift = dY (the last two in one buffer, as the
// maps are laid out). One thread per value.

const MODE: u32 = {{MODE}}u;

struct P {
    n: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
// [2n]: scale, then shift
@group(0) @binding(2) var<storage, read> maps: array<f32>;
// MODE 1: dY
@group(0) @binding(3) var<storage, read> dy: array<f32>;
// MODE 0: y; MODE 1: dx
@group(0) @binding(4) var<storage, read_write> out: array<f32>;
// MODE 1: [2n] dscale, then dshift
@group(0) @binding(5) var<storage, read_write> dmaps: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    if (MODE == 0u) {
        out[i] = x[i] * maps[i] + maps[p.n + i];
    } else {
        let g = dy[i];
        out[i] = g * maps[i];
        dmaps[i] = g * x[i];
        dmaps[p.n + i] = g;
    }
}
