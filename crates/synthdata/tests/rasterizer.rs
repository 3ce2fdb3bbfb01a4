//! The rasterizer against analytic coverage, perspective-correct interpolation computed by
//! ray-plane intersection, depth ordering, both windings, and the resolve's box filter.

use gagavatar_synthdata::{Rasterizer, NO_FACE};

/// Barycentrics are stored as f32: a few ulps of values in [0, 1].
const BARY_TOL: f64 = 2e-6;
/// Samples closer than this (in sample-grid units, relative to the edge length) to an edge are
/// skipped by the coverage check: on the line the inclusive test may go either way in floating
/// point.
const EDGE_EPS: f64 = 1e-9;
/// Resolved colours are f32 sums of at most 64 samples.
const COLOUR_TOL: f32 = 1e-5;

/// Screen-space barycentrics of point (x, y) in triangle `t` (pixel coordinates).
fn screen_bary(t: &[[f64; 3]; 3], x: f64, y: f64) -> [f64; 3] {
    let [a, b, c] = t;
    let det = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    let l1 = ((x - a[0]) * (c[1] - a[1]) - (y - a[1]) * (c[0] - a[0])) / det;
    let l2 = ((b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0])) / det;
    [1.0 - l1 - l2, l1, l2]
}

#[test]
fn single_triangle_coverage_matches_the_analytic_test() {
    let tri = [[2.3, 1.7, 1.0], [13.6, 4.1, 1.0], [5.2, 12.9, 1.0]];
    for ss in [1, 2, 3] {
        let r = Rasterizer::new(16, 16, ss).unwrap();
        let g = r.rasterize(&tri, &[[0, 1, 2]]).unwrap();
        let mut covered = 0;
        for sy in 0..g.sample_height() {
            for sx in 0..g.sample_width() {
                let (x, y) = g.sample_position(sx, sy);
                let l = screen_bary(&tri, x, y);
                let i = sy * g.sample_width() + sx;
                let min = l.iter().copied().fold(f64::INFINITY, f64::min);
                if min.abs() < EDGE_EPS {
                    continue;
                }
                let inside = min > 0.0;
                assert_eq!(
                    g.face[i] == 0,
                    inside,
                    "ss {ss} sample ({sx}, {sy}) at ({x}, {y}): barycentrics {l:?}, face {}",
                    g.face[i]
                );
                covered += inside as usize;
            }
        }
        // The triangle's area (in pixels) times ss^2 samples per pixel, roughly.
        let area = 0.5
            * ((tri[1][0] - tri[0][0]) * (tri[2][1] - tri[0][1])
                - (tri[1][1] - tri[0][1]) * (tri[2][0] - tri[0][0]))
                .abs();
        let expected = area * (ss * ss) as f64;
        assert!(
            (covered as f64 - expected).abs() < 0.1 * expected,
            "ss {ss}: {covered} samples covered, area says {expected}"
        );
    }
}

/// A triangle in 3D seen by a pinhole camera: the barycentrics the rasterizer stores must be
/// those of the point where the sample's ray meets the triangle (perspective-correct), not the
/// screen-space ones.
#[test]
fn interpolation_is_perspective_correct() {
    let (w, h, f) = (24usize, 24usize, 30.0f64);
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let p3 = [[-0.6, -0.5, 2.0], [0.7, -0.3, 5.0], [-0.1, 0.6, 3.0]];
    let screen: Vec<[f64; 3]> = p3
        .iter()
        .map(|p| [f * p[0] / p[2] + cx, f * p[1] / p[2] + cy, p[2]])
        .collect();
    let r = Rasterizer::new(w, h, 2).unwrap();
    let g = r.rasterize(&screen, &[[0, 1, 2]]).unwrap();
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let n = cross(sub(p3[1], p3[0]), sub(p3[2], p3[0]));
    let mut checked = 0;
    let mut max_screen_gap = 0f64;
    for sy in 0..g.sample_height() {
        for sx in 0..g.sample_width() {
            let i = sy * g.sample_width() + sx;
            if g.face[i] == NO_FACE {
                continue;
            }
            let (x, y) = g.sample_position(sx, sy);
            let dir = [(x - cx) / f, (y - cy) / f, 1.0];
            let t = dot(n, p3[0]) / dot(n, dir);
            let hit = dir.map(|d| d * t);
            // Barycentrics of the hit point: sub-triangle areas over the whole.
            let area = |a: [f64; 3], b: [f64; 3], c: [f64; 3]| dot(cross(sub(b, a), sub(c, a)), n);
            let total = area(p3[0], p3[1], p3[2]);
            let want = [
                area(hit, p3[1], p3[2]) / total,
                area(p3[0], hit, p3[2]) / total,
                area(p3[0], p3[1], hit) / total,
            ];
            let got = g.barycentrics(i);
            for k in 0..3 {
                assert!(
                    (got[k] as f64 - want[k]).abs() < BARY_TOL,
                    "sample ({sx}, {sy}) vertex {k}: expected {} got {}",
                    want[k],
                    got[k]
                );
            }
            assert!(
                (g.inv_depth[i] as f64 - 1.0 / hit[2]).abs() < 1e-6,
                "sample ({sx}, {sy}): 1/z expected {} got {}",
                1.0 / hit[2],
                g.inv_depth[i]
            );
            let s = screen_bary(&[screen[0], screen[1], screen[2]], x, y);
            max_screen_gap = max_screen_gap.max((s[1] - want[1]).abs());
            checked += 1;
        }
    }
    assert!(checked > 100, "only {checked} samples covered");
    // The depths differ 2.5x, so screen-space interpolation would be visibly wrong: the test
    // above distinguishes the two.
    assert!(
        max_screen_gap > 0.05,
        "screen and perspective barycentrics agree ({max_screen_gap})"
    );
}

#[test]
fn nearer_triangle_wins_in_either_drawing_order() {
    let near = [[1.0, 1.0, 2.0], [14.0, 2.0, 2.0], [3.0, 14.0, 2.0]];
    let far = [[2.0, 0.5, 3.0], [15.0, 13.0, 3.0], [0.5, 9.0, 3.0]];
    let verts: Vec<[f64; 3]> = near.iter().chain(&far).copied().collect();
    let r = Rasterizer::new(16, 16, 2).unwrap();
    for (faces, near_id) in [
        ([[0, 1, 2], [3, 4, 5]], 0u32),
        ([[3, 4, 5], [0, 1, 2]], 1u32),
    ] {
        let g = r.rasterize(&verts, &faces).unwrap();
        let g_near = r.rasterize(&verts[..3], &[[0, 1, 2]]).unwrap();
        let mut overlap = 0;
        for i in 0..g.face.len() {
            if g_near.face[i] == 0 {
                assert_eq!(g.face[i], near_id, "sample {i}: the nearer face must win");
                overlap += 1;
            } else if g.face[i] != NO_FACE {
                assert_eq!(
                    g.face[i],
                    1 - near_id,
                    "sample {i}: only the far face is here"
                );
            }
        }
        assert!(overlap > 50);
    }
}

#[test]
fn both_windings_are_drawn_alike() {
    let v = [[1.5, 2.0, 1.0], [12.0, 3.5, 1.5], [4.0, 13.0, 2.0]];
    let r = Rasterizer::new(16, 16, 3).unwrap();
    let ccw = r.rasterize(&v, &[[0, 1, 2]]).unwrap();
    let cw = r.rasterize(&v, &[[0, 2, 1]]).unwrap();
    assert_eq!(ccw.face, cw.face);
    assert!(ccw.face.iter().filter(|&&f| f == 0).count() > 100);
    for i in 0..ccw.face.len() {
        if ccw.face[i] == 0 {
            let (a, b) = (ccw.barycentrics(i), cw.barycentrics(i));
            // Swapping vertices 1 and 2 swaps their weights.
            for (k, j) in [(0, 0), (1, 2), (2, 1)] {
                assert!(
                    (a[k] - b[j]).abs() < 1e-6,
                    "sample {i}: {a:?} vs swapped {b:?}"
                );
            }
        }
    }
}

#[test]
fn resolve_averages_samples_with_black_background() {
    // Two triangles covering the left half of the image exactly (x < 3.5 in pixel coordinates
    // = the edge between pixel 3 and 4): a vertical edge through the middle of nothing.
    let v = [
        [-0.5, -0.5, 1.0],
        [3.5, -0.5, 1.0],
        [3.5, 7.5, 1.0],
        [-0.5, 7.5, 1.0],
    ];
    let faces = [[0, 1, 2], [0, 2, 3]];
    for ss in [1, 2, 4] {
        let r = Rasterizer::new(8, 8, ss).unwrap();
        let g = r.rasterize(&v, &faces).unwrap();
        // Per-vertex colour: red = x position of vertex (linear, so the mean over a pixel's
        // samples is the value at the pixel centre), green constant.
        let img = g.resolve(|f, b| {
            let tri = faces[f as usize];
            let x: f32 = (0..3).map(|k| b[k] * v[tri[k] as usize][0] as f32).sum();
            [x, 0.5, 0.0]
        });
        for py in 0..8 {
            for px in 0..8 {
                let got = img[py * 8 + px];
                let want = if px < 4 {
                    [px as f32, 0.5, 0.0]
                } else {
                    [0.0, 0.0, 0.0]
                };
                for c in 0..3 {
                    assert!(
                        (got[c] - want[c]).abs() < COLOUR_TOL,
                        "ss {ss} pixel ({px}, {py}) channel {c}: expected {} got {}",
                        want[c],
                        got[c]
                    );
                }
            }
        }
    }
    // An edge through a pixel: a triangle covering exactly half of pixel (0, 0)'s samples.
    let r = Rasterizer::new(1, 1, 4).unwrap();
    let half = [
        [-0.5, -0.5, 1.0],
        [0.0, -0.5, 1.0],
        [0.0, 0.5, 1.0],
        [-0.5, 0.5, 1.0],
    ];
    let g = r.rasterize(&half, &[[0, 1, 2], [0, 2, 3]]).unwrap();
    let img = g.resolve(|_, _| [1.0, 1.0, 1.0]);
    assert!(
        (img[0][0] - 0.5).abs() < COLOUR_TOL,
        "half coverage gave {}",
        img[0][0]
    );
}

#[test]
fn triangles_behind_the_near_plane_or_off_screen_are_skipped() {
    let r = Rasterizer::new(8, 8, 1).unwrap();
    let behind = [[0.0, 0.0, -1.0], [7.0, 0.0, 1.0], [0.0, 7.0, 1.0]];
    let g = r.rasterize(&behind, &[[0, 1, 2]]).unwrap();
    assert!(g.face.iter().all(|&f| f == NO_FACE));
    let off = [[20.0, 20.0, 1.0], [30.0, 20.0, 1.0], [20.0, 30.0, 1.0]];
    let g = r.rasterize(&off, &[[0, 1, 2]]).unwrap();
    assert!(g.face.iter().all(|&f| f == NO_FACE));
}
