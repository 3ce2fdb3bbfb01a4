// The weight and style gradients of a modulated convolution
//   y[co] = d[co] conv(x * s, W)[co] + ...,  d[co] = gain / sqrt(sum_ci s[ci]^2 E[co, ci] + 1e-8),
//   E[co, ci] = sum_tap W[co, ci, tap]^2 (without demodulation d = gain, a constant),
// from G = conv_wgrad(x, dZ), the weight gradient of the plain convolution of x (dZ: the
// gradient of y before the activation). With dd[co] = sum_{ci,tap} W s[ci] G and
// c[co] = d(loss)/d(norm2[co]) = -dd[co] d[co]^3 / (2 gain^2):
//   MODE 0, one workgroup per co:  c[co] (0 without demodulation)
//   MODE 1, one thread per weight: dW = d[co] s[ci] G + 2 c[co] s[ci]^2 W
//   MODE 2, one workgroup per ci:  ds[ci] = sum_{co,tap} d[co] G W + 2 s[ci] sum_co c[co] E[co, ci]

const MODE: u32 = {{MODE}}u;
const DEMOD: bool = {{DEMOD}};
const ACCUMULATE: bool = {{ACCUMULATE}};

struct P {
    cin: u32,
    cout: u32,
    taps: u32,
    // offsets into vecs: the style s [cin] and, with demodulation, d [cout]
    style_off: u32,
    demod_off: u32,
    // offset of dW (MODE 1) or ds (MODE 2) in `out`
    out_off: u32,
    gain: f32,
    _p0: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> vecs: array<f32>;
// [cout, cin, taps]
@group(0) @binding(2) var<storage, read> wt: array<f32>;
// G [cout, cin, taps]
@group(0) @binding(3) var<storage, read> g: array<f32>;
// c [cout]: written by MODE 0, read by MODES 1 and 2
@group(0) @binding(4) var<storage, read_write> coef: array<f32>;
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

var<workgroup> part: array<f32, 256>;
var<workgroup> part2: array<f32, 256>;

fn d_of(co: u32) -> f32 {
    if (DEMOD) {
        return vecs[p.demod_off + co];
    }
    return p.gain;
}

fn c_of(co: u32) -> f32 {
    if (DEMOD) {
        return coef[co];
    }
    return 0.0;
}

fn reduce(t: u32) {
    workgroupBarrier();
    for (var w = 128u; w > 0u; w = w >> 1u) {
        if (t < w) {
            part[t] = part[t] + part[t + w];
            part2[t] = part2[t] + part2[t + w];
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(global_invocation_id) gid: vec3<u32>,
        @builtin(local_invocation_index) t: u32) {
    let per = p.cin * p.taps;
    if (MODE == 0u) {
        let co = wid.x;
        var s = 0.0;
        for (var e = t; e < per; e = e + 256u) {
            let i = co * per + e;
            s = s + wt[i] * vecs[p.style_off + e / p.taps] * g[i];
        }
        part[t] = s;
        part2[t] = 0.0;
        reduce(t);
        if (t == 0u && DEMOD) {
            let d = d_of(co);
            coef[co] = -part[0] * d * d * d / (2.0 * p.gain * p.gain);
        }
    } else if (MODE == 1u) {
        let i = lin(gid, 256u);
        if (i >= p.cout * per) {
            return;
        }
        let co = i / per;
        let st = vecs[p.style_off + (i % per) / p.taps];
        var v = d_of(co) * st * g[i] + 2.0 * c_of(co) * st * st * wt[i];
        if (ACCUMULATE) {
            v = out[p.out_off + i] + v;
        }
        out[p.out_off + i] = v;
    } else {
        let ci = wid.x;
        var a = 0.0;
        var b = 0.0;
        for (var e = t; e < p.cout * p.taps; e = e + 256u) {
            let co = e / p.taps;
            let i = (co * p.cin + ci) * p.taps + e % p.taps;
            let w = wt[i];
            a = a + d_of(co) * g[i] * w;
            b = b + c_of(co) * w * w;
        }
        part[t] = a;
        part2[t] = b;
        reduce(t);
        if (t == 0u) {
            var v = part[0] + 2.0 * vecs[p.style_off + ci] * part2[0];
            if (ACCUMULATE) {
                v = out[p.out_off + ci] + v;
            }
            out[p.out_off + ci] = v;
        }
    }
}
