//! The compositing's backward on the GPU against the CPU's (`gagavatar_splat::raster::backward`)
//! on the same scenes. On lavapipe the projection and the tile lists are the CPU's bit for bit
//! (the splatting tests), so both backward passes read the same splats; the CPU's is given the
//! GPU forward's per-pixel state, so a transmittance stop that a driver rounds differently
//! (lavapipe does at one pixel in some scenes, see `RASTER_TOL`) cannot make them differ, and
//! that state is checked against the CPU forward's on its own.

use gagavatar_splat::binning::bin;
use gagavatar_splat::project::{project, project_backward, CamK, GEOM};
use gagavatar_splat::raster::{backward, forward, Frame, PixelState};
use gagavatar_splat::testscene::{avatar_scene, Regime, Rng};
use gagavatar_splat::{Camera, GaussianScene};

use super::splat::{GpuSplatGrad, SplatGrads};
use crate::splat::{GpuSplat, SplatInputs};
use crate::testutil::{assert_close_rel as check, gpu};
use crate::{Gpu, Tuning};

/// Each gradient array's worst difference, relative to its largest magnitude: the sums run in
/// other orders (per-tile trees against the CPU's lanes), each term's f32 operations are the
/// same up to fused multiply-adds.
const GRAD_RTOL: f64 = 1e-4;

/// Through the projection: the same operations (a driver may fuse some), the conic's inverse
/// and the clamped Jacobian amplifying an ulp of thin Gaussians' covariances.
const GEOM_RTOL: f64 = 1e-4;

/// Pixels whose forward state (final transmittance or last Gaussian) may differ from the
/// CPU's: a transmittance stop within rounding of 1e-4 (see the splatting's `RASTER_TOL`).
const STATE_FLIPS: usize = 2;

/// A `w x h` camera 9 units from the origin with the focal length (relative to the image)
/// `focal`.
fn small_camera(w: usize, h: usize, focal: f64) -> Camera {
    let tm = Camera::look_at_origin_matrix(9.0, 0.2, -0.1);
    Camera::from_transform_matrix(&tm, focal, w, h).unwrap()
}

/// Random Gaussians in front of the camera: tiny, huge, thin and ordinary ones.
fn random_scene(seed: u64, channels: usize, n: usize) -> GaussianScene {
    let mut rng = Rng::new(seed);
    let mut s = GaussianScene {
        channels,
        ..Default::default()
    };
    for i in 0..n {
        s.means
            .extend([0, 1, 2].map(|_| rng.range(-0.8, 0.8) as f32));
        let scale = match i % 7 {
            0 => [0.4, 0.5, 0.3],
            1 => [1e-3, 2e-3, 1e-3],
            2 => [0.2, 0.004, 0.05],
            _ => [0, 1, 2].map(|_| rng.range(0.01, 0.08)),
        };
        s.scales.extend(scale.map(|v| v as f32));
        s.opacities.push(rng.range(0.05, 1.0) as f32);
        s.rotations
            .extend([0, 1, 2, 3].map(|_| rng.normal() as f32));
        for _ in 0..channels {
            s.features.push(rng.range(-1.0, 2.0) as f32);
        }
    }
    s
}

fn gpu_splat(g: &Gpu, scene: &GaussianScene, bg: &[f32], cam: &Camera, t: &Tuning) -> GpuSplat {
    let inputs = SplatInputs::from_scene(scene, bg);
    GpuSplat::new(g, t, &inputs, None, 0, cam.width, cam.height).unwrap()
}

/// The GPU's training forward and backward of `grad` against the CPU's backward run on the
/// GPU forward's state; the state itself against the CPU forward's. Returns the GPU's
/// gradients.
fn compare(
    label: &str,
    scene: &GaussianScene,
    bg: &[f32],
    cam: &Camera,
    tuning: &Tuning,
    seed: u64,
) -> SplatGrads {
    let g = gpu().expect("a GPU");
    let (c, n) = (scene.channels, scene.len());
    let (w, h) = (cam.width, cam.height);
    let mut rng = Rng::new(seed);
    let grad: Vec<f32> = (0..c * w * h)
        .map(|_| rng.range(-1.0, 1.0) as f32)
        .collect();
    let mut splat = gpu_splat(g, scene, bg, cam, tuning);
    let mut bwd = GpuSplatGrad::new(g, &splat).unwrap();
    let (image, got) = bwd.run(g, &mut splat, cam, &grad).unwrap();
    let state = bwd.read_state(g).unwrap();

    let k = CamK::<f32>::new(cam);
    let geom: Vec<f32> = [
        &scene.means[..],
        &scene.opacities,
        &scene.scales,
        &scene.rotations,
    ]
    .concat();
    let proj = project(&k, &geom);
    let bins = bin(&proj, k.grid_x, k.grid_y);
    let frame = Frame {
        proj: &proj,
        bins: &bins,
        features: &scene.features,
        channels: c,
        background: bg,
        width: w,
        height: h,
    };
    let (cpu_image, cpu_state) = forward(&frame);
    check(&format!("{label}: image"), &cpu_image, &image, 1e-5);
    // The GPU's state in the CPU's terms: list positions within the pixel's tile.
    let grid_x = w.div_ceil(16);
    let ranges = g
        .read_u32(&splat.bins.ranges, 2 * grid_x * h.div_ceil(16))
        .unwrap();
    let mut gpu_state = PixelState {
        final_t: state.final_t.clone(),
        n_contrib: vec![0; w * h],
    };
    let mut flips = 0;
    let mut took = 0;
    for y in 0..h {
        for x in 0..w {
            let (o, tile) = (y * w + x, (y / 16) * grid_x + x / 16);
            let last = state.last[o];
            gpu_state.n_contrib[o] = if last == 0 {
                0
            } else {
                last - ranges[2 * tile]
            };
            took += (last > 0) as usize;
            let same_t = (state.final_t[o] - cpu_state.final_t[o]).abs() <= 1e-6;
            flips += (!same_t || gpu_state.n_contrib[o] != cpu_state.n_contrib[o]) as usize;
        }
    }
    assert!(
        flips <= STATE_FLIPS,
        "{label}: {flips} pixels' forward state differs from the CPU's (at most {STATE_FLIPS})"
    );
    assert!(
        took > w * h / 4,
        "{label}: only {took} pixels took a Gaussian"
    );
    let want = backward(&frame, &gpu_state, &grad, n);
    check(
        &format!("{label}: d features"),
        &want.features,
        &got.features,
        GRAD_RTOL,
    );
    check(
        &format!("{label}: d background"),
        &want.background,
        &got.background,
        GRAD_RTOL,
    );
    let names = [
        "mean x", "mean y", "conic A", "conic B", "conic C", "opacity",
    ];
    for (q, name) in names.iter().enumerate() {
        let pick = |v: &[f32]| -> Vec<f32> { v.iter().skip(q).step_by(6).copied().collect() };
        check(
            &format!("{label}: d {name}"),
            &pick(&want.screen),
            &pick(&got.screen),
            GRAD_RTOL,
        );
    }
    // Through the projection, from the GPU's own screen-space gradients (checked above).
    let mut want = vec![0f32; n * GEOM];
    project_backward(&k, &geom, &got.screen, &proj.radius, &mut want);
    // The CPU's are four blocks, [means (3N) | opacities (N) | scales (3N) | quaternions (4N)];
    // the GPU's a row of 11 per Gaussian.
    let gg = &got.geom;
    let rows = |first: usize, width: usize| -> Vec<f32> {
        (0..n)
            .flat_map(|i| (0..width).map(move |k| gg[i * GEOM + first + k]))
            .collect()
    };
    let blocks = [
        ("mean", 0, 3),
        ("opacity", 3, 1),
        ("scale", 4, 3),
        ("quaternion", 7, 4),
    ];
    let mut at = 0;
    for (name, first, width) in blocks {
        check(
            &format!("{label}: d {name} through the projection"),
            &want[at..at + n * width],
            &rows(first, width),
            GEOM_RTOL,
        );
        at += n * width;
    }
    got
}

/// An avatar-like scene (two planes of Gaussians and a head) on a small camera with partial
/// tiles, at the model's 32 channels, in both size regimes.
#[test]
fn splat_backward_matches_the_cpu() {
    if gpu().is_none() {
        return;
    }
    for regime in [Regime::Small, Regime::Large] {
        let (scene, _) = avatar_scene(20, 300, 32, regime, 3);
        let bg: Vec<f32> = (0..32).map(|c| 0.03 * c as f32 - 0.4).collect();
        compare(
            &format!("avatar {regime:?}"),
            &scene,
            &bg,
            &small_camera(90, 70, 12.0),
            &Tuning::default(),
            7,
        );
    }
}

/// Random tiny, huge and thin Gaussians, 5 channels; the gradients are the same bits on a
/// second run, and with pair buffers too small at first (grown, the backward rebuilt).
#[test]
fn splat_backward_of_odd_scenes_is_reproducible_and_survives_growth() {
    if gpu().is_none() {
        return;
    }
    let scene = random_scene(5, 5, 700);
    let bg = [0.1, -0.2, 0.3, 0.0, 0.5];
    let cam = small_camera(75, 61, 12.0 * 75.0 / 512.0);
    let first = compare("random", &scene, &bg, &cam, &Tuning::default(), 11);
    let again = compare("random again", &scene, &bg, &cam, &Tuning::default(), 11);
    assert!(
        first.features == again.features
            && first.screen == again.screen
            && first.background == again.background,
        "a second run gave other gradients"
    );
    let mut tight = Tuning::default();
    tight.apply("pairs_per_gaussian=0.05").unwrap();
    compare("random, growing pairs", &scene, &bg, &cam, &tight, 11);
}

#[test]
fn splat_backward_refuses_bad_gradients() {
    let Some(g) = gpu() else { return };
    let scene = random_scene(6, 3, 50);
    let cam = small_camera(32, 32, 1.0);
    let mut splat = gpu_splat(g, &scene, &[0.0; 3], &cam, &Tuning::default());
    let mut bwd = GpuSplatGrad::new(g, &splat).unwrap();
    assert!(bwd.run(g, &mut splat, &cam, &[0.0; 7]).is_err());
    let mut nan = vec![0f32; 3 * 32 * 32];
    nan[5] = f32::NAN;
    assert!(bwd.run(g, &mut splat, &cam, &nan).is_err());
}
