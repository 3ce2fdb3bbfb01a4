//! A CPU triangle rasterizer: z-buffer, perspective-correct barycentrics, deferred shading and
//! supersampled antialiasing (an `ss x ss` grid of samples per pixel, box-averaged; shading
//! once per pixel and visible face, see [`GBuffer::resolve`]), black background.
//!
//! Coordinates: vertices come in *output-image pixel coordinates* with pixel centres at integers
//! (the spec's `pixel = ((ndc + 1) W - 1) / 2`), plus their view-space depth `z` (> 0 in front of
//! the camera). Sample `k` of the `ss` per pixel along an axis sits at `i - 1/2 + (k + 1/2) / ss`
//! inside pixel `i`, so the box average of a pixel's samples is centred on the pixel centre.
//!
//! Both windings are drawn (no back-face culling): a mesh with holes (the FLAME mouth and eye
//! sockets) shows its inside through them, and the shader is told which side it sees (the
//! caller decides what "front" means, see [`Rasterizer::rasterize`]). Triangles with a vertex at
//! or behind [`Z_NEAR`] are skipped rather than clipped: the generator's cameras keep every
//! vertex about 9 units away, so clipping would be dead code.
//!
//! Samples exactly on a shared edge are covered by both triangles (inclusive edge test), so no
//! cracks appear; the depth test keeps the nearer one and, on an exact tie, the first drawn,
//! which keeps the output a deterministic function of the input.

use image::RgbImage;

use crate::error::{Result, SynthError};

/// Marks a sample that no triangle covers.
pub const NO_FACE: u32 = u32::MAX;

/// Nearest accepted vertex depth; triangles with a vertex closer than this are skipped.
pub const Z_NEAR: f64 = 1e-3;

/// Largest supported supersampling factor per axis.
pub const MAX_SUPERSAMPLE: usize = 8;

/// Per-sample result of [`Rasterizer::rasterize`]: which face is visible and where on it.
#[derive(Debug, Clone)]
pub struct GBuffer {
    /// Output image size.
    pub width: usize,
    pub height: usize,
    /// Samples per pixel along each axis.
    pub ss: usize,
    /// Visible face per sample (row-major over the `width*ss x height*ss` sample grid), or
    /// [`NO_FACE`].
    pub face: Vec<u32>,
    /// Perspective-correct barycentric weights of the face's vertices 1 and 2 (vertex 0 gets
    /// `1 - b1 - b2`).
    pub bary: Vec<[f32; 2]>,
    /// `1 / z` of the visible surface (0 where nothing is drawn): larger is nearer.
    pub inv_depth: Vec<f32>,
}

impl GBuffer {
    pub fn sample_width(&self) -> usize {
        self.width * self.ss
    }

    pub fn sample_height(&self) -> usize {
        self.height * self.ss
    }

    /// Position of sample `(sx, sy)` in output pixel coordinates.
    pub fn sample_position(&self, sx: usize, sy: usize) -> (f64, f64) {
        let s = self.ss as f64;
        ((sx as f64 + 0.5) / s - 0.5, (sy as f64 + 0.5) / s - 0.5)
    }

    /// Barycentrics `[b0, b1, b2]` of sample `i`.
    pub fn barycentrics(&self, i: usize) -> [f32; 3] {
        let [b1, b2] = self.bary[i];
        [1.0 - b1 - b2, b1, b2]
    }

    /// Resolves the samples into a `height x width` float image (row-major), MSAA-style:
    /// coverage and depth are per sample, but each pixel calls `shade(face, barycentrics)` once
    /// per face visible in it, at the mean barycentrics of that face's samples, weighted by how
    /// many samples it covers (uncovered samples count as black). For attributes linear in the
    /// barycentrics this equals shading every sample; shaders band-limit their own texture.
    pub fn resolve<F>(&self, shade: F) -> Vec<[f32; 3]>
    where
        F: Fn(u32, [f32; 3]) -> [f32; 3],
    {
        let (w, h, ss) = (self.width, self.height, self.ss);
        let sw = self.sample_width();
        let norm = 1.0 / (ss * ss) as f32;
        let mut out = vec![[0f32; 3]; w * h];
        // (face, summed b1, summed b2, samples) per face seen in the pixel.
        let mut groups: Vec<(u32, f32, f32, u32)> = Vec::with_capacity(ss * ss);
        for py in 0..h {
            for px in 0..w {
                groups.clear();
                for ky in 0..ss {
                    let row = (py * ss + ky) * sw + px * ss;
                    for i in row..row + ss {
                        let f = self.face[i];
                        if f == NO_FACE {
                            continue;
                        }
                        let [b1, b2] = self.bary[i];
                        match groups.iter_mut().find(|g| g.0 == f) {
                            Some(g) => {
                                g.1 += b1;
                                g.2 += b2;
                                g.3 += 1;
                            }
                            None => groups.push((f, b1, b2, 1)),
                        }
                    }
                }
                let mut acc = [0f32; 3];
                for &(f, s1, s2, n) in &groups {
                    let k = n as f32;
                    let (b1, b2) = (s1 / k, s2 / k);
                    let c = shade(f, [1.0 - b1 - b2, b1, b2]);
                    for d in 0..3 {
                        acc[d] += c[d] * k;
                    }
                }
                out[py * w + px] = acc.map(|a| a * norm);
            }
        }
        out
    }
}

/// Quantises a float image (values in [0, 1]) to 8-bit RGB.
pub fn to_rgb8(pixels: &[[f32; 3]], width: usize, height: usize) -> RgbImage {
    let mut img = RgbImage::new(width as u32, height as u32);
    for (dst, src) in img.pixels_mut().zip(pixels) {
        dst.0 = src.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
    }
    img
}

/// Output size and supersampling of a rasterization.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rasterizer {
    pub width: usize,
    pub height: usize,
    pub ss: usize,
}

impl Rasterizer {
    pub fn new(width: usize, height: usize, ss: usize) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(SynthError::Mesh(format!(
                "image size {width}x{height} is empty"
            )));
        }
        if ss == 0 || ss > MAX_SUPERSAMPLE {
            return Err(SynthError::Mesh(format!(
                "supersampling {ss} is outside 1..={MAX_SUPERSAMPLE}"
            )));
        }
        Ok(Self { width, height, ss })
    }

    /// Rasterizes `faces` over `verts` (`[x_px, y_px, z_view]`, see the module docs) into a
    /// G-buffer. Errors on a face index out of range or a non-finite vertex; triangles with
    /// zero screen area or a vertex nearer than [`Z_NEAR`] are skipped.
    pub fn rasterize(&self, verts: &[[f64; 3]], faces: &[[u32; 3]]) -> Result<GBuffer> {
        if let Some(i) = verts.iter().position(|v| v.iter().any(|x| !x.is_finite())) {
            return Err(SynthError::Mesh(format!(
                "vertex {i} is not finite: {:?}",
                verts[i]
            )));
        }
        if let Some((i, f)) = faces
            .iter()
            .enumerate()
            .find(|(_, f)| f.iter().any(|&k| k as usize >= verts.len()))
        {
            return Err(SynthError::Mesh(format!(
                "face {i} {f:?} names a vertex beyond the {} given",
                verts.len()
            )));
        }
        let ss = self.ss;
        let (sw, sh) = (self.width * ss, self.height * ss);
        let n = sw * sh;
        let mut g = GBuffer {
            width: self.width,
            height: self.height,
            ss,
            face: vec![NO_FACE; n],
            bary: vec![[0.0; 2]; n],
            inv_depth: vec![0.0; n],
        };
        let s = ss as f64;
        // Pixel coordinate -> sample-grid coordinate (sample k's centre at k).
        let to_grid = |v: &[f64; 3]| [(v[0] + 0.5) * s - 0.5, (v[1] + 0.5) * s - 0.5, v[2]];
        for (fi, f) in faces.iter().enumerate() {
            let p = f.map(|k| to_grid(&verts[k as usize]));
            if p.iter().any(|v| v[2] < Z_NEAR) {
                continue;
            }
            // Edge function of edge (a, b) at q: positive on one side, zero on the line.
            let area = (p[1][0] - p[0][0]) * (p[2][1] - p[0][1])
                - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]);
            // Vertices are finite (checked above), so the area is too.
            if area.abs() <= 1e-12 {
                continue;
            }
            let inv_area = 1.0 / area;
            let xmin = p.iter().map(|v| v[0]).fold(f64::INFINITY, f64::min);
            let xmax = p.iter().map(|v| v[0]).fold(f64::NEG_INFINITY, f64::max);
            let ymin = p.iter().map(|v| v[1]).fold(f64::INFINITY, f64::min);
            let ymax = p.iter().map(|v| v[1]).fold(f64::NEG_INFINITY, f64::max);
            if xmax < 0.0 || ymax < 0.0 || xmin > (sw - 1) as f64 || ymin > (sh - 1) as f64 {
                continue;
            }
            let x0 = xmin.max(0.0).ceil() as usize;
            let x1 = (xmax.min((sw - 1) as f64).floor() as usize).min(sw - 1);
            let y0 = ymin.max(0.0).ceil() as usize;
            let y1 = (ymax.min((sh - 1) as f64).floor() as usize).min(sh - 1);
            if x0 > x1 || y0 > y1 {
                continue;
            }
            // Normalised barycentric l_k = E_k(q) / area is affine in q: l_k = a_k x + b_k y + c_k.
            let mut coef = [[0f64; 3]; 3];
            for k in 0..3 {
                let (a, b) = (p[(k + 1) % 3], p[(k + 2) % 3]);
                // E_k(q) = (b - a) x (q - a), the signed area opposite vertex k.
                let ax = -(b[1] - a[1]);
                let by = b[0] - a[0];
                let c = -(ax * a[0] + by * a[1]);
                coef[k] = [ax * inv_area, by * inv_area, c * inv_area];
            }
            let iz = p.map(|v| 1.0 / v[2]);
            for y in y0..=y1 {
                let yf = y as f64;
                let row = y * sw;
                for x in x0..=x1 {
                    let xf = x as f64;
                    let l0 = coef[0][0] * xf + coef[0][1] * yf + coef[0][2];
                    let l1 = coef[1][0] * xf + coef[1][1] * yf + coef[1][2];
                    let l2 = coef[2][0] * xf + coef[2][1] * yf + coef[2][2];
                    if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                        continue;
                    }
                    // 1/z is affine in screen space; attributes divided by z are too.
                    let (w0, w1, w2) = (l0 * iz[0], l1 * iz[1], l2 * iz[2]);
                    let inv = w0 + w1 + w2;
                    let i = row + x;
                    if (inv as f32) <= g.inv_depth[i] {
                        continue;
                    }
                    g.inv_depth[i] = inv as f32;
                    g.face[i] = fi as u32;
                    g.bary[i] = [(w1 / inv) as f32, (w2 / inv) as f32];
                }
            }
        }
        Ok(g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_inputs_are_errors() {
        assert!(Rasterizer::new(0, 4, 1).is_err());
        assert!(Rasterizer::new(4, 4, 0).is_err());
        assert!(Rasterizer::new(4, 4, MAX_SUPERSAMPLE + 1).is_err());
        let r = Rasterizer::new(4, 4, 1).unwrap();
        let v = [[0.0, 0.0, 1.0], [3.0, 0.0, 1.0], [0.0, 3.0, 1.0]];
        assert!(r.rasterize(&v, &[[0, 1, 3]]).is_err());
        let bad = [[0.0, 0.0, f64::NAN], [3.0, 0.0, 1.0], [0.0, 3.0, 1.0]];
        assert!(r.rasterize(&bad, &[[0, 1, 2]]).is_err());
    }
}
