//! SSD anchors as MediaPipe's `SsdAnchorsCalculator` lays them out for the face detectors
//! (spec TRACKING.md section 9): fixed anchor size 1, so only the centres matter. Layers with
//! the same stride share one grid; each cell holds one anchor per aspect ratio (here 1.0) plus
//! one interpolated-scale anchor when that ratio is non-zero; cells are ordered by row, then
//! column, then anchor.

/// An anchor centre in [0, 1] tensor coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anchor {
    pub x: f32,
    pub y: f32,
}

/// Anchors for an input of `size` pixels with layers of the given `strides`, one aspect ratio
/// of 1.0 per layer and the interpolated-scale anchor when `interpolated` is true.
pub fn ssd_anchors(size: usize, strides: &[usize], interpolated: bool) -> Vec<Anchor> {
    let per_layer = 1 + interpolated as usize;
    let mut out = Vec::new();
    let mut layer = 0;
    while layer < strides.len() {
        let stride = strides[layer];
        let mut last = layer;
        while last < strides.len() && strides[last] == stride {
            last += 1;
        }
        let per_cell = (last - layer) * per_layer;
        let grid = size.div_ceil(stride);
        for y in 0..grid {
            for x in 0..grid {
                let a = Anchor {
                    x: (x as f32 + 0.5) / grid as f32,
                    y: (y as f32 + 0.5) / grid as f32,
                };
                out.extend(std::iter::repeat_n(a, per_cell));
            }
        }
        layer = last;
    }
    out
}

/// The short-range detector's 896 anchors (128 px; strides 8, 16, 16, 16).
pub fn short_range() -> Vec<Anchor> {
    ssd_anchors(128, &[8, 16, 16, 16], true)
}

/// The full-range detector's 2304 anchors (192 px; stride 4, one anchor per cell).
pub fn full_range() -> Vec<Anchor> {
    ssd_anchors(192, &[4], false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_and_order() {
        let a = short_range();
        assert_eq!(a.len(), 896);
        assert_eq!(
            a[0],
            Anchor {
                x: 0.5 / 16.0,
                y: 0.5 / 16.0
            }
        );
        assert_eq!(a[1], a[0]);
        assert_eq!(a[2].x, 1.5 / 16.0);
        assert_eq!(
            a[512],
            Anchor {
                x: 0.5 / 8.0,
                y: 0.5 / 8.0
            }
        );
        assert_eq!(a[517], a[512]);
        assert_eq!(a[518].x, 1.5 / 8.0);
        let f = full_range();
        assert_eq!(f.len(), 2304);
        assert_eq!(
            f[48],
            Anchor {
                x: 0.5 / 48.0,
                y: 1.5 / 48.0
            }
        );
    }
}
