//! Exact nearest neighbours (k-d tree vs brute force, bit for bit) and the lifting loss (value
//! against the reference, gradient against f64 central differences).

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::*;
use gagavatar_train::nearest::{lifting_loss, nearest_brute_force, nearest_indices, KdTree};

/// f32 loss against the f64 reference (relative).
const TOL_LOSS: f64 = 1e-5;
/// f32 gradient against the f64 reference (relative to the largest entry).
const TOL_GRAD: f64 = 1e-5;
/// f64 analytic gradient against f64 central differences (the loss is quadratic between index
/// changes, so only rounding remains).
const TOL_FD: f64 = 1e-7;

fn check_exact(name: &str, points: &[[f32; 3]], queries: &[[f32; 3]]) {
    let tree = KdTree::new(points).unwrap();
    let got = tree.nearest_all(queries).unwrap();
    for (qi, (q, g)) in queries.iter().zip(&got).enumerate() {
        let want = nearest_brute_force(points, q).unwrap();
        assert!(
            g.0 == want.0 && g.1.to_bits() == want.1.to_bits(),
            "{name}: query {qi} {q:?}: expected (index {}, d2 {}), got (index {}, d2 {})",
            want.0,
            want.1,
            g.0,
            g.1
        );
    }
}

fn random_points(rng: &mut Rng, n: usize, lo: f64, hi: f64) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| [0, 1, 2].map(|_| rng.range(lo, hi) as f32))
        .collect()
}

#[test]
fn uniform_cube() {
    let mut rng = Rng::from_state(1);
    let pts = random_points(&mut rng, 20_000, -1.0, 1.0);
    let qs = random_points(&mut rng, 3_000, -1.2, 1.2);
    check_exact("uniform", &pts, &qs);
}

#[test]
fn duplicates_and_ties() {
    let mut rng = Rng::from_state(2);
    // Each point repeated 7 times at scattered indices: ties must go to the lowest index.
    let base = random_points(&mut rng, 500, -1.0, 1.0);
    let mut pts = Vec::new();
    for _ in 0..7 {
        pts.extend_from_slice(&base);
    }
    for i in (1..pts.len()).rev() {
        let j = (rng.next_u64() % (i as u64 + 1)) as usize;
        pts.swap(i, j);
    }
    let mut qs = random_points(&mut rng, 1_000, -1.0, 1.0);
    qs.extend_from_slice(&base[..200]); // queries exactly on points (distance 0)
                                        // Queries equidistant from two grid points (exact halves).
    qs.extend((0..50).map(|i| [i as f32 * 0.25 + 0.125, 0.0, 0.0]));
    pts.extend((0..50).map(|i| [i as f32 * 0.25, 0.0, 0.0]));
    check_exact("duplicates", &pts, &qs);
    // All points identical.
    let same = vec![[0.3f32, -0.2, 0.1]; 1_000];
    check_exact("identical", &same, &random_points(&mut rng, 100, -1.0, 1.0));
    let tree = KdTree::new(&same).unwrap();
    assert_eq!(
        tree.nearest(&[5.0, 5.0, 5.0]).0,
        0,
        "lowest index among identical points"
    );
}

#[test]
fn clusters_planes_and_far_queries() {
    let mut rng = Rng::from_state(3);
    // Tight clusters plus outliers.
    let mut pts = Vec::new();
    for _ in 0..40 {
        let c = [0, 1, 2].map(|_| rng.range(-10.0, 10.0));
        for _ in 0..300 {
            pts.push([0, 1, 2].map(|a| (c[a] + 1e-3 * rng.normal()) as f32));
        }
    }
    pts.extend(random_points(&mut rng, 50, -100.0, 100.0));
    let mut qs = random_points(&mut rng, 1_500, -12.0, 12.0);
    qs.extend(random_points(&mut rng, 200, 1e3, 1e4)); // far away
    qs.extend(random_points(&mut rng, 200, -1e4, -1e3));
    check_exact("clusters", &pts, &qs);
    // Two lifted-like planes: a regular grid (many equal coordinates) pushed along the view axis.
    let s = 120;
    let mut planes = Vec::new();
    for sign in [1.0f64, -1.0] {
        for i in 0..s {
            for j in 0..s {
                let (u, v) = (
                    1.0 - 2.0 * j as f64 / (s - 1) as f64,
                    1.0 - 2.0 * i as f64 / (s - 1) as f64,
                );
                let d = sign * 0.3 * rng.uniform();
                planes.push([u as f32, v as f32, (2.0 + d) as f32]);
            }
        }
    }
    let head: Vec<[f32; 3]> = (0..3_000)
        .map(|_| {
            let (t, p) = (
                rng.range(0.0, std::f64::consts::PI),
                rng.range(0.0, 2.0 * std::f64::consts::PI),
            );
            [
                (0.8 * t.sin() * p.cos()) as f32,
                (0.9 * t.cos()) as f32,
                (2.0 + 0.6 * t.sin() * p.sin()) as f32,
            ]
        })
        .collect();
    check_exact("planes", &planes, &head);
    // Collinear points and a single point.
    let line: Vec<[f32; 3]> = (0..1000).map(|i| [i as f32 * 1e-3, 0.0, 0.0]).collect();
    check_exact("line", &line, &random_points(&mut rng, 300, -0.5, 1.5));
    check_exact(
        "single",
        &[[1.0, 2.0, 3.0]],
        &random_points(&mut rng, 10, -5.0, 5.0),
    );
}

#[test]
fn bad_sets_are_errors() {
    assert!(KdTree::new(&[]).unwrap_err().to_string().contains("empty"));
    let e = KdTree::new(&[[0.0, 0.0, 0.0], [f32::NAN, 0.0, 0.0]])
        .unwrap_err()
        .to_string();
    assert!(e.contains("point 1"), "{e}");
    let tree = KdTree::new(&[[0.0, 0.0, 0.0]]).unwrap();
    assert!(tree.nearest_all(&[[0.0, f32::INFINITY, 0.0]]).is_err());
    let dev = Device::Cpu;
    let z = |d: &[usize]| Tensor::zeros(d, DType::F32, &dev).unwrap();
    for (l, t, what) in [
        (z(&[2, 0, 3]), z(&[2, 5, 3]), "empty"),
        (z(&[2, 4, 3]), z(&[2, 0, 3]), "empty"),
        (z(&[2, 4, 2]), z(&[2, 5, 3]), "[B, N, 3]"),
        (z(&[2, 4, 3]), z(&[3, 5, 3]), "batch"),
        (z(&[4, 3]), z(&[5, 3]), "[B, N, 3]"),
    ] {
        let e = lifting_loss(&l, &t).unwrap_err().to_string();
        assert!(
            e.contains(what),
            "{:?} vs {:?}: expected `{what}` in `{e}`",
            l.dims(),
            t.dims()
        );
    }
    let mut v = vec![0f32; 2 * 4 * 3];
    v[13] = f32::NAN;
    let nan = Tensor::from_vec(v, (2, 4, 3), &dev).unwrap();
    let e = lifting_loss(&nan, &z(&[2, 5, 3])).unwrap_err().to_string();
    assert!(e.contains("lifted points[1]"), "{e}");
}

#[test]
fn golden_lifting_loss() {
    let io = load("losses.safetensors");
    let lifted = Var::from_tensor(get(&io, "lifted")).unwrap();
    let targets = get(&io, "targets");
    let loss = lifting_loss(lifted.as_tensor(), targets).unwrap();
    assert_eq!(loss.dtype(), DType::F32);
    assert_close(
        "point loss",
        &loss.reshape(1).unwrap(),
        &get(&io, "point").reshape(1).unwrap(),
        TOL_LOSS,
    );
    let g = loss.backward().unwrap();
    // Only the point term depends on the lifted points, so the total's gradient is its own.
    assert_close_to_max(
        "point gradient",
        g.get(lifted.as_tensor()).unwrap(),
        get(&io, "grad_lifted"),
        TOL_GRAD,
    );
}

#[test]
fn gradient_matches_finite_differences() {
    let mut rng = Rng::from_state(9);
    let (b, n, m) = (2, 60, 25);
    let lv: Vec<f64> = (0..b * n * 3).map(|_| rng.normal()).collect();
    let tv: Vec<f64> = (0..b * m * 3).map(|_| 0.7 * rng.normal()).collect();
    let dev = Device::Cpu;
    let targets = Tensor::from_vec(tv, (b, m, 3), &dev).unwrap();
    let lifted = Var::from_tensor(&Tensor::from_vec(lv.clone(), (b, n, 3), &dev).unwrap()).unwrap();
    let loss = lifting_loss(lifted.as_tensor(), &targets).unwrap();
    assert_eq!(loss.dtype(), DType::F64);
    let grad = to_f64(loss.backward().unwrap().get(lifted.as_tensor()).unwrap());
    let eval = |v: &[f64]| -> f64 {
        let t = Tensor::from_vec(v.to_vec(), (b, n, 3), &dev).unwrap();
        scalar(&lifting_loss(&t, &targets).unwrap())
    };
    let h = 1e-6;
    let mut fd = vec![0.0; lv.len()];
    for (i, f) in fd.iter_mut().enumerate() {
        let (mut p, mut q) = (lv.clone(), lv.clone());
        p[i] += h;
        q[i] -= h;
        *f = (eval(&p) - eval(&q)) / (2.0 * h);
    }
    let used = grad.iter().filter(|g| **g != 0.0).count();
    assert!(
        used > 10,
        "some lifted points must be nearest to a target ({used})"
    );
    let scale = fd.iter().fold(0f64, |a, v| a.max(v.abs()));
    for (i, (g, f)) in grad.iter().zip(&fd).enumerate() {
        assert!(
            (g - f).abs() <= TOL_FD * scale.max(1.0),
            "coordinate {i}: finite difference {f}, backward {g}"
        );
    }
    // The nearest-index search itself, per sample.
    let nn = nearest_indices(lifted.as_tensor(), &targets).unwrap();
    assert_eq!((nn.len(), nn[0].len()), (b, m));
}
