//! Deterministic synthetic scenes for benchmarks, tests and examples (seeded by [`Rng`], so
//! they are identical everywhere).

use crate::camera::Camera;
use crate::scene::GaussianScene;

pub use crate::rng::Rng;

/// Size regime of the avatar-like benchmark scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Regime {
    /// World scales around 0.005 (a few pixels at 512x512).
    Small,
    /// World scales around 0.025 (about 30 px radius).
    Large,
}

/// The avatar-like scene of the benchmarks: two lifted planes of `plane x plane` points (one
/// in front of and one behind the head-centre plane, like the dual-lifting branch) plus
/// `head` points on an ellipsoid, seen by a camera at distance 9 with focal 12.
pub fn avatar_scene(
    plane: usize,
    head: usize,
    channels: usize,
    regime: Regime,
    seed: u64,
) -> (GaussianScene, Camera) {
    let mut rng = Rng::new(seed);
    let base = match regime {
        Regime::Small => 0.005,
        Regime::Large => 0.025,
    };
    let tm = Camera::look_at_origin_matrix(9.0, 0.0, 0.0);
    let cam = Camera::from_transform_matrix(&tm, 12.0, 512, 512).expect("valid camera");
    let mut s = GaussianScene {
        channels,
        ..Default::default()
    };
    let push = |s: &mut GaussianScene, rng: &mut Rng, p: [f64; 3], quat_scale: f64| {
        s.means.extend(p.iter().map(|&v| v as f32));
        // A smooth colour pattern in the first three channels so renders are readable; the
        // remaining channels are noise like untrained latent features.
        for ch in 0..channels {
            let v = if ch < 3 {
                0.5 + 0.45 * (4.0 * p[0] + 2.1 * ch as f64 + 3.0 * p[1] * p[1] + 5.0 * p[2]).sin()
            } else {
                rng.range(0.0, 1.0)
            };
            s.features.push(v as f32);
        }
        s.opacities.push(rng.range(0.2, 0.95) as f32);
        for _ in 0..3 {
            s.scales.push((base * rng.range(0.5, 1.5)) as f32);
        }
        let q: Vec<f64> = (0..4).map(|_| rng.normal()).collect();
        let n = q.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12);
        s.rotations
            .extend(q.iter().map(|x| (x / n * quat_scale) as f32));
    };
    // The plane spans the view at the head-centre depth: half-width 9/12 = 0.75.
    for side in [1.0, -1.0] {
        for i in 0..plane {
            for j in 0..plane {
                let u = 1.0 - 2.0 * j as f64 / (plane - 1).max(1) as f64;
                let v = 1.0 - 2.0 * i as f64 / (plane - 1).max(1) as f64;
                let r2 = u * u + v * v;
                // Lifted towards (front) or away from (back) the camera, more near the centre.
                let lift = side * 0.4 * (-2.0 * r2).exp() * rng.range(0.5, 1.0);
                let p = [u * 0.75, v * 0.75, -lift];
                push(&mut s, &mut rng, p, 1.0);
            }
        }
    }
    for _ in 0..head {
        let d: Vec<f64> = (0..3).map(|_| rng.normal()).collect();
        let n = d.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12);
        let p = [d[0] / n * 0.45, d[1] / n * 0.6, d[2] / n * 0.5];
        // The release's expression-branch quaternions are normalised across points: tiny.
        push(&mut s, &mut rng, p, 0.014);
    }
    (s, cam)
}
