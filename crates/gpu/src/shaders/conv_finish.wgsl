// Split-K convolution, second step: sums the partial results of the depth slices and applies
// the epilogue of conv.wgsl. One thread per output value.

@group(0) @binding(0) var<uniform> p: P;
// [slices, cout, H, W]
@group(0) @binding(1) var<storage, read> part: array<f32>;
@group(0) @binding(2) var<storage, read> vecs: array<f32>;
@group(0) @binding(3) var<storage, read> aux: array<f32>;
@group(0) @binding(4) var<storage, read> sft: array<f32>;
@group(0) @binding(5) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let hw = p.h * p.w;
    let i = lin(gid, 256u);
    if (i >= p.cout * hw) {
        return;
    }
    let co = i / hw;
    let pix = i % hw;
    var v = 0.0;
    for (var s = 0u; s < p.slices; s = s + 1u) {
        v = v + part[s * p.cout * hw + i];
    }
    y[p.out_off + i] = epilogue(v, co, pix, hw);
}
