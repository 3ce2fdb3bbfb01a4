//! Invariants (empty scenes, culled Gaussians, determinism, batching, file round trips) and
//! bad inputs that must come back as typed errors.

use candle_core::{DType, Device, Tensor, Var};
use gagavatar_splat::testscene::{avatar_scene, Regime};
use gagavatar_splat::{splat, Camera, GaussianScene, Gaussians, SplatError, SplatOutput};

fn cam(w: usize, h: usize, yaw: f64) -> Camera {
    Camera::from_transform_matrix(&Camera::look_at_origin_matrix(9.0, yaw, 0.1), 12.0, w, h)
        .unwrap()
}

fn small_scene() -> GaussianScene {
    avatar_scene(24, 300, 5, Regime::Large, 3).0
}

fn run(s: &GaussianScene, bg: &[f32], cams: &[Camera]) -> Result<SplatOutput, SplatError> {
    let tensors = s.to_tensors(&Device::Cpu).unwrap();
    let bg = Tensor::from_slice(bg, bg.len(), &Device::Cpu).unwrap();
    splat(&Gaussians::from_tensors(&tensors), &bg, cams)
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

#[test]
fn no_gaussians_gives_background() {
    let s = GaussianScene {
        channels: 3,
        ..Default::default()
    };
    let out = run(&s, &[0.1, 0.5, -2.0], &[cam(37, 21, 0.0)]).unwrap();
    assert_eq!(out.image.dims(), [1, 3, 21, 37]);
    let img = flat(&out.image);
    for (i, v) in img.iter().enumerate() {
        let want = [0.1, 0.5, -2.0][i / (21 * 37)];
        assert_eq!(*v, want, "pixel {i}: expected {want}, got {v}");
    }
    assert!(flat(&out.transmittance).iter().all(|&t| t == 1.0));
    assert_eq!(out.tile_pairs, vec![0]);
}

#[test]
fn culled_gaussians_change_nothing() {
    let s = small_scene();
    let c = cam(64, 48, 0.2);
    let base = run(&s, &[0.0; 5], std::slice::from_ref(&c)).unwrap();
    let mut more = s.clone();
    // Behind the camera, inside the near cull distance, far off screen, and with zero opacity.
    let centre = c.center();
    let extra: [([f32; 3], f32); 4] = [
        ([0.0, 0.0, -20.0], 0.9),
        (
            [
                centre[0] as f32 * 0.99,
                centre[1] as f32 * 0.99,
                centre[2] as f32 * 0.99,
            ],
            0.9,
        ),
        ([50.0, 0.0, 0.0], 0.9),
        ([0.0, 0.0, 0.0], 0.0),
    ];
    for (p, o) in extra {
        more.means.extend(p);
        more.features.extend([9.0f32; 5]);
        more.opacities.push(o);
        more.scales.extend([0.05f32; 3]);
        more.rotations.extend([1.0f32, 0.0, 0.0, 0.0]);
    }
    let out = run(&more, &[0.0; 5], &[c]).unwrap();
    assert_eq!(flat(&base.image), flat(&out.image));
    let radii: Vec<u32> = out.radii.flatten_all().unwrap().to_vec1().unwrap();
    let n = s.len();
    assert_eq!(
        &radii[n..n + 3],
        &[0, 0, 0],
        "the first three extras must be culled"
    );
}

fn forward_and_grads(s: &GaussianScene, c: &Camera) -> (Vec<f32>, Vec<Vec<f32>>) {
    let [m, f, o, sc, r] = s.to_tensors(&Device::Cpu).unwrap();
    let vars: Vec<Var> = [m, f, o, sc, r]
        .iter()
        .map(|t| Var::from_tensor(t).unwrap())
        .collect();
    let bg = Var::from_tensor(&Tensor::new(&[0.2f32, 0.1, 0.0, 0.3, 0.4], &Device::Cpu).unwrap())
        .unwrap();
    let out = splat(
        &Gaussians {
            means: vars[0].as_tensor(),
            features: vars[1].as_tensor(),
            opacities: vars[2].as_tensor(),
            scales: vars[3].as_tensor(),
            rotations: vars[4].as_tensor(),
        },
        bg.as_tensor(),
        std::slice::from_ref(c),
    )
    .unwrap();
    let weights = Tensor::arange(0f32, out.image.elem_count() as f32, &Device::Cpu)
        .unwrap()
        .reshape(out.image.dims())
        .unwrap()
        .sin()
        .unwrap();
    let grads = (out.image.clone() * weights)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let mut g: Vec<Vec<f32>> = vars
        .iter()
        .map(|v| flat(grads.get(v.as_tensor()).unwrap()))
        .collect();
    g.push(flat(grads.get(bg.as_tensor()).unwrap()));
    (flat(&out.image), g)
}

#[test]
fn bit_identical_across_runs_and_thread_counts() {
    let s = small_scene();
    let c = cam(70, 50, -0.1);
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    let a = pool(1).install(|| forward_and_grads(&s, &c));
    let b = pool(2).install(|| forward_and_grads(&s, &c));
    let again = pool(2).install(|| forward_and_grads(&s, &c));
    assert!(
        a.0.iter().any(|&v| v != 0.0),
        "the scene must render something"
    );
    assert_eq!(a.0, b.0, "forward differs between 1 and 2 threads");
    assert_eq!(a.1, b.1, "gradients differ between 1 and 2 threads");
    assert_eq!(b, again, "two runs differ");
}

#[test]
fn batch_equals_single_calls() {
    let s = small_scene();
    let (c1, c2) = (cam(40, 30, 0.3), cam(40, 30, -0.4));
    let [m, f, o, sc, r] = s.to_tensors(&Device::Cpu).unwrap();
    let two = |t: &Tensor| Tensor::stack(&[t, t], 0).unwrap();
    let bg = Tensor::new(&[[0.0f32; 5], [1.0; 5]], &Device::Cpu).unwrap();
    let out = splat(
        &Gaussians {
            means: &two(&m),
            features: &two(&f),
            opacities: &two(&o),
            scales: &two(&sc),
            rotations: &two(&r),
        },
        &bg,
        &[c1.clone(), c2.clone()],
    )
    .unwrap();
    let one = run(&s, &[0.0; 5], &[c1]).unwrap();
    let other = run(&s, &[1.0; 5], &[c2]).unwrap();
    assert_eq!(flat(&out.image.get(0).unwrap()), flat(&one.image));
    assert_eq!(flat(&out.image.get(1).unwrap()), flat(&other.image));
    assert_eq!(out.tile_pairs, vec![one.tile_pairs[0], other.tile_pairs[0]]);
}

#[test]
fn non_finite_inputs_are_errors() {
    let c = cam(16, 16, 0.0);
    for (field, idx, value) in [
        (0, 4, f32::NAN),
        (1, 2, f32::INFINITY),
        (2, 0, f32::NAN),
        (3, 1, f32::NEG_INFINITY),
        (4, 3, f32::NAN),
    ] {
        let mut s = small_scene();
        let v = match field {
            0 => &mut s.means,
            1 => &mut s.features,
            2 => &mut s.opacities,
            3 => &mut s.scales,
            _ => &mut s.rotations,
        };
        v[idx] = value;
        match run(&s, &[0.0; 5], std::slice::from_ref(&c)) {
            Err(SplatError::NonFinite { index, .. }) => assert_eq!(index, idx),
            other => panic!("field {field}: expected NonFinite, got {other:?}"),
        }
    }
    let s = small_scene();
    assert!(matches!(
        run(&s, &[0.0, 0.0, f32::NAN, 0.0, 0.0], &[c]),
        Err(SplatError::NonFinite { .. })
    ));
}

#[test]
fn bad_shapes_sizes_and_batches_are_errors() {
    let s = small_scene();
    let n = s.len();
    let dev = Device::Cpu;
    let [m, f, o, sc, r] = s.to_tensors(&dev).unwrap();
    let bg = Tensor::zeros(5, DType::F32, &dev).unwrap();
    let c = cam(16, 16, 0.0);
    let call = |g: Gaussians, bg: &Tensor, cams: &[Camera]| splat(&g, bg, cams);
    let rot3 = r.narrow(1, 0, 3).unwrap();
    let short_f = f.narrow(0, 0, n - 1).unwrap();
    let cases: Vec<(&str, Result<SplatOutput, SplatError>)> = vec![
        (
            "rotations k=3",
            call(
                Gaussians {
                    means: &m,
                    features: &f,
                    opacities: &o,
                    scales: &sc,
                    rotations: &rot3,
                },
                &bg,
                std::slice::from_ref(&c),
            ),
        ),
        (
            "features N-1",
            call(
                Gaussians {
                    means: &m,
                    features: &short_f,
                    opacities: &o,
                    scales: &sc,
                    rotations: &r,
                },
                &bg,
                std::slice::from_ref(&c),
            ),
        ),
        (
            "background C-1",
            call(
                Gaussians {
                    means: &m,
                    features: &f,
                    opacities: &o,
                    scales: &sc,
                    rotations: &r,
                },
                &bg.narrow(0, 0, 4).unwrap(),
                std::slice::from_ref(&c),
            ),
        ),
        (
            "two cameras for one set",
            call(
                Gaussians {
                    means: &m,
                    features: &f,
                    opacities: &o,
                    scales: &sc,
                    rotations: &r,
                },
                &bg,
                &[c.clone(), c.clone()],
            ),
        ),
        (
            "f16",
            call(
                Gaussians {
                    means: &m.to_dtype(DType::F16).unwrap(),
                    features: &f.to_dtype(DType::F16).unwrap(),
                    opacities: &o.to_dtype(DType::F16).unwrap(),
                    scales: &sc.to_dtype(DType::F16).unwrap(),
                    rotations: &r.to_dtype(DType::F16).unwrap(),
                },
                &bg.to_dtype(DType::F16).unwrap(),
                std::slice::from_ref(&c),
            ),
        ),
        (
            "mixed dtypes",
            call(
                Gaussians {
                    means: &m.to_dtype(DType::F64).unwrap(),
                    features: &f,
                    opacities: &o,
                    scales: &sc,
                    rotations: &r,
                },
                &bg,
                std::slice::from_ref(&c),
            ),
        ),
    ];
    for (name, result) in cases {
        assert!(result.is_err(), "{name}: expected an error");
        println!("{name}: {}", result.err().unwrap());
    }
    let tm = Camera::look_at_origin_matrix(9.0, 0.0, 0.0);
    assert!(matches!(
        Camera::from_transform_matrix(&tm, 12.0, 0, 16),
        Err(SplatError::ImageSize { .. })
    ));
    assert!(matches!(
        Camera::from_transform_matrix(&tm, 12.0, 16, 0),
        Err(SplatError::ImageSize { .. })
    ));
}

#[test]
fn ply_round_trip_and_corrupt_files() {
    let s = small_scene();
    let dir = std::env::temp_dir().join(format!("gagavatar-ply-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("scene.ply");
    s.save_ply(&path).unwrap();
    let back = GaussianScene::load(&path).unwrap();
    assert_eq!(back.len(), s.len());
    assert_eq!(back.channels, s.channels);
    // Exact except where the .ply stores a transform: log scale and opacity logit.
    assert_eq!(back.means, s.means);
    assert_eq!(back.features, s.features);
    assert_eq!(back.rotations, s.rotations);
    for (i, (a, b)) in back.scales.iter().zip(&s.scales).enumerate() {
        assert!(
            (a - b).abs() <= 1e-6 * b.abs(),
            "scale {i}: expected {b}, got {a}"
        );
    }
    for (i, (a, b)) in back.opacities.iter().zip(&s.opacities).enumerate() {
        assert!((a - b).abs() <= 1e-6, "opacity {i}: expected {b}, got {a}");
    }
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(dir.join("cut.ply"), &bytes[..bytes.len() - 10]).unwrap();
    std::fs::write(dir.join("junk.ply"), b"hello").unwrap();
    std::fs::write(dir.join("scene.txt"), b"hello").unwrap();
    for bad in ["cut.ply", "junk.ply", "scene.txt", "missing.safetensors"] {
        let err = GaussianScene::load(&dir.join(bad));
        assert!(err.is_err(), "{bad} must fail");
        println!("{bad}: {}", err.err().unwrap());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
