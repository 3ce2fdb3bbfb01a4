//! The synthetic asset: release layout, determinism, mesh sanity, and that it exercises the
//! jaw, eyes, landmarks and correctives like the real one.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use gagavatar_flame::synth::{SYNTH_FACES, SYNTH_VERTICES};
use gagavatar_flame::{synthesize, BasisLayout, FlameAsset, FlameConfig, FlameModel, FlameParams};

fn release_shapes() -> Vec<(&'static str, Vec<usize>)> {
    vec![
        ("flame_model.v_template", vec![5023, 3]),
        ("flame_model.f", vec![9976, 3]),
        ("flame_model.shapedirs", vec![5023, 3, 400]),
        ("flame_model.posedirs", vec![5023, 3, 36]),
        ("flame_model.J_regressor", vec![5, 5023]),
        ("flame_model.weights", vec![5023, 5]),
        ("flame_model.kintree_table", vec![2, 5]),
        ("lmk_embeddings.static_lmk_faces_idx", vec![51]),
        ("lmk_embeddings.static_lmk_bary_coords", vec![51, 3]),
        ("lmk_embeddings.dynamic_lmk_faces_idx", vec![79, 17]),
        ("lmk_embeddings.dynamic_lmk_bary_coords", vec![79, 17, 3]),
        ("lmk_embeddings.full_lmk_faces_idx_with_eye", vec![1, 70]),
        (
            "lmk_embeddings.full_lmk_bary_coords_with_eye",
            vec![1, 70, 3],
        ),
    ]
}

#[test]
fn has_the_release_layout_exactly() {
    let a = synthesize(0);
    assert_eq!(a.n_vertices, SYNTH_VERTICES);
    assert_eq!(a.n_faces(), SYNTH_FACES);
    assert_eq!(a.layout, BasisLayout::RELEASE);
    let map = a.to_tensor_map();
    let want = release_shapes();
    assert_eq!(map.len(), want.len());
    for (k, shape) in want {
        assert_eq!(map.get(k).map(|t| t.shape.clone()), Some(shape), "{k}");
    }
    assert_eq!(a.kintree_table[1..5], [0, 1, 1, 1]);
}

#[test]
fn is_deterministic_per_seed() {
    let a = synthesize(11);
    let b = synthesize(11);
    let c = synthesize(12);
    assert!(a == b);
    assert_eq!(a.v_template, c.v_template, "geometry is seed-independent");
    assert_eq!(a.faces, c.faces);
    assert_ne!(a.shapedirs, c.shapedirs);
    assert_ne!(a.posedirs, c.posedirs);
}

fn v(a: &FlameAsset, i: u32) -> [f64; 3] {
    let i = i as usize * 3;
    [
        a.v_template[i] as f64,
        a.v_template[i + 1] as f64,
        a.v_template[i + 2] as f64,
    ]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[test]
fn mesh_is_edge_manifold_oriented_and_non_degenerate() {
    let a = synthesize(0);
    // Directed edge counts: an interior edge appears once in each direction.
    let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
    let mut used = vec![false; a.n_vertices];
    let mut min_area = f64::MAX;
    for f in &a.faces {
        assert!(
            f[0] != f[1] && f[1] != f[2] && f[0] != f[2],
            "repeated vertex in {f:?}"
        );
        for k in 0..3 {
            *directed.entry((f[k], f[(k + 1) % 3])).or_default() += 1;
            used[f[k] as usize] = true;
        }
        let n = cross(sub(v(&a, f[1]), v(&a, f[0])), sub(v(&a, f[2]), v(&a, f[0])));
        min_area = min_area.min(0.5 * dot(n, n).sqrt());
    }
    assert!(used.iter().all(|&u| u), "unreferenced vertex");
    assert!(min_area > 1e-8, "degenerate face: area {min_area:e}");
    let mut boundary = Vec::new();
    for (&(i, j), &n) in &directed {
        assert_eq!(n, 1, "edge {i}->{j} used {n} times in one direction");
        if !directed.contains_key(&(j, i)) {
            boundary.push((i, j));
        }
    }
    // Mouth slit (2 * 16 edges) and two 4x4 sockets (16 each).
    assert_eq!(boundary.len(), 64, "boundary edges");
    // The boundary edges form exactly three closed loops.
    let next: HashMap<u32, u32> = boundary.iter().copied().collect();
    assert_eq!(
        next.len(),
        64,
        "a boundary vertex with two outgoing rim edges"
    );
    let mut seen = std::collections::HashSet::new();
    let mut loops = Vec::new();
    for &(start, _) in &boundary {
        if seen.contains(&start) {
            continue;
        }
        let mut len = 0;
        let mut cur = start;
        loop {
            seen.insert(cur);
            cur = next[&cur];
            len += 1;
            if cur == start {
                break;
            }
            assert!(len <= 64, "boundary does not close");
        }
        loops.push(len);
    }
    loops.sort();
    assert_eq!(loops, vec![16, 16, 32]);
    // Orientation is outward: positive enclosed volume (the eyeballs are closed; the head's
    // holes are small).
    let mut volume = 0.0;
    for f in &a.faces {
        volume += dot(v(&a, f[0]), cross(v(&a, f[1]), v(&a, f[2]))) / 6.0;
    }
    assert!(volume > 1e-3, "volume {volume}");
}

#[test]
fn skinning_regressor_and_landmarks_are_well_formed() {
    let a = synthesize(0);
    for (i, row) in a.weights.chunks(5).enumerate() {
        let s: f32 = row.iter().sum();
        assert!(
            (s - 1.0).abs() < 1e-5 && row.iter().all(|&w| w >= 0.0),
            "weights row {i}: {row:?}"
        );
    }
    let nv = a.n_vertices;
    let mut joints = [[0.0f64; 3]; 5];
    for (j, joint) in joints.iter_mut().enumerate() {
        let row = &a.j_regressor[j * nv..(j + 1) * nv];
        let s: f32 = row.iter().sum();
        assert!((s - 1.0).abs() < 1e-4, "J_regressor row {j} sums to {s}");
        for (vi, &w) in row.iter().enumerate() {
            for (c, jc) in joint.iter_mut().enumerate() {
                *jc += w as f64 * a.v_template[vi * 3 + c] as f64;
            }
        }
    }
    let [global, neck, jaw, eye_l, eye_r] = joints;
    assert!(
        global[1] < neck[1] && neck[1] < jaw[1] && jaw[1] < eye_l[1],
        "{joints:?}"
    );
    assert!(
        (eye_l[0] + eye_r[0]).abs() < 1e-6 && eye_l[0] > 0.02,
        "eyes at ±x: {eye_l:?} {eye_r:?}"
    );
    assert!(eye_l[2] > 0.05, "eyes at the front: {eye_l:?}");
    // Head size: about 0.16-0.22 wide before the x5.
    let xs: Vec<f32> = a.v_template.chunks(3).map(|p| p[0]).collect();
    let width =
        xs.iter().cloned().fold(f32::MIN, f32::max) - xs.iter().cloned().fold(f32::MAX, f32::min);
    assert!((0.15..0.25).contains(&width), "width {width}");
    let lm = &a.landmarks;
    for b in lm
        .static_bary
        .iter()
        .chain(&lm.dynamic_bary)
        .chain(&lm.full_bary)
    {
        assert!(
            (b.iter().sum::<f32>() - 1.0).abs() < 1e-5 && b.iter().all(|&x| x >= -1e-6),
            "{b:?}"
        );
    }
    // Distinct contour per yaw: row 0 vs row 30 vs row 69.
    let row = |r: usize| &lm.dynamic_faces[r * 17..(r + 1) * 17];
    assert_ne!(row(0), row(30));
    assert_ne!(row(30), row(69));
}

fn model() -> (FlameAsset, FlameModel) {
    let a = synthesize(0);
    let m = FlameModel::new(&a, FlameConfig::default(), &Device::Cpu, DType::F64).unwrap();
    (a, m)
}

type Rows = Vec<Vec<f64>>;

fn run(m: &FlameModel, pose: [f64; 6], eye: [f64; 6]) -> (Rows, Rows, Rows) {
    let mut p = FlameParams::zeros(m, 1).unwrap();
    p.pose = Tensor::from_vec(pose.to_vec(), (1, 6), &m.device).unwrap();
    p.eye = Tensor::from_vec(eye.to_vec(), (1, 6), &m.device).unwrap();
    let out = m.forward(&p).unwrap();
    let lm = m.landmarks(&out.vertices, &p.pose).unwrap();
    (
        out.vertices.squeeze(0).unwrap().to_vec2().unwrap(),
        lm.lmk68.squeeze(0).unwrap().to_vec2().unwrap(),
        lm.full.squeeze(0).unwrap().to_vec2().unwrap(),
    )
}

#[test]
fn jaw_opens_the_mouth() {
    let (a, m) = model();
    let (v0, l0, _) = run(&m, [0.0; 6], [0.0; 6]);
    let (v1, l1, _) = run(&m, [0.0, 0.0, 0.0, 0.3, 0.0, 0.0], [0.0; 6]);
    // iBUG 62 / 66: inner upper / lower lip centre.
    let (up, low) = (62, 66);
    assert!(
        l1[low][1] < l0[low][1] - 0.05,
        "lower lip y {} -> {}",
        l0[low][1],
        l1[low][1]
    );
    assert!(
        (l1[up][1] - l0[up][1]).abs() < 0.01,
        "upper lip y {} -> {}",
        l0[up][1],
        l1[up][1]
    );
    let gap = |l: &Vec<Vec<f64>>| l[up][1] - l[low][1];
    assert!(
        gap(&l1) > gap(&l0) + 0.05,
        "mouth gap {} -> {}",
        gap(&l0),
        gap(&l1)
    );
    // Every vertex fully on the jaw moves; the skull does not.
    let moved = |i: usize| {
        (0..3)
            .map(|c| (v1[i][c] - v0[i][c]).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    for i in 0..a.n_vertices {
        let w = &a.weights[i * 5..i * 5 + 5];
        if w[2] > 0.999 {
            assert!(moved(i) > 1e-3, "jaw vertex {i} did not move");
        }
        if w[1] > 0.999 && a.posedirs[i * 108..(i + 1) * 108].iter().all(|&x| x == 0.0) {
            assert!(moved(i) < 1e-9, "skull vertex {i} moved by {}", moved(i));
        }
    }
}

#[test]
fn eyes_rotate_rigidly_about_their_joints() {
    let (a, m) = model();
    let (v0, _, f0) = run(&m, [0.0; 6], [0.0; 6]);
    // Joint 3 (the +x eye) turns about y; joint 4 stays.
    let (v1, _, f1) = run(&m, [0.0; 6], [0.0, 0.4, 0.0, 0.0, 0.0, 0.0]);
    let (left_pupil, right_pupil) = (69, 68);
    let dx = f1[left_pupil][0] - f0[left_pupil][0];
    let expected = 5.0 * 0.0115 * 0.4f64.sin();
    assert!(
        (dx - expected).abs() < 1e-3,
        "pupil moved {dx}, expected ~{expected}"
    );
    for c in 0..3 {
        assert!((f1[right_pupil][c] - f0[right_pupil][c]).abs() < 1e-12);
    }
    // Eyeball vertices keep their distance to the eyeball centre.
    let eye: Vec<usize> = (0..a.n_vertices)
        .filter(|&i| a.weights[i * 5 + 3] > 0.999)
        .collect();
    assert_eq!(eye.len(), 146);
    let centre = |vs: &Vec<Vec<f64>>| -> [f64; 3] {
        std::array::from_fn(|c| eye.iter().map(|&i| vs[i][c]).sum::<f64>() / eye.len() as f64)
    };
    let (c0, c1) = (centre(&v0), centre(&v1));
    for &i in &eye {
        let r0: f64 = (0..3)
            .map(|c| (v0[i][c] - c0[c]).powi(2))
            .sum::<f64>()
            .sqrt();
        let r1: f64 = (0..3)
            .map(|c| (v1[i][c] - c1[c]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(
            (r0 - r1).abs() < 1e-9 && (r0 - 5.0 * 0.0115).abs() < 1e-6,
            "vertex {i}: {r0} -> {r1}"
        );
    }
}

#[test]
fn blendshapes_deform_smoothly_and_expression_spares_the_skull() {
    let a = synthesize(0);
    let k = 400;
    let mut max_shape = 0.0f32;
    for vi in 0..a.n_vertices {
        for c in 0..3 {
            let row = &a.shapedirs[(vi * 3 + c) * k..(vi * 3 + c + 1) * k];
            max_shape = max_shape.max(row[0].abs());
            // Top of the skull (y > 0.09) carries no expression.
            if a.v_template[vi * 3 + 1] > 0.09 {
                assert!(
                    row[300..].iter().all(|&x| x == 0.0),
                    "expression on the skull at {vi}"
                );
            }
        }
    }
    assert!(
        (1e-3..2e-2).contains(&max_shape),
        "first shape component peak {max_shape}"
    );
    assert!(a.posedirs.iter().any(|&x| x != 0.0));
}

/// The 70-point `_with_eye` set is laid out like iBUG 68 + two pupils on the neutral head seen
/// from the front (FLAME -x is image-left, +y is up), so a landmark fitter finds on the
/// synthetic head the structure it finds on a real one.
#[test]
fn with_eye_landmarks_follow_the_ibug_layout() {
    let (_, m) = model();
    let (_, _, f) = run(&m, [0.0; 6], [0.0; 6]);
    assert_eq!(f.len(), 70);
    let (x, y) = (|i: usize| f[i][0], |i: usize| f[i][1]);
    // Left-to-right runs in image order (increasing x).
    for run in [
        (0..=8).collect::<Vec<_>>(),
        (8..=16).collect(),
        (17..=21).collect(),
        (22..=26).collect(),
        (31..=35).collect(),
        vec![36, 37, 38, 39],
        vec![42, 43, 44, 45],
        vec![48, 49, 50, 51, 52, 53, 54],
        vec![60, 61, 62, 63, 64],
    ] {
        for w in run.windows(2) {
            assert!(
                x(w[0]) < x(w[1]),
                "x[{}] {} >= x[{}] {}",
                w[0],
                x(w[0]),
                w[1],
                x(w[1])
            );
        }
    }
    // Mirror pairs (contour, brows, eye corners, mouth corners) sit at opposite x.
    for (a, b) in [(0, 16), (17, 26), (36, 45), (39, 42), (48, 54), (68, 69)] {
        assert!(
            (x(a) + x(b)).abs() < 0.02,
            "pair {a}/{b}: x {} {}",
            x(a),
            x(b)
        );
        assert!(x(a) < 0.0, "{a} should be on the subject's right (-x)");
    }
    // Pupils between their eye corners, at eye height.
    for (p, outer, inner) in [(68, 36, 39), (69, 45, 42)] {
        let (lo, hi) = (x(outer).min(x(inner)), x(outer).max(x(inner)));
        assert!(
            lo < x(p) && x(p) < hi,
            "pupil {p} x {} not in ({lo}, {hi})",
            x(p)
        );
        assert!(
            (y(p) - y(outer)).abs() < 0.05,
            "pupil {p} y {} vs {}",
            y(p),
            y(outer)
        );
    }
    // Top to bottom: brows, eyes, nose bridge to tip, mouth, chin.
    let chain = [19, 37, 27, 30, 33, 51, 62, 66, 57, 8];
    for w in chain.windows(2) {
        assert!(
            y(w[0]) > y(w[1]),
            "y[{}] {} <= y[{}] {}",
            w[0],
            y(w[0]),
            w[1],
            y(w[1])
        );
    }
    // The nose tip stands out in front of the eyes.
    assert!(
        f[30][2] > f[39][2] + 0.05,
        "nose tip z {} vs eye z {}",
        f[30][2],
        f[39][2]
    );
}

/// `BasisMotion::RigidFree` changes each identity basis by a rigid motion only (on the head
/// surface; eyeballs follow their centres), and `AsDrawn` is the plain asset.
#[test]
// Gauss-Jordan reads and writes two rows of one matrix by index.
#[allow(clippy::needless_range_loop)]
fn rigid_free_bases_differ_by_rigid_motions() {
    use gagavatar_flame::{synthesize_with, BasisMotion};
    let a = synthesize(0);
    assert_eq!(synthesize_with(0, BasisMotion::AsDrawn), a);
    let b = synthesize_with(0, BasisMotion::RigidFree);
    assert_eq!(b.v_template, a.v_template);
    let k_total = 400;
    let head = 4731; // head vertices come first (see synth.rs)
    let mut changed = 0;
    for k in [0usize, 1, 7, 50, 299] {
        // Fit d(v) = t + w x v by least squares over the head's vertices; the residual must be
        // at float32 rounding of the bases.
        let mut rows: Vec<([f64; 6], f64)> = Vec::new();
        let mut max_d: f64 = 0.0;
        for i in 0..head {
            let p = v(&a, i as u32);
            for c in 0..3 {
                let d = (a.shapedirs[(i * 3 + c) * k_total + k]
                    - b.shapedirs[(i * 3 + c) * k_total + k]) as f64;
                max_d = max_d.max(d.abs());
                let mut m = [0.0; 6];
                m[c] = 1.0;
                // (w x p)_c
                match c {
                    0 => {
                        m[4] = p[2];
                        m[5] = -p[1];
                    }
                    1 => {
                        m[3] = -p[2];
                        m[5] = p[0];
                    }
                    _ => {
                        m[3] = p[1];
                        m[4] = -p[0];
                    }
                }
                rows.push((m, d));
            }
        }
        let mut ata = [[0.0f64; 6]; 6];
        let mut atb = [0.0f64; 6];
        for (m, d) in &rows {
            for i in 0..6 {
                atb[i] += m[i] * d;
                for j in 0..6 {
                    ata[i][j] += m[i] * m[j];
                }
            }
        }
        // Gauss-Jordan on the 6x6 (well conditioned: the head spans all six motions).
        let mut x = atb;
        for col in 0..6 {
            let piv = ata[col][col];
            for j in 0..6 {
                ata[col][j] /= piv;
            }
            x[col] /= piv;
            for r in 0..6 {
                if r != col {
                    let f = ata[r][col];
                    for j in 0..6 {
                        ata[r][j] -= f * ata[col][j];
                    }
                    x[r] -= f * x[col];
                }
            }
        }
        let resid = rows
            .iter()
            .map(|(m, d)| (d - (0..6).map(|i| m[i] * x[i]).sum::<f64>()).abs())
            .fold(0.0, gagavatar_testkit::max_or_nan);
        assert!(
            resid < 1e-6,
            "basis {k}: non-rigid change {resid:e} (change up to {max_d:e})"
        );
        if max_d > 1e-5 {
            changed += 1;
        }
    }
    assert!(
        changed >= 4,
        "the rigid parts removed are not visible ({changed} of 5 bases)"
    );
}
