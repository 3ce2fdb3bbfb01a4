// Splatting backward, step 1: per Gaussian, its tile rectangle and where its (tile, Gaussian)
// pairs sat before the sort by tile (pair_emit.wgsl wrote them at its depth rank's scanned
// offset, rectangle row by row): the raster backward writes each pair's sums there, so each
// Gaussian's sit together for splat_grad_sum.wgsl.

struct P {
    n: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> depth_vals: array<u32>;
@group(0) @binding(2) var<storage, read> rects: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> counts: array<u32>;
@group(0) @binding(4) var<storage, read> offsets: array<u32>;
// per Gaussian: packed x range, packed y range, first slot, slots
@group(0) @binding(5) var<storage, read_write> info: array<vec4<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = lin(gid, 256u);
    if (r >= p.n) {
        return;
    }
    let g = depth_vals[r];
    let rc = rects[g];
    info[g] = vec4<u32>(rc.x, rc.y, offsets[r], counts[r]);
}
