//! The feature maps the networks pass between layers: one image, NHWC (TFLite's layout), f32.

/// A `h x w x c` feature map, channels fastest (`data[(y * w + x) * c + ch]`).
#[derive(Debug, Clone, PartialEq)]
pub struct Nhwc {
    pub h: usize,
    pub w: usize,
    pub c: usize,
    pub data: Vec<f32>,
}

impl Nhwc {
    /// A map of zeros.
    pub fn zeros(h: usize, w: usize, c: usize) -> Self {
        Nhwc {
            h,
            w,
            c,
            data: vec![0.0; h * w * c],
        }
    }

    /// Wraps `data`, which must hold exactly `h * w * c` values.
    pub fn from_vec(h: usize, w: usize, c: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), h * w * c, "feature map size");
        Nhwc { h, w, c, data }
    }

    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.h * self.w
    }

    /// The `c` values of pixel `(y, x)`.
    pub fn at(&self, y: usize, x: usize) -> &[f32] {
        let o = (y * self.w + x) * self.c;
        &self.data[o..o + self.c]
    }
}
