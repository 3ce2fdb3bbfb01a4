// Helpers shared by every kernel (prepended to each source).

// The flat index of a thread of a `linear_grid` dispatch with workgroups of `wg` threads.
fn lin(gid: vec3<u32>, wg: u32) -> u32 {
    return gid.y * (32768u * wg) + gid.x;
}

// Leaky ReLU with slope 0.2, as `max(v, 0.2 v)` (the CPU path's expression).
fn lrelu(v: f32) -> f32 {
    return max(v, 0.2 * v);
}

// erf from Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7), the formula of the CPU path's ViT (and
// PyTorch's vectorised CPU erf).
fn erf_as(x: f32) -> f32 {
    let z = abs(x);
    let t = 1.0 / (1.0 + 0.3275911 * z);
    let poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))));
    let e = 1.0 - poly * exp(-z * z);
    return select(e, -e, x < 0.0);
}

// GELU with erf, `v (1 + erf(v / sqrt 2)) / 2`.
fn gelu_erf(v: f32) -> f32 {
    return 0.5 * v * (1.0 + erf_as(v * 0.70710678118654752));
}

// The CPU splatting's exp (gagavatar_splat::real::exp_f32), operation for operation: Cody-Waite
// range reduction, a degree-7 polynomial in Horner form with fused multiply-adds, 2^k from the
// exponent bits. Where the device fuses as the CPU does, the results are bit-identical.
fn exp_splat(x_in: f32) -> f32 {
    let x = min(max(x_in, -87.0), 88.0);
    let round = 12582912.0;
    let shifted = fma(x, 1.44269504088896341, round);
    // k = shifted - round, the integer the rounding trick produced, read from the bits: a
    // compiler may legally fold `(a + round) - round` to `a` and lose the rounding.
    let kbits = bitcast<u32>(shifted) - bitcast<u32>(round);
    let k = f32(bitcast<i32>(kbits));
    var r = fma(k, -0.693359375, x);
    r = fma(k, 2.12194440e-4, r);
    var p = 1.9875692e-4;
    p = fma(p, r, 1.3982e-3);
    p = fma(p, r, 8.333452e-3);
    p = fma(p, r, 4.1665796e-2);
    p = fma(p, r, 1.6666665e-1);
    p = fma(p, r, 0.5);
    p = fma(p, r, 1.0);
    p = fma(p, r, 1.0);
    let scale = bitcast<f32>((kbits + 127u) << 23u);
    return p * scale;
}

// sin and cos of x >= 0 to about one ulp (Cody-Waite reduction by pi/4 in three parts and the
// Cephes single-precision polynomials): the device's own sin/cos may be far less accurate
// (Vulkan allows an absolute error of 2^-11).
fn sin_cos(x: f32) -> vec2<f32> {
    var j = u32(x * 1.27323954473516);
    var y = f32(j);
    if ((j & 1u) == 1u) {
        j = j + 1u;
        y = y + 1.0;
    }
    j = j & 7u;
    var ssign = 1.0;
    var csign = 1.0;
    if (j > 3u) {
        j = j - 4u;
        ssign = -ssign;
        csign = -csign;
    }
    if (j > 1u) {
        csign = -csign;
    }
    let z = ((x - y * 0.78515625) - y * 2.4187564849853515625e-4) - y * 3.77489497744594108e-8;
    let zz = z * z;
    let sp = ((-1.9515295891e-4 * zz + 8.3321608736e-3) * zz - 1.6666654611e-1) * zz * z + z;
    let cp = ((2.443315711809948e-5 * zz - 1.388731625493765e-3) * zz + 4.166664568298827e-2) * zz * zz - 0.5 * zz + 1.0;
    var s = sp;
    var c = cp;
    if (j == 1u || j == 2u) {
        s = cp;
        c = sp;
    }
    return vec2<f32>(ssign * s, csign * c);
}
