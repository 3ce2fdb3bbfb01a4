//! RGB <-> I420 (YUV 4:2:0 planar) with BT.601 limited range: the matrix and range browsers use
//! for H.264 without colour information, and the ones we signal in the SPS anyway.

const KR: f64 = 0.299;
const KB: f64 = 0.114;
const KG: f64 = 1.0 - KR - KB;
/// Limited range: luma spans 16..=235 (219 steps), chroma 16..=240 (224 steps).
const Y_SCALE: f64 = 219.0 / 255.0;
const C_SCALE: f64 = 224.0 / 255.0;

/// 16.16 fixed point keeps the conversion exact to well under one code value and identical on
/// every machine.
const FIX: f64 = 65536.0;
const fn fix(v: f64) -> i32 {
    // `as` rounds toward zero; add half away from zero to round to nearest.
    if v >= 0.0 {
        (v * FIX + 0.5) as i32
    } else {
        (v * FIX - 0.5) as i32
    }
}

const YR: i32 = fix(KR * Y_SCALE);
const YG: i32 = fix(KG * Y_SCALE);
const YB: i32 = fix(KB * Y_SCALE);
const UR: i32 = fix(-KR / (2.0 * (1.0 - KB)) * C_SCALE);
const UG: i32 = fix(-KG / (2.0 * (1.0 - KB)) * C_SCALE);
const UB: i32 = fix(0.5 * C_SCALE);
const VR: i32 = fix(0.5 * C_SCALE);
const VG: i32 = fix(-KG / (2.0 * (1.0 - KR)) * C_SCALE);
const VB: i32 = fix(-KB / (2.0 * (1.0 - KR)) * C_SCALE);
const HALF: i32 = 1 << 15;

/// Width or height rounded up to even: H.264 4:2:0 cannot code odd sizes.
pub(crate) fn even(n: usize) -> usize {
    n + (n & 1)
}

/// Converts `rgb` (`width` x `height`, HWC) to I420 of the even-rounded size in `out`
/// (Y plane, then U, then V; resized as needed). Odd sizes are padded by repeating the last
/// column / row. Chroma is the mean of each 2x2 block.
pub(crate) fn rgb_to_i420(rgb: &[u8], width: usize, height: usize, out: &mut Vec<u8>) {
    let (w2, h2) = (even(width), even(height));
    let (cw, ch) = (w2 / 2, h2 / 2);
    out.resize(w2 * h2 + 2 * cw * ch, 0);
    let (y_plane, uv) = out.split_at_mut(w2 * h2);
    let (u_plane, v_plane) = uv.split_at_mut(cw * ch);
    let px = |x: usize, y: usize| {
        let i = (y.min(height - 1) * width + x.min(width - 1)) * 3;
        (rgb[i] as i32, rgb[i + 1] as i32, rgb[i + 2] as i32)
    };
    for y in 0..h2 {
        let row = &mut y_plane[y * w2..(y + 1) * w2];
        for (x, out) in row.iter_mut().enumerate() {
            let (r, g, b) = px(x, y);
            *out = (((YR * r + YG * g + YB * b + HALF) >> 16) + 16) as u8;
        }
    }
    for cy in 0..ch {
        for cx in 0..cw {
            let (mut r, mut g, mut b) = (0, 0, 0);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let p = px(2 * cx + dx, 2 * cy + dy);
                r += p.0;
                g += p.1;
                b += p.2;
            }
            // Sums of four: divide by 4 inside the fixed-point shift.
            let u = (UR * r + UG * g + UB * b + 4 * HALF) >> 18;
            let v = (VR * r + VG * g + VB * b + 4 * HALF) >> 18;
            u_plane[cy * cw + cx] = (u + 128).clamp(0, 255) as u8;
            v_plane[cy * cw + cx] = (v + 128).clamp(0, 255) as u8;
        }
    }
}

/// Which Y'CbCr -> RGB matrix a decoded picture uses (limited range: Y in 16..=235).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum YuvMatrix {
    /// BT.601 / SMPTE 170M, and what decoders assume when a stream does not say.
    Bt601,
    Bt709,
}

impl YuvMatrix {
    /// swscale's inverse tables (`ff_yuv2rgb_coeffs`: crv, cbu, cgu, cgv in 16.16, chroma
    /// already scaled by 255/224 for limited range).
    fn sws_table(self) -> [i32; 4] {
        match self {
            YuvMatrix::Bt601 => [104597, 132201, 25675, 53279],
            YuvMatrix::Bt709 => [117489, 138438, 13975, 34925],
        }
    }
}

/// The fixed-point factors of ffmpeg's (swscale's) fast 4:2:0 -> RGB conversion, which the
/// `ffmpeg` program uses for `-pix_fmt rgb24`: 16-bit coefficients in 3.13 fixed point applied to
/// samples scaled by 8, every product floored (`pmulhw`). Using the same arithmetic makes the
/// built-in decoder's pictures equal ffmpeg's (bit for bit on x86, measured on ffmpeg 5.1), so
/// a video reads the same with or without ffmpeg; exact rounding would be 0.5-1.5 code values
/// brighter on average.
#[derive(Debug, Clone, Copy)]
struct SwsFactors {
    y: i32,
    y_offset: i32,
    vr: i32,
    ub: i32,
    ug: i32,
    vg: i32,
}

impl SwsFactors {
    fn new(m: YuvMatrix) -> Self {
        // swscale's roundToInt16: 16.16 times 2^13, rounded to an integer.
        let q = |v: i64| ((v * (1 << 13) + (1 << 15)) >> 16) as i32;
        let [crv, cbu, cgu, cgv] = m.sws_table().map(i64::from);
        let cy = (1i64 << 16) * 255 / 219;
        SwsFactors {
            y: q(cy),
            y_offset: (((16i64 << 16) * 8 + (1 << 15)) >> 16) as i32,
            vr: q(crv),
            ub: q(cbu),
            ug: q(-cgu),
            vg: q(-cgv),
        }
    }
}

/// One I420 picture as planes with strides (the decoder's buffers are padded).
pub(crate) struct I420<'a> {
    pub y: &'a [u8],
    pub u: &'a [u8],
    pub v: &'a [u8],
    pub y_stride: usize,
    pub uv_stride: usize,
    pub width: usize,
    pub height: usize,
}

/// I420 to RGB HWC (`width * height * 3` bytes) with BT.601 limited range, each chroma sample
/// covering its 2x2 block.
#[cfg(test)]
pub(crate) fn i420_to_rgb(p: &I420<'_>) -> Vec<u8> {
    i420_to_rgb_with(p, YuvMatrix::Bt601)
}

/// I420 (limited range) to RGB HWC, `width * height * 3` bytes, with ffmpeg's arithmetic (see
/// [`SwsFactors`]); each chroma sample covers its 2x2 block.
pub(crate) fn i420_to_rgb_with(p: &I420<'_>, m: YuvMatrix) -> Vec<u8> {
    let f = SwsFactors::new(m);
    let mut out = vec![0u8; p.width * p.height * 3];
    let px = |o: &mut [u8], y: u8, (r, g, b): (i32, i32, i32)| {
        let l = ((y as i32 * 8 - f.y_offset) * f.y) >> 16;
        o[0] = (l + r).clamp(0, 255) as u8;
        o[1] = (l + g).clamp(0, 255) as u8;
        o[2] = (l + b).clamp(0, 255) as u8;
    };
    for y in 0..p.height {
        let yrow = &p.y[y * p.y_stride..][..p.width];
        let urow = &p.u[(y / 2) * p.uv_stride..][..p.width.div_ceil(2)];
        let vrow = &p.v[(y / 2) * p.uv_stride..][..p.width.div_ceil(2)];
        let orow = &mut out[y * p.width * 3..(y + 1) * p.width * 3];
        // Two pixels share a chroma sample: its three terms are computed once per pair.
        for (((o, ys), &u), &v) in orow.chunks_mut(6).zip(yrow.chunks(2)).zip(urow).zip(vrow) {
            let u = u as i32 * 8 - 1024;
            let v = v as i32 * 8 - 1024;
            let c = (
                (v * f.vr) >> 16,
                ((u * f.ug) >> 16) + ((v * f.vg) >> 16),
                (u * f.ub) >> 16,
            );
            px(&mut o[..3], ys[0], c);
            if let (Some(&y1), Some(o1)) = (ys.get(1), o.get_mut(3..6)) {
                px(o1, y1, c);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rounding in both directions plus the 8-bit planes: a round trip of a flat colour may move
    /// each channel by this much (limited range has fewer codes than full-range RGB).
    const ROUND_TRIP_TOL: i32 = 2;

    #[test]
    fn flat_colours_round_trip() {
        for &(r, g, b) in &[
            (0u8, 0u8, 0u8),
            (255, 255, 255),
            (255, 0, 0),
            (0, 255, 0),
            (0, 0, 255),
            (200, 150, 120),
            (12, 34, 56),
        ] {
            let rgb: Vec<u8> = [r, g, b].repeat(4 * 4);
            let mut yuv = Vec::new();
            rgb_to_i420(&rgb, 4, 4, &mut yuv);
            let back = i420_to_rgb(&I420 {
                y: &yuv[..16],
                u: &yuv[16..20],
                v: &yuv[20..24],
                y_stride: 4,
                uv_stride: 2,
                width: 4,
                height: 4,
            });
            for (i, (&a, &e)) in back.iter().zip(rgb.iter()).enumerate() {
                assert!(
                    (a as i32 - e as i32).abs() <= ROUND_TRIP_TOL,
                    "colour {:?} index {i}: expected {e}, got {a}",
                    (r, g, b)
                );
            }
        }
    }

    #[test]
    fn known_bt601_codes() {
        // Limited range: black is Y=16, white Y=235, greys have neutral chroma 128; pure red is
        // (81, 90, 240) in BT.601 limited range (ITU-R BT.601 with 8-bit rounding).
        let cases = [
            ((0u8, 0u8, 0u8), (16u8, 128u8, 128u8)),
            ((255, 255, 255), (235, 128, 128)),
            ((255, 0, 0), (81, 90, 240)),
        ];
        for ((r, g, b), expected) in cases {
            let rgb: Vec<u8> = [r, g, b].repeat(4);
            let mut yuv = Vec::new();
            rgb_to_i420(&rgb, 2, 2, &mut yuv);
            assert_eq!((yuv[0], yuv[4], yuv[5]), expected, "rgb {:?}", (r, g, b));
        }
    }

    #[test]
    fn odd_sizes_repeat_the_last_column_and_row() {
        // 3x3 with a distinct last column and row: the padded 4x4 luma repeats them.
        let mut rgb = vec![0u8; 3 * 3 * 3];
        for y in 0..3 {
            for x in 0..3 {
                let v = (y * 3 + x) as u8 * 20;
                rgb[(y * 3 + x) * 3..][..3].copy_from_slice(&[v, v, v]);
            }
        }
        let mut yuv = Vec::new();
        rgb_to_i420(&rgb, 3, 3, &mut yuv);
        assert_eq!(yuv.len(), 16 + 4 + 4);
        for y in 0..4 {
            assert_eq!(yuv[y * 4 + 3], yuv[y * 4 + 2], "row {y}: padded column");
        }
        for x in 0..4 {
            assert_eq!(yuv[12 + x], yuv[8 + x], "column {x}: padded row");
        }
    }
}
