// Split-K convolution, second step: sums the partial results of the depth slices and applies
// the epilogue of conv.wgsl. One thread per output value.

struct P {
    cin: u32,
    cout: u32,
    h: u32,
    w: u32,
    in_off: u32,
    out_off: u32,
    bias_off: u32,
    insc_off: u32,
    outsc_off: u32,
    aux_off: u32,
    sft_scale_off: u32,
    sft_shift_off: u32,
    noise_w: f32,
    slices: u32,
    _p1: u32,
    _p2: u32,
}

const OUT_SCALE: bool = {{OUT_SCALE}};
const BIAS: bool = {{BIAS}};
const NOISE: bool = {{NOISE}};
const LRELU: bool = {{LRELU}};
const RESID: bool = {{RESID}};
const SFT: bool = {{SFT}};
const SIGMOID: bool = {{SIGMOID}};

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
