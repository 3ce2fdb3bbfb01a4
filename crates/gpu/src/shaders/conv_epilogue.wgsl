// The fused epilogue of one convolution output, in the CPU path's order. It is appended to
// conv.wgsl, conv_mma.wgsl and conv_finish.wgsl and reads their flags, parameters and buffers.
fn epilogue(acc: f32, co: u32, pix: u32, hw: u32) -> f32 {
    var v = acc;
    if (OUT_SCALE) {
        v = v * vecs[p.outsc_off + co];
    }
    if (BIAS) {
        v = v + vecs[p.bias_off + co];
    }
    if (NOISE) {
        v = v + p.noise_w * aux[p.aux_off + pix];
    }
    if (LRELU) {
        v = lrelu(v);
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
