//! Records are exact for the images: FLAME vertices recomputed from a record with an independent
//! `FlameModel` and projected with `gagavatar_splat::Camera` land on the rendered head, the
//! record's bbox is the rendered head's box, and the surface seen at each visible vertex's
//! projection is that vertex's own neighbourhood (so no flip, mirror or shift hides anywhere).

use candle_core::{DType, Device};
use gagavatar_flame::{synthesize, FlameConfig, FlameModel, TrackedFrame};
use gagavatar_splat::Camera;
use gagavatar_synthdata::{FrameSample, Generator, SynthConfig, NO_FACE};

/// A vertex on the silhouette can round to a pixel none of whose samples the surface covers
/// (measured: 8-18 of ~4600 in-image vertices per frame, all on the outline); a percent of such
/// misses is allowed.
const MIN_HIT_FRACTION: f64 = 0.99;
/// The record bbox is the vertex box; the rendered box is whole pixels touched by coverage.
const BBOX_TOL_PX: f64 = 1.0;

fn independent_vertices(model: &FlameModel, rec: &TrackedFrame) -> Vec<[f64; 3]> {
    let out = model.forward(&rec.params(model).unwrap()).unwrap();
    out.vertices
        .squeeze(0)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap()
        .into_iter()
        .map(|v| [v[0] as f64, v[1] as f64, v[2] as f64])
        .collect()
}

/// Pixel position and depth through the splatting camera.
fn project(cam: &Camera, p: [f64; 3]) -> [f64; 3] {
    let v: Vec<f64> = (0..3)
        .map(|i| (0..3).map(|j| cam.rot[i][j] * p[j]).sum::<f64>() + cam.trans[i])
        .collect();
    let (fx, fy) = cam.focal_px();
    [
        fx * v[0] / v[2] + (cam.width as f64 - 1.0) / 2.0,
        fy * v[1] / v[2] + (cam.height as f64 - 1.0) / 2.0,
        v[2],
    ]
}

fn setup(size: usize) -> (Generator, FlameModel) {
    let asset = synthesize(0);
    let g = Generator::new(&asset, SynthConfig::new(4, 5, size, 11)).unwrap();
    let model = FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F32).unwrap();
    (g, model)
}

#[test]
fn record_vertices_land_on_the_head_and_bbox_matches() {
    for size in [64, 128] {
        let (g, model) = setup(size);
        for (i, f) in [(0, 0), (0, 3), (1, 1), (2, 4), (3, 2)] {
            let r = g.render(i, f).unwrap();
            let tm = r.record.transform_matrix.unwrap();
            let cam = Camera::from_transform_matrix(&tm, 12.0, size, size).unwrap();
            let verts = independent_vertices(&model, &r.record);
            let lit = |x: usize, y: usize| r.image.get_pixel(x as u32, y as u32).0 != [0, 0, 0];
            let (mut inside, mut hits) = (0usize, 0usize);
            let mut misses = Vec::new();
            for (v, p) in verts.iter().enumerate() {
                let q = project(&cam, *p);
                let (x, y) = (q[0].round(), q[1].round());
                if x < 0.0 || y < 0.0 || x > (size - 1) as f64 || y > (size - 1) as f64 {
                    continue;
                }
                inside += 1;
                if lit(x as usize, y as usize) {
                    hits += 1;
                } else if misses.len() < 5 {
                    misses.push((v, q));
                }
            }
            let frac = hits as f64 / inside as f64;
            eprintln!(
                "size {size} {}: {hits}/{inside} vertices on lit pixels",
                r.name
            );
            assert!(
                frac >= MIN_HIT_FRACTION,
                "size {size} {}: {hits}/{inside} vertices on lit pixels; misses (vertex, \
                 projection): {misses:?}",
                r.name
            );
            // Rendered box: first/last lit column and row, as pixel edges.
            let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
            for (x, y, p) in r.image.enumerate_pixels() {
                if p.0 != [0, 0, 0] {
                    x0 = x0.min(x as usize);
                    y0 = y0.min(y as usize);
                    x1 = x1.max(x as usize + 1);
                    y1 = y1.max(y as usize + 1);
                }
            }
            let bb = r.record.bbox.unwrap();
            let s = size as f64;
            let got = [x0 as f64, y0 as f64, x1 as f64, y1 as f64];
            eprintln!(
                "size {size} {}: bbox record {:?} px, rendered {got:?}",
                r.name,
                bb.map(|b| (b * size as f64 * 100.0).round() / 100.0)
            );
            for k in 0..4 {
                let want = bb[k] * s;
                assert!(
                    (got[k] - want).abs() <= BBOX_TOL_PX,
                    "size {size} {}: bbox side {k}: record {want:.2} px, rendered {} px",
                    r.name,
                    got[k]
                );
            }
        }
    }
}

/// The G-buffer's surface at each visible vertex's independent projection is that vertex:
/// interpolated canonical coordinates there equal the vertex's own (within the distance a
/// sub-pixel offset can move). The same check with the projection mirrored must fail, so the
/// test can tell a mirrored image from a right one.
#[test]
fn surface_at_each_projected_vertex_is_that_vertex() {
    let size = 128;
    let (g, model) = setup(size);
    let anchors = g.anchors();
    for (i, f) in [(0, 1), (1, 3), (3, 4)] {
        let r = g.render(i, f).unwrap();
        let tm = r.record.transform_matrix.unwrap();
        let cam = Camera::from_transform_matrix(&tm, 12.0, size, size).unwrap();
        let verts = independent_vertices(&model, &r.record);
        let verts32: Vec<[f32; 3]> = verts.iter().map(|v| v.map(|x| x as f32)).collect();
        let (_, gb) = g.rasterize(&tm, &verts32).unwrap();
        let faces = &g.model().faces;
        let ss = gb.ss;
        // Face units per pixel at distance ~9 (the head is about 1/6 of the image per unit).
        let fp = tm[2][3] / (6.0 * size as f64) * anchors.scale as f64 / 5.0;
        let tol = 1.5 * fp;
        let sample_at = |q: [f64; 3]| -> Option<usize> {
            let sx = ((q[0] + 0.5) * ss as f64).floor();
            let sy = ((q[1] + 0.5) * ss as f64).floor();
            if sx < 0.0 || sy < 0.0 {
                return None;
            }
            let (sx, sy) = (sx as usize, sy as usize);
            (sx < gb.sample_width() && sy < gb.sample_height()).then(|| sy * gb.sample_width() + sx)
        };
        let canonical_at = |s: usize| -> Option<[f64; 3]> {
            if gb.face[s] == NO_FACE {
                return None;
            }
            let b = gb.barycentrics(s);
            let face = faces[gb.face[s] as usize];
            let c = [0, 1, 2].map(|d| {
                (0..3)
                    .map(|k| b[k] as f64 * anchors.canonical[face[k] as usize][d] as f64)
                    .sum::<f64>()
            });
            Some(c)
        };
        let near = |c: [f64; 3], v: usize| {
            let e = anchors.canonical[v];
            let dist = ((c[0] - e[0] as f64).powi(2)
                + (c[1] - e[1] as f64).powi(2)
                + (c[2] - e[2] as f64).powi(2))
            .sqrt();
            dist <= tol
        };
        let (mut visible, mut matched, mut mirrored_matched) = (0, 0, 0);
        for (v, p) in verts.iter().enumerate() {
            let q = project(&cam, *p);
            let Some(s) = sample_at(q) else { continue };
            // Visible: the vertex's own depth is the depth drawn there.
            let want_inv = 1.0 / q[2];
            if gb.face[s] == NO_FACE || (gb.inv_depth[s] as f64 - want_inv).abs() > 2e-4 * want_inv
            {
                continue;
            }
            visible += 1;
            matched += canonical_at(s).is_some_and(|c| near(c, v)) as usize;
            let m = [size as f64 - 1.0 - q[0], q[1], q[2]];
            mirrored_matched += sample_at(m)
                .and_then(canonical_at)
                .is_some_and(|c| near(c, v)) as usize;
        }
        eprintln!(
            "{}: {matched}/{visible} visible vertices see their own surface, mirrored \
             {mirrored_matched}",
            r.name
        );
        assert!(
            visible > 1000,
            "{}: only {visible} visible vertices",
            r.name
        );
        assert!(
            matched as f64 >= 0.99 * visible as f64,
            "{}: {matched}/{visible} visible vertices see their own surface (tol {tol:.4})",
            r.name
        );
        assert!(
            (mirrored_matched as f64) < 0.2 * visible as f64,
            "{}: the mirrored projection matches too ({mirrored_matched}/{visible}): the check \
             cannot see a mirror",
            r.name
        );
    }
}

/// The frontal camera (PyTorch3D's `look_at_view_transform(9, 0, 0)` = our yaw pi) sees the
/// face upright and unmirrored: the subject's left eye (joint 3, +x) on the image's right, the
/// top of the head above the mouth, the pupils dark. Yaw 0 of `look_at_origin_matrix` puts the
/// camera behind the head.
#[test]
fn frontal_camera_sees_the_face_upright_and_unmirrored() {
    let size = 128;
    let (g, _) = setup(size);
    let front = Camera::look_at_origin_matrix(9.0, std::f64::consts::PI, 0.0);
    // PyTorch3D's frontal look-at rotation, entry by entry.
    let want = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
    for r in 0..3 {
        for c in 0..3 {
            assert!(
                (front[r][c] - want[r][c]).abs() < 1e-12,
                "R[{r}][{c}] = {}",
                front[r][c]
            );
        }
    }
    let neutral = |tm| FrameSample {
        expression: vec![0.0; 100],
        pose: [0.0; 6],
        eye: [0.0; 6],
        transform: tm,
    };
    let shape = vec![0.0; 300];
    let verts = g.pose(&shape, &[neutral(front)]).unwrap().remove(0);
    let cam = Camera::from_transform_matrix(&front, 12.0, size, size).unwrap();
    let anchors = g.anchors();
    let centre_px = |e: usize| {
        let ids: Vec<usize> = (0..verts.len())
            .filter(|&v| anchors.vertex_material[v] == gagavatar_synthdata::Material::Eye(e as u8))
            .collect();
        let mut c = [0f64; 3];
        for &v in &ids {
            for d in 0..3 {
                c[d] += verts[v][d] as f64 / ids.len() as f64;
            }
        }
        project(&cam, c)
    };
    let (left, right) = (centre_px(0), centre_px(1));
    assert!(
        left[0] > size as f64 / 2.0 && right[0] < size as f64 / 2.0,
        "subject's left eye at x {:.1}, right eye at x {:.1}: mirrored",
        left[0],
        right[0]
    );
    let top = verts
        .iter()
        .map(|v| v.map(f64::from))
        .max_by(|a, b| a[1].total_cmp(&b[1]))
        .unwrap();
    assert!(
        project(&cam, top)[1] < left[1].min(right[1]),
        "the top of the head is not above the eyes: upside down"
    );
    // The pupils are what the camera sees at the eyes' projections.
    let app = g.appearance(0);
    let img = g.shade(&app, &front, &verts).unwrap();
    let brightness = |q: [f64; 3], img: &image::RgbImage| {
        let p = img.get_pixel(q[0].round() as u32, q[1].round() as u32).0;
        (p[0] as f64 + p[1] as f64 + p[2] as f64) / (3.0 * 255.0)
    };
    let pupil = |e: usize| {
        // The front pole of each eyeball: its vertex with the largest z.
        let v = (0..verts.len())
            .filter(|&v| anchors.vertex_material[v] == gagavatar_synthdata::Material::Eye(e as u8))
            .max_by(|&a, &b| verts[a][2].total_cmp(&verts[b][2]))
            .unwrap();
        verts[v].map(f64::from)
    };
    for e in 0..2 {
        let b = brightness(project(&cam, pupil(e)), &img);
        assert!(
            b < 0.12,
            "eye {e}: the pupil's pixel has brightness {b:.3}, not a pupil"
        );
    }
    // The surface drawn at the eyes' projections: eyeballs from the front, skin (the back of
    // the head) from yaw 0.
    let back = Camera::look_at_origin_matrix(9.0, 0.0, 0.0);
    for (tm, want_eye) in [(front, true), (back, false)] {
        let verts = g.pose(&shape, &[neutral(tm)]).unwrap().remove(0);
        let cam = Camera::from_transform_matrix(&tm, 12.0, size, size).unwrap();
        let (_, gb) = g.rasterize(&tm, &verts).unwrap();
        for e in 0..2 {
            let q = project(&cam, pupil(e));
            let s = ((q[1] + 0.5) * gb.ss as f64) as usize * gb.sample_width()
                + ((q[0] + 0.5) * gb.ss as f64) as usize;
            let m = anchors.face_material[gb.face[s] as usize];
            assert_eq!(
                m == gagavatar_synthdata::Material::Eye(e as u8),
                want_eye,
                "camera {tm:?}: eye {e} projects onto {m:?}"
            );
        }
    }
}

/// The front/back decision assumes outward-facing triangles (counter-clockwise seen from
/// outside); the synthetic asset's head must be wound that way.
#[test]
fn synthetic_head_faces_point_outward() {
    let (g, _) = setup(64);
    let a = g.anchors();
    let faces = &g.model().faces;
    let mut outward = 0;
    for (fi, f) in faces.iter().enumerate() {
        let p = f.map(|k| a.canonical[k as usize].map(f64::from));
        let e1 = [0, 1, 2].map(|d| p[1][d] - p[0][d]);
        let e2 = [0, 1, 2].map(|d| p[2][d] - p[0][d]);
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let c = [0, 1, 2].map(|d| (p[0][d] + p[1][d] + p[2][d]) / 3.0);
        // Relative to the part's own centre: eyeballs are spheres, the head is star-shaped
        // about a point on the vertical axis at the face's height.
        let centre = match a.face_material[fi] {
            gagavatar_synthdata::Material::Eye(e) => a.eye_centre[e as usize].map(f64::from),
            gagavatar_synthdata::Material::Skin => [a.crown[0] as f64, c[1], a.crown[2] as f64],
        };
        let d = [0, 1, 2].map(|k| c[k] - centre[k]);
        outward += (n[0] * d[0] + n[1] * d[1] + n[2] * d[2] > 0.0) as usize;
    }
    assert!(
        outward as f64 > 0.97 * faces.len() as f64,
        "{outward} of {} faces point outward",
        faces.len()
    );
}
