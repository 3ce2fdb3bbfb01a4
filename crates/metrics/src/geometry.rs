//! The plane geometry dlib's alignment uses, with dlib's conventions: integer rectangles are
//! inclusive (`width = right - left + 1`), so are real-valued ones (`DRect`), and a point is
//! rounded to a pixel as `floor(v + 0.5)`.

use crate::error::{input_err, Result};

/// A face rectangle in pixels, inclusive on every side (dlib's `rectangle`): `left..=right`,
/// `top..=bottom`. It may reach outside the image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FaceRect {
    pub left: i64,
    pub top: i64,
    pub right: i64,
    pub bottom: i64,
}

/// Largest coordinate magnitude a rectangle may have; far beyond any image, and small enough
/// that every computation stays exact in f64.
pub const MAX_COORD: i64 = 1 << 24;

impl FaceRect {
    /// A rectangle from its inclusive sides; `right >= left` and `bottom >= top`.
    pub fn new(left: i64, top: i64, right: i64, bottom: i64) -> Result<Self> {
        if [left, top, right, bottom]
            .iter()
            .any(|v| v.abs() > MAX_COORD)
        {
            return Err(input_err(
                "face rectangle",
                format!("coordinates ({left}, {top}, {right}, {bottom}) are out of range"),
            ));
        }
        if right < left || bottom < top {
            return Err(input_err(
                "face rectangle",
                format!("right/bottom ({right}, {bottom}) before left/top ({left}, {top})"),
            ));
        }
        Ok(Self {
            left,
            top,
            right,
            bottom,
        })
    }

    /// A rectangle from a real-valued box `[x0, x1) x [y0, y1)` (e.g. a detector's box in
    /// pixels): the sides are rounded to the nearest pixel and the exclusive end becomes the
    /// inclusive `right = round(x1) - 1`.
    pub fn from_box(x0: f64, y0: f64, x1: f64, y1: f64) -> Result<Self> {
        if ![x0, y0, x1, y1].iter().all(|v| v.is_finite()) {
            return Err(input_err(
                "face box",
                format!("non-finite value in ({x0}, {y0}, {x1}, {y1})"),
            ));
        }
        let lim = MAX_COORD as f64;
        if [x0, y0, x1, y1].iter().any(|v| v.abs() > lim) {
            return Err(input_err(
                "face box",
                format!("({x0}, {y0}, {x1}, {y1}) is out of range"),
            ));
        }
        let r = |v: f64| (v + 0.5).floor() as i64;
        Self::new(r(x0), r(y0), r(x1) - 1, r(y1) - 1)
    }

    pub fn width(&self) -> i64 {
        self.right - self.left + 1
    }

    pub fn height(&self) -> i64 {
        self.bottom - self.top + 1
    }
}

/// dlib's `drectangle`: real-valued, inclusive (`width = right - left + 1`); empty when
/// `left > right` or `top > bottom`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DRect {
    pub left: f64,
    pub top: f64,
    pub right: f64,
    pub bottom: f64,
}

impl DRect {
    pub fn is_empty(&self) -> bool {
        self.top > self.bottom || self.left > self.right
    }

    pub fn width(&self) -> f64 {
        if self.is_empty() {
            0.0
        } else {
            self.right - self.left + 1.0
        }
    }

    pub fn height(&self) -> f64 {
        if self.is_empty() {
            0.0
        } else {
            self.bottom - self.top + 1.0
        }
    }

    pub fn area(&self) -> f64 {
        self.width() * self.height()
    }

    pub fn center(&self) -> [f64; 2] {
        [
            (self.left + self.right) / 2.0,
            (self.top + self.bottom) / 2.0,
        ]
    }

    /// A rectangle of the given (inclusive) width and height centred on `c`.
    pub fn centered(c: [f64; 2], width: f64, height: f64) -> Self {
        let (w, h) = (width - 1.0, height - 1.0);
        DRect {
            left: c[0] - w / 2.0,
            top: c[1] - h / 2.0,
            right: c[0] + w / 2.0,
            bottom: c[1] + h / 2.0,
        }
    }

    pub fn translate(&self, dx: f64, dy: f64) -> Self {
        DRect {
            left: self.left + dx,
            top: self.top + dy,
            right: self.right + dx,
            bottom: self.bottom + dy,
        }
    }

    pub fn intersect(&self, o: &DRect) -> Self {
        DRect {
            left: self.left.max(o.left),
            top: self.top.max(o.top),
            right: self.right.min(o.right),
            bottom: self.bottom.min(o.bottom),
        }
    }

    /// Grown by `d` on every side.
    pub fn grow(&self, d: f64) -> Self {
        DRect {
            left: self.left - d,
            top: self.top - d,
            right: self.right + d,
            bottom: self.bottom + d,
        }
    }

    /// The smallest rectangle holding both (an empty one adds nothing).
    pub fn union(&self, o: &DRect) -> Self {
        if o.is_empty() {
            return *self;
        }
        if self.is_empty() {
            return *o;
        }
        DRect {
            left: self.left.min(o.left),
            top: self.top.min(o.top),
            right: self.right.max(o.right),
            bottom: self.bottom.max(o.bottom),
        }
    }

    pub fn tl(&self) -> [f64; 2] {
        [self.left, self.top]
    }
    pub fn tr(&self) -> [f64; 2] {
        [self.right, self.top]
    }
    pub fn bl(&self) -> [f64; 2] {
        [self.left, self.bottom]
    }
    pub fn br(&self) -> [f64; 2] {
        [self.right, self.bottom]
    }
}

/// dlib's `floor(v + 0.5)` rounding of a coordinate to a pixel.
pub fn round_px(v: f64) -> i64 {
    (v + 0.5).floor() as i64
}

/// `x -> m x + b`, dlib's `point_transform_affine`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Affine2 {
    pub m: [[f64; 2]; 2],
    pub b: [f64; 2],
}

impl Affine2 {
    pub fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        [
            self.m[0][0] * p[0] + self.m[0][1] * p[1] + self.b[0],
            self.m[1][0] * p[0] + self.m[1][1] * p[1] + self.b[1],
        ]
    }

    /// The affine map taking `(0, 0)`, `(w, 0)`, `(0, h)` to `p0`, `p1`, `p2` (`w, h > 0`); the
    /// exact solution of what dlib's `find_affine_transform` solves by least squares.
    pub fn from_axes(w: f64, h: f64, p0: [f64; 2], p1: [f64; 2], p2: [f64; 2]) -> Self {
        Affine2 {
            m: [
                [(p1[0] - p0[0]) / w, (p2[0] - p0[0]) / h],
                [(p1[1] - p0[1]) / w, (p2[1] - p0[1]) / h],
            ],
            b: p0,
        }
    }
}

/// The least-squares similarity transform (rotation, uniform scale, translation) taking
/// `from[i]` to `to[i]` (Umeyama 1991, the formulas dlib's `find_similarity_transform` uses).
/// In 2-D the optimum has a closed form: with `cov = mean((to - mean_to)(from - mean_from)^T) =
/// [[a, b], [c, d]]`, `scale * R = [[a + d, b - c], [c - b, a + d]] / var(from)`; this is
/// Umeyama's `c R` including his reflection case (the best proper rotation).
pub fn similarity_transform(from: &[[f64; 2]], to: &[[f64; 2]]) -> Affine2 {
    let n = from.len().min(to.len()) as f64;
    let mut mf = [0.0f64; 2];
    let mut mt = [0.0f64; 2];
    for (f, t) in from.iter().zip(to) {
        mf[0] += f[0];
        mf[1] += f[1];
        mt[0] += t[0];
        mt[1] += t[1];
    }
    for v in [&mut mf, &mut mt] {
        v[0] /= n;
        v[1] /= n;
    }
    let mut sigma_from = 0.0;
    let mut cov = [[0.0f64; 2]; 2];
    for (f, t) in from.iter().zip(to) {
        let df = [f[0] - mf[0], f[1] - mf[1]];
        let dt = [t[0] - mt[0], t[1] - mt[1]];
        sigma_from += df[0] * df[0] + df[1] * df[1];
        for (i, row) in cov.iter_mut().enumerate() {
            for (j, c) in row.iter_mut().enumerate() {
                *c += dt[i] * df[j];
            }
        }
    }
    sigma_from /= n;
    for row in cov.iter_mut() {
        for c in row.iter_mut() {
            *c /= n;
        }
    }
    let (a, b, c, d) = (cov[0][0], cov[0][1], cov[1][0], cov[1][1]);
    let (p, q) = (a + d, c - b);
    // dlib keeps scale 1 and the identity for a degenerate (single-point) source.
    let m = if sigma_from != 0.0 {
        [
            [p / sigma_from, -q / sigma_from],
            [q / sigma_from, p / sigma_from],
        ]
    } else {
        [[1.0, 0.0], [0.0, 1.0]]
    };
    let b = [
        mt[0] - (m[0][0] * mf[0] + m[0][1] * mf[1]),
        mt[1] - (m[1][0] * mf[0] + m[1][1] * mf[1]),
    ];
    Affine2 { m, b }
}

/// `p` rotated by `angle` (radians) about `center`, dlib's `rotate_point`.
pub fn rotate_point(center: [f64; 2], p: [f64; 2], angle: f64) -> [f64; 2] {
    let (s, c) = (angle.sin(), angle.cos());
    let (dx, dy) = (p[0] - center[0], p[1] - center[1]);
    [c * dx - s * dy + center[0], s * dx + c * dy + center[1]]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Exact-input transforms are recovered to rounding error.
    const TOL: f64 = 1e-12;

    #[test]
    fn similarity_recovers_a_known_transform() {
        let (s, th, t) = (1.7f64, 0.4f64, [3.0, -2.0]);
        let from = [
            [0.0, 0.0],
            [10.0, 1.0],
            [4.0, 7.0],
            [-3.0, 2.5],
            [1.0, -6.0],
        ];
        let to: Vec<[f64; 2]> = from
            .iter()
            .map(|p| {
                [
                    s * (th.cos() * p[0] - th.sin() * p[1]) + t[0],
                    s * (th.sin() * p[0] + th.cos() * p[1]) + t[1],
                ]
            })
            .collect();
        let a = similarity_transform(&from, &to);
        let want = [[s * th.cos(), -s * th.sin()], [s * th.sin(), s * th.cos()]];
        for (i, (row, want_row)) in a.m.iter().zip(&want).enumerate() {
            for (j, (got, w)) in row.iter().zip(want_row).enumerate() {
                assert!((got - w).abs() < TOL, "m[{i}][{j}] expected {w} got {got}");
            }
            assert!(
                (a.b[i] - t[i]).abs() < TOL,
                "b[{i}]: expected {} got {}",
                t[i],
                a.b[i]
            );
        }
    }

    #[test]
    fn similarity_of_a_mirrored_set_is_a_proper_rotation() {
        let from = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
        let to = [[0.0, 0.0], [-1.0, 0.0], [0.0, 1.0]];
        let a = similarity_transform(&from, &to);
        // No proper similarity maps a mirror image exactly. Worked by hand with the centred
        // points x_i, y_i: scale*cos = sum(x.y) / sum|x|^2 = 0 and scale*sin = sum(x cross y) /
        // sum|x|^2 = (-2/3) / (4/3) = -1/2, i.e. a quarter turn clockwise at half scale, and
        // b = mean(to) - M mean(from) = (-1/2, 1/2).
        let want_m = [[0.0, 0.5], [-0.5, 0.0]];
        let want_b = [-0.5, 0.5];
        for (i, (row, want_row)) in a.m.iter().zip(&want_m).enumerate() {
            for (j, (got, w)) in row.iter().zip(want_row).enumerate() {
                assert!(
                    (got - w).abs() < TOL,
                    "m[{i}][{j}]: expected {w}, got {got}"
                );
            }
            assert!(
                (a.b[i] - want_b[i]).abs() < TOL,
                "b[{i}]: expected {}, got {}",
                want_b[i],
                a.b[i]
            );
        }
        // And it is the least-squares optimum: every nearby proper similarity does worse.
        let cost = |m: [[f64; 2]; 2], b: [f64; 2]| -> f64 {
            from.iter()
                .zip(&to)
                .map(|(p, q)| {
                    let x = m[0][0] * p[0] + m[0][1] * p[1] + b[0] - q[0];
                    let y = m[1][0] * p[0] + m[1][1] * p[1] + b[1] - q[1];
                    x * x + y * y
                })
                .sum()
        };
        let best = cost(a.m, a.b);
        for (dc, ds, dx, dy) in [
            (0.01, 0.0, 0.0, 0.0),
            (-0.01, 0.0, 0.0, 0.0),
            (0.0, 0.01, 0.0, 0.0),
            (0.0, -0.01, 0.0, 0.0),
            (0.0, 0.0, 0.01, 0.0),
            (0.0, 0.0, 0.0, -0.01),
        ] {
            let (c, s) = (a.m[0][0] + dc, a.m[1][0] + ds);
            let other = cost([[c, -s], [s, c]], [a.b[0] + dx, a.b[1] + dy]);
            assert!(other > best, "({dc}, {ds}, {dx}, {dy}): {other} <= {best}");
        }
    }

    #[test]
    fn rect_from_box_rounds_and_rejects_nan() {
        let r = FaceRect::from_box(10.4, 20.6, 50.5, 61.0).unwrap();
        assert_eq!((r.left, r.top, r.right, r.bottom), (10, 21, 50, 60));
        assert!(FaceRect::from_box(f64::NAN, 0.0, 1.0, 1.0).is_err());
        assert!(FaceRect::from_box(0.0, 0.0, f64::INFINITY, 1.0).is_err());
        assert!(FaceRect::new(5, 5, 4, 10).is_err());
    }
}
