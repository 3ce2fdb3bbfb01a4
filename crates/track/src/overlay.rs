//! A picture of a fit for people to judge it: over the original frame, the fitted FLAME mesh
//! (the edges of its camera-facing triangles inside the crop window, thin and
//! semi-transparent), the detected
//! landmarks and the fitted FLAME's 70 reprojected landmarks in two colours joined by a line
//! (the error), and the crop window.
//!
//! Sizes scale with the crop window (a face of any size in any frame reads the same), and
//! everything is clipped to the frame. The mesh is given as projected 2D vertices because
//! skinning the full FLAME is the flame crate's job; [`mesh_edges`] turns its triangles into
//! the edge list once per asset.

use image::RgbImage;

use crate::pipeline::FrameTrack;

/// Mesh edges: light cyan at 30% (the face stays visible under some 10k edges).
pub const MESH_COLOUR: [u8; 3] = [120, 230, 255];
pub const MESH_ALPHA: f32 = 0.3;
/// Detected landmarks: green.
pub const DETECTED_COLOUR: [u8; 3] = [40, 255, 80];
/// The fitted FLAME's reprojected landmarks: magenta.
pub const FITTED_COLOUR: [u8; 3] = [255, 40, 200];
/// The crop window: yellow.
pub const WINDOW_COLOUR: [u8; 3] = [255, 220, 0];

/// The fitted mesh in frame pixels: per vertex its projection (`None` behind the camera), and
/// the triangles (vertex indices) whose facing decides which edges are drawn.
#[derive(Debug, Clone, Copy)]
pub struct ProjectedMesh<'a> {
    pub points: &'a [Option<[f64; 2]>],
    pub faces: &'a [[u32; 3]],
}

/// The unique edges of a triangle list, each with the (up to two) triangles it borders.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshEdges {
    pub edges: Vec<([u32; 2], [Option<u32>; 2])>,
}

pub fn mesh_edges(faces: &[[u32; 3]]) -> MeshEdges {
    let mut map: std::collections::HashMap<(u32, u32), [Option<u32>; 2]> =
        std::collections::HashMap::with_capacity(faces.len() * 2);
    for (f, tri) in faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            let key = (a.min(b), a.max(b));
            let e = map.entry(key).or_insert([None, None]);
            if e[0].is_none() {
                e[0] = Some(f as u32);
            } else {
                e[1] = Some(f as u32);
            }
        }
    }
    let mut edges: Vec<_> = map.into_iter().map(|((a, b), t)| ([a, b], t)).collect();
    edges.sort_unstable_by_key(|e| e.0);
    MeshEdges { edges }
}

/// Signed area of a projected triangle in image coordinates (y down); `None` if a corner is
/// not projected or an index is out of range.
fn signed_area(points: &[Option<[f64; 2]>], tri: &[u32; 3]) -> Option<f64> {
    let p = |i: u32| points.get(i as usize).copied().flatten();
    let (a, b, c) = (p(tri[0])?, p(tri[1])?, p(tri[2])?);
    Some(0.5 * ((b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])))
}

/// Pixels a drawing may touch: `[x0, y0, x1, y1)`.
type Clip = [i64; 4];

/// Alpha-blends `colour` into pixel (x, y) if it lies in the image and in `clip`.
fn blend_in(img: &mut RgbImage, clip: &Clip, x: i64, y: i64, colour: [u8; 3], alpha: f32) {
    if x < clip[0] || y < clip[1] || x >= clip[2] || y >= clip[3] {
        return;
    }
    blend(img, x, y, colour, alpha);
}

/// Alpha-blends `colour` into pixel (x, y) if it lies in the image.
fn blend(img: &mut RgbImage, x: i64, y: i64, colour: [u8; 3], alpha: f32) {
    if x < 0 || y < 0 || x >= img.width() as i64 || y >= img.height() as i64 {
        return;
    }
    let px = img.get_pixel_mut(x as u32, y as u32);
    for c in 0..3 {
        let v = px[c] as f32 * (1.0 - alpha) + colour[c] as f32 * alpha;
        px[c] = v.round().clamp(0.0, 255.0) as u8;
    }
}

/// A line of `width` pixels between two points (corner convention), blended at `alpha`.
/// Points far outside the frame are clipped first so a wild projection costs nothing.
fn line(img: &mut RgbImage, a: [f64; 2], b: [f64; 2], width: f64, colour: [u8; 3], alpha: f32) {
    let all = [0, 0, img.width() as i64, img.height() as i64];
    line_in(img, &all, a, b, width, colour, alpha)
}

/// [`line`] touching only the pixels in `clip`.
fn line_in(
    img: &mut RgbImage,
    clip: &Clip,
    a: [f64; 2],
    b: [f64; 2],
    width: f64,
    colour: [u8; 3],
    alpha: f32,
) {
    if !(a.iter().chain(&b).all(|v| v.is_finite())) {
        return;
    }
    let (w, h) = (img.width() as f64, img.height() as f64);
    let margin = width + 2.0;
    if (a[0] < -margin && b[0] < -margin)
        || (a[1] < -margin && b[1] < -margin)
        || (a[0] > w + margin && b[0] > w + margin)
        || (a[1] > h + margin && b[1] > h + margin)
    {
        return;
    }
    let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
    // Longer than the frame's diagonal: a degenerate projection, not worth drawing.
    if len > 4.0 * (w + h) {
        return;
    }
    let steps = (len.ceil() as usize).max(1);
    let r = (width / 2.0).max(0.5);
    let ri = r.ceil() as i64;
    let mut last = (i64::MIN, i64::MIN);
    for s in 0..=steps {
        let t = s as f64 / steps as f64;
        let x = a[0] + t * (b[0] - a[0]) - 0.5;
        let y = a[1] + t * (b[1] - a[1]) - 0.5;
        let (xi, yi) = (x.round() as i64, y.round() as i64);
        if (xi, yi) == last {
            continue;
        }
        last = (xi, yi);
        if r <= 0.5 {
            blend_in(img, clip, xi, yi, colour, alpha);
            continue;
        }
        for dy in -ri..=ri {
            for dx in -ri..=ri {
                if ((dx * dx + dy * dy) as f64) <= r * r {
                    blend_in(img, clip, xi + dx, yi + dy, colour, alpha);
                }
            }
        }
    }
}

/// A filled disc of radius `r` centred at `p` (corner convention).
fn disc(img: &mut RgbImage, p: [f64; 2], r: f64, colour: [u8; 3], alpha: f32) {
    if !(p[0].is_finite() && p[1].is_finite()) {
        return;
    }
    let (cx, cy) = (p[0] - 0.5, p[1] - 0.5);
    let ri = r.ceil() as i64 + 1;
    let (x0, y0) = (cx.round() as i64, cy.round() as i64);
    for y in y0 - ri..=y0 + ri {
        for x in x0 - ri..=x0 + ri {
            let d2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
            if d2 <= r * r {
                blend(img, x, y, colour, alpha);
            }
        }
    }
}

/// Draws one frame's fit over `frame` (the original frame the track's coordinates refer to).
/// `mesh`: the fitted FLAME's vertices in frame pixels with its triangles, and the edges from
/// [`mesh_edges`] of those triangles.
pub fn draw_fit(
    frame: &RgbImage,
    track: &FrameTrack,
    mesh: Option<(&ProjectedMesh, &MeshEdges)>,
) -> RgbImage {
    let mut img = frame.clone();
    // The window's side in 512-crop units: 1 at a 512 px window.
    let scale = (track.window.width().max(1) as f64 / 512.0).max(0.25);
    let thin = (0.9 * scale).max(1.0);
    // The mesh is drawn inside the crop window only: that is what the model sees, and a fit
    // whose far vertices fly off (a head seen from very close) stays readable.
    let window = track.window.as_array();
    if let Some((m, edges)) = mesh {
        // Triangles facing the camera have a negative signed area in image coordinates (FLAME
        // winds them counter-clockwise seen from outside; the image's y points down). An edge
        // is drawn when a triangle it borders faces the camera: the silhouette stays, the
        // back of the head does not clutter the face.
        let facing: Vec<bool> = m
            .faces
            .iter()
            .map(|t| signed_area(m.points, t).is_some_and(|a| a < 0.0))
            .collect();
        for ([a, b], tris) in &edges.edges {
            let front = tris
                .iter()
                .flatten()
                .any(|&t| facing.get(t as usize).copied().unwrap_or(false));
            if !front {
                continue;
            }
            let p = |i: u32| m.points.get(i as usize).copied().flatten();
            if let (Some(pa), Some(pb)) = (p(*a), p(*b)) {
                line_in(&mut img, &window, pa, pb, 1.0, MESH_COLOUR, MESH_ALPHA);
            }
        }
    }
    let w = track.window.as_array().map(|v| v as f64);
    let corners = [[w[0], w[1]], [w[2], w[1]], [w[2], w[3]], [w[0], w[3]]];
    for k in 0..4 {
        line(
            &mut img,
            corners[k],
            corners[(k + 1) % 4],
            2.0 * thin,
            WINDOW_COLOUR,
            0.9,
        );
    }
    let r = (2.5 * scale).max(2.0);
    if let Some(det) = &track.detected {
        for (d, f) in det.iter().zip(&track.reprojected) {
            if let (Some(d), Some(f)) = (d, f) {
                line(&mut img, *d, *f, thin, [255, 255, 255], 0.6);
            }
        }
        for d in det.iter().flatten() {
            disc(&mut img, *d, r, DETECTED_COLOUR, 0.95);
        }
    }
    // Smaller than the detected discs, so both show where they coincide.
    for f in track.reprojected.iter().flatten() {
        disc(&mut img, *f, 0.6 * r, FITTED_COLOUR, 0.95);
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb;

    #[test]
    fn edges_of_two_triangles_share_the_diagonal() {
        let e = mesh_edges(&[[0, 1, 2], [0, 2, 3]]);
        assert_eq!(e.edges.len(), 5);
        let diag = e.edges.iter().find(|(k, _)| *k == [0, 2]).unwrap();
        assert_eq!(diag.1, [Some(0), Some(1)]);
    }

    #[test]
    fn signed_area_is_negative_for_clockwise_on_screen() {
        // On screen (y down) these corners run counter-clockwise as seen by a viewer.
        let pts = [Some([0.0, 0.0]), Some([0.0, 10.0]), Some([10.0, 0.0])];
        assert!(signed_area(&pts, &[0, 1, 2]).unwrap() < 0.0);
        assert!(signed_area(&pts, &[0, 2, 1]).unwrap() > 0.0);
        assert!(signed_area(&pts, &[0, 1, 7]).is_none());
    }

    #[test]
    fn lines_and_discs_stay_inside_the_image_and_skip_non_finite_points() {
        let mut img = RgbImage::new(20, 10);
        line(&mut img, [-50.0, 5.0], [70.0, 5.0], 3.0, [255, 0, 0], 1.0);
        line(&mut img, [f64::NAN, 0.0], [5.0, 5.0], 1.0, [0, 255, 0], 1.0);
        disc(&mut img, [19.9, 9.9], 4.0, [0, 0, 255], 1.0);
        disc(&mut img, [f64::INFINITY, 1.0], 4.0, [0, 0, 255], 1.0);
        assert_eq!(img.get_pixel(0, 5)[0], 255);
        assert_eq!(img.get_pixel(19, 5)[0], 255);
        assert_eq!(img.get_pixel(19, 9)[2], 255);
        assert_eq!(img.get_pixel(0, 0), &Rgb([0, 0, 0]));
        assert!(img.pixels().all(|p| p[1] == 0), "the NaN line drew");
        let mut img = RgbImage::new(20, 10);
        line_in(
            &mut img,
            &[5, 0, 10, 10],
            [0.0, 5.0],
            [20.0, 5.0],
            1.0,
            [0, 255, 0],
            1.0,
        );
        let lit: Vec<u32> = (0..20).filter(|&x| img.get_pixel(x, 5)[1] > 0).collect();
        assert_eq!(lit, (5..10).collect::<Vec<u32>>());
    }
}
