// The fused epilogue of one convolution output, in the CPU path's order, with the parameters
// and epilogue flags it reads. It is appended to conv.wgsl, conv_mma.wgsl and conv_finish.wgsl,
// which declare the buffers it reads (`vecs`, `aux`, `sft`) and share this uniform layout
// (`slices` is read by the split-K finish only).

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
    noise_w_off: u32,
    slices: u32,
    _p1: u32,
    _p2: u32,
}

const OUT_SCALE: bool = {{OUT_SCALE}};
const BIAS: bool = {{BIAS}};
const NOISE: bool = {{NOISE}};
// The activation: 0 none, 1 leaky ReLU (0.2), 2 ReLU, 3 GELU (erf).
const ACT: u32 = {{ACT}}u;
const RESID: bool = {{RESID}};
const SFT: bool = {{SFT}};
const SIGMOID: bool = {{SIGMOID}};

fn epilogue(acc: f32, co: u32, pix: u32, hw: u32) -> f32 {
    var v = acc;
    if (OUT_SCALE) {
        v = v * vecs[p.outsc_off + co];
    }
    if (BIAS) {
        v = v + vecs[p.bias_off + co];
    }
    if (NOISE) {
        v = v + vecs[p.noise_w_off] * aux[p.aux_off + pix];
    }
    if (ACT == 1u) {
        v = lrelu(v);
    } else if (ACT == 2u) {
        v = max(v, 0.0);
    } else if (ACT == 3u) {
        v = gelu_erf(v);
    }
    if (RESID) {
        v = v + aux[p.aux_off + co * hw + pix];
    }
    if (SFT) {
        v = v * sft[p.sft_scale_off + co * hw + pix] + sft[p.sft_shift_off + co * hw + pix];
    }
    if (SIGMOID) {
        v = 1.0 / (1.0 + exp(-v));
    }
    return v;
}
