// The ViT's first activation, channel-major [C, G + 1]: the embedded patches (columns 0..G)
// and the class token (column G, last: attention does not depend on the order of tokens),
// each plus its position embedding (`pos` [1 + G, C], row 0 the class token's).

struct P {
    c: u32,
    g: u32,
    cls_off: u32,
    pos_off: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> patches: array<f32>;
// the class token [C] at cls_off and the position embedding at pos_off
@group(0) @binding(2) var<storage, read> emb: array<f32>;
@group(0) @binding(3) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    let n = p.g + 1u;
    if (i >= p.c * n) {
        return;
    }
    let ch = i / n;
    let t = i % n;
    if (t < p.g) {
        y[i] = patches[ch * p.g + t] + emb[p.pos_off + (t + 1u) * p.c + ch];
    } else {
        y[i] = emb[p.cls_off + ch] + emb[p.pos_off + ch];
    }
}
