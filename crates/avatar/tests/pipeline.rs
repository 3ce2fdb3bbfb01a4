//! The pipeline in-process on the shipped demo model and its real source photo (the CLI tests
//! keep to the CLI itself): loading with the FLAME asset the weights name, reconstructing once,
//! rendering single frames and batches on the CPU, the GPU drive against the CPU one through
//! the same trait, and every bad input as a typed error.

use std::path::{Path, PathBuf};

use gagavatar_avatar::{AvatarError, Camera, Drive, Engine, EngineConfig, FlameSource, FrameCodes};
use gagavatar_flame::TrackedFrame;

/// Batched GEMMs may sum in another order than single frames: at most one 8-bit level.
const BATCH_LEVELS: i32 = 1;
/// The GPU's fine image is within 1e-5 of the CPU's at this size (crates/gpu's FINE_TOL), which
/// can still flip a rounding: one 8-bit level.
const GPU_LEVELS: i32 = 1;

fn demo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo")
}

fn source() -> (image::RgbImage, TrackedFrame) {
    let img = image::open(demo().join("source.png")).unwrap().to_rgb8();
    let rec = TrackedFrame::from_json_file(&demo().join("source.json")).unwrap();
    (img, rec)
}

fn engine() -> Engine {
    Engine::open(&EngineConfig::new(demo().join("weights.safetensors"))).unwrap()
}

/// The source's codes with the expression scaled and the jaw opened by `jaw` radians.
fn codes(base: &FrameCodes, scale: f32, jaw: f32) -> FrameCodes {
    let mut c = base.clone();
    for v in &mut c.expression {
        *v *= scale;
    }
    c.pose[3] += jaw;
    c
}

fn max_level_diff(a: &[u8], b: &[u8]) -> i32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x as i32 - *y as i32).abs())
        .max()
        .unwrap_or(0)
}

#[test]
fn the_demo_model_opens_with_the_flame_its_weights_name() {
    let e = engine();
    assert_eq!(e.flame_label(), "the built-in synthetic asset");
    assert!(e.warnings().is_empty(), "{:?}", e.warnings());
    assert_eq!(e.image_size(), 64);
}

#[test]
fn one_avatar_renders_single_frames_and_batches_alike() {
    let e = engine();
    let (img, rec) = source();
    let avatar = e.avatar(&img, &rec).unwrap();
    let base = avatar.codes(&rec, "source").unwrap();
    let cam = avatar.source_camera().unwrap();
    let mut turned: Camera = cam;
    // A small turn of the camera about the vertical axis.
    let (s, c) = 0.15f64.sin_cos();
    for row in turned.iter_mut() {
        let (x, z) = (row[0], row[2]);
        row[0] = c * x + s * z;
        row[2] = -s * x + c * z;
    }
    let frames: Vec<(FrameCodes, Camera)> = vec![
        (base.clone(), cam),
        (codes(&base, 2.0, 0.2), cam),
        (codes(&base, 0.0, 0.0), turned),
    ];
    let mut drive = avatar.cpu_drive();
    let batch = drive.render_batch(&frames).unwrap();
    assert_eq!(batch.len(), 3);
    for (i, (c, cam)) in frames.iter().enumerate() {
        let single = drive.render(c, cam).unwrap();
        assert_eq!(single.len(), 3 * 64 * 64);
        let d = max_level_diff(&single, &batch[i]);
        assert!(
            d <= BATCH_LEVELS,
            "frame {i}: batch vs single differ by {d} levels"
        );
    }
    // Fixed noise: the same frame twice is the same bytes; other codes or cameras differ.
    assert_eq!(drive.render(&base, &cam).unwrap(), batch[0]);
    assert_ne!(
        batch[0], batch[1],
        "a new expression and jaw changed nothing"
    );
    assert_ne!(batch[0], batch[2], "a new camera changed nothing");
    let t = drive.times();
    assert_eq!(t.frames, 3 + 3 + 1);
    assert!(t.renderer > std::time::Duration::ZERO && t.gpu.is_zero());
    // Streamed two at a time, in order, each frame within a batch's rounding of the batch of
    // three; a stop after the first frame renders no further batch.
    let mut streamed = Vec::new();
    let n = drive
        .render_stream(&frames, 2, &mut |k, img| {
            streamed.push((k, img));
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
    assert_eq!(n, 3);
    for (i, (k, img)) in streamed.iter().enumerate() {
        assert_eq!(*k, i);
        let d = max_level_diff(img, &batch[i]);
        assert!(
            d <= BATCH_LEVELS,
            "streamed frame {i}: {d} levels from the batch"
        );
    }
    let before = drive.times().frames;
    let n = drive
        .render_stream(&frames, 1, &mut |_, _| std::ops::ControlFlow::Break(()))
        .unwrap();
    assert_eq!((n, drive.times().frames - before), (1, 1));
}

#[test]
fn the_avatar_matches_the_model_run_by_hand() {
    // The library adds no step of its own: its frame is the model's reconstruct + drive.
    let e = engine();
    let (img, rec) = source();
    let avatar = e.avatar(&img, &rec).unwrap();
    let model = e.model();
    let image = gagavatar_avatar::image_tensor(&img, 64).unwrap();
    let cam = avatar.source_camera().unwrap();
    let tm = gagavatar_avatar::transforms_tensor(&[cam]).unwrap();
    let gaussians = model.reconstruct(&image, &tm).unwrap();
    let verts = e
        .flame()
        .forward(&rec.params(e.flame()).unwrap())
        .unwrap()
        .vertices;
    let by_hand = model
        .drive(
            &gaussians,
            &verts,
            &tm,
            gagavatar_net::style_unet::Noise::Fixed,
        )
        .unwrap();
    let want = gagavatar_avatar::to_rgb8(&by_hand.fine)
        .unwrap()
        .pop()
        .unwrap();
    let got = avatar
        .cpu_drive()
        .render(&avatar.codes(&rec, "source").unwrap(), &cam)
        .unwrap();
    let d = max_level_diff(&want, &got);
    // FLAME with a cached identity sums the shape basis apart from the expression's.
    assert!(d <= BATCH_LEVELS, "library vs model by hand: {d} levels");
}

#[test]
fn the_gpu_drive_renders_what_the_cpu_drive_renders() {
    let gpu = match gagavatar_gpu::Gpu::new(gagavatar_gpu::AdapterPolicy::AllowCpu) {
        Ok(g) => std::sync::Arc::new(g),
        Err(e) => {
            gagavatar_testkit::optional_path(
                "the_gpu_drive_renders_what_the_cpu_drive_renders",
                false,
                &format!("no GPU device: {e}"),
                gagavatar_testkit::REQUIRE_GPU,
            );
            return;
        }
    };
    let e = engine();
    let (img, rec) = source();
    let avatar = e.avatar(&img, &rec).unwrap();
    let base = avatar.codes(&rec, "source").unwrap();
    let cam = avatar.source_camera().unwrap();
    let frames = vec![(base.clone(), cam), (codes(&base, 1.5, 0.1), cam)];
    let mut cpu = avatar.cpu_drive();
    let mut dev = avatar
        .gpu_drive(gpu, &gagavatar_gpu::Tuning::default())
        .unwrap();
    let drives: [&mut dyn Drive; 2] = [&mut cpu, &mut dev];
    let [a, b] = drives.map(|d| d.render_batch(&frames).unwrap());
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        let d = max_level_diff(x, y);
        assert!(
            d <= GPU_LEVELS,
            "frame {i}: CPU vs GPU differ by {d} levels"
        );
    }
    assert_eq!(dev.times().frames, 2);
    assert!(dev.times().gpu > std::time::Duration::ZERO);
    // Streamed, the GPU's frames are its batch's bytes.
    let mut streamed = Vec::new();
    let n = dev
        .render_stream(&frames, 1, &mut |k, img| {
            streamed.push((k, img));
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
    assert_eq!(n, 2);
    for (i, (k, img)) in streamed.iter().enumerate() {
        assert_eq!(*k, i);
        assert!(img == &b[i], "streamed frame {i} differs from the batch");
    }
    assert_eq!(dev.times().frames, 4);
}

/// `Engine::avatar_on_gpu`: the network on the GPU, the Gaussians kept there for the GPU drive
/// (and read back for the CPU's uses), on the real demo photo. Two avatars made one after the
/// other keep their own Gaussians (the pass's buffers are reused).
#[test]
fn an_avatar_made_on_the_gpu_renders_what_the_cpu_one_renders() {
    let gpu = match gagavatar_gpu::Gpu::new(gagavatar_gpu::AdapterPolicy::AllowCpu) {
        Ok(g) => std::sync::Arc::new(g),
        Err(e) => {
            gagavatar_testkit::optional_path(
                "an_avatar_made_on_the_gpu_renders_what_the_cpu_one_renders",
                false,
                &format!("no GPU device: {e}"),
                gagavatar_testkit::REQUIRE_GPU,
            );
            return;
        }
    };
    let e = engine();
    let (img, rec) = source();
    let tuning = gagavatar_gpu::Tuning::default();
    let pass = e.gpu_reconstruct(gpu.clone(), &tuning).unwrap();
    let on_gpu = e.avatar_on_gpu(&pass, &img, &rec).unwrap();
    assert!(on_gpu.is_on_gpu());
    let mirrored = image::imageops::flip_horizontal(&img);
    let other = e.avatar_on_gpu(&pass, &mirrored, &rec).unwrap();
    let on_cpu = e.avatar(&img, &rec).unwrap();
    assert!(!on_cpu.is_on_gpu());
    let base = on_cpu.codes(&rec, "source").unwrap();
    let cam = on_cpu.source_camera().unwrap();
    let frames = vec![(base.clone(), cam), (codes(&base, 1.5, 0.1), cam)];
    let want = on_cpu.cpu_drive().render_batch(&frames).unwrap();
    let mut dev = on_gpu.gpu_drive(gpu.clone(), &tuning).unwrap();
    let got = dev.render_batch(&frames).unwrap();
    let mut read_back = on_gpu.cpu_drive();
    let cpu_of_gpu = read_back.render_batch(&frames).unwrap();
    for (i, ((w, g), r)) in want.iter().zip(&got).zip(&cpu_of_gpu).enumerate() {
        let d = max_level_diff(w, g);
        assert!(
            d <= GPU_LEVELS,
            "frame {i}: CPU avatar vs GPU avatar differ by {d} levels"
        );
        let d = max_level_diff(w, r);
        assert!(
            d <= GPU_LEVELS,
            "frame {i}: the read-back Gaussians differ by {d} levels"
        );
    }
    let mirrored_frame = other
        .gpu_drive(gpu, &tuning)
        .unwrap()
        .render(&base, &cam)
        .unwrap();
    assert!(
        max_level_diff(&mirrored_frame, &got[0]) > 8,
        "the second avatar overwrote the first or rendered the first"
    );
}

#[test]
fn several_avatars_render_in_one_batch_as_each_alone() {
    let e = engine();
    let (img, rec) = source();
    let a = e.avatar(&img, &rec).unwrap();
    // Another person: the photo mirrored and another FLAME shape.
    let mirrored = image::imageops::flip_horizontal(&img);
    let mut other = rec.clone();
    for v in other.shapecode.iter_mut().take(20) {
        *v = -*v + 0.5;
    }
    let b = e.avatar(&mirrored, &other).unwrap();
    let (ca, cb) = (a.codes(&rec, "a").unwrap(), b.codes(&other, "b").unwrap());
    let (cam_a, cam_b) = (a.source_camera().unwrap(), b.source_camera().unwrap());
    let jobs = vec![
        (0, ca.clone(), cam_a),
        (1, cb.clone(), cam_b),
        (0, codes(&ca, 1.5, 0.2), cam_a),
        (1, codes(&cb, 0.0, 0.1), cam_a),
    ];
    let together = gagavatar_avatar::render_many(&[&a, &b], &jobs).unwrap();
    assert_eq!(together.len(), 4);
    for (j, (index, c, cam)) in jobs.iter().enumerate() {
        let alone = [&a, &b][*index].cpu_drive().render(c, cam).unwrap();
        let d = max_level_diff(&alone, &together[j]);
        assert!(
            d <= BATCH_LEVELS,
            "frame {j}: batched vs alone differ by {d} levels"
        );
    }
    assert_ne!(together[0], together[1], "the two avatars rendered alike");
    // Bad batches: an index past the avatars, an avatar of another engine, nothing to do.
    let err = gagavatar_avatar::render_many(&[&a], &jobs).unwrap_err();
    assert!(err.to_string().contains("avatar 1 of 1"), "{err}");
    let e2 = engine();
    let c = e2.avatar(&img, &rec).unwrap();
    let err = gagavatar_avatar::render_many(&[&a, &c], &jobs).unwrap_err();
    assert!(err.to_string().contains("another engine"), "{err}");
    assert!(gagavatar_avatar::render_many(&[&a], &[]).is_err());
    assert!(gagavatar_avatar::render_many(&[], &jobs).is_err());
}

#[test]
fn bad_inputs_are_typed_errors() {
    let e = engine();
    let (img, rec) = source();
    let avatar = e.avatar(&img, &rec).unwrap();
    let base = avatar.codes(&rec, "source").unwrap();
    let cam = avatar.source_camera().unwrap();
    let mut drive = avatar.cpu_drive();

    let mut short = base.clone();
    short.expression.pop();
    let err = drive.render(&short, &cam).unwrap_err();
    assert!(matches!(err, AvatarError::Input { .. }), "{err}");
    assert!(err.to_string().contains("expression"), "{err}");

    let mut nan = cam;
    nan[1][3] = f64::NAN;
    let err = drive.render(&base, &nan).unwrap_err();
    assert!(err.to_string().contains("not finite"), "{err}");
    assert!(drive.render_batch(&[]).is_err());

    let mut no_camera = rec.clone();
    no_camera.transform_matrix = None;
    let err = e.avatar(&img, &no_camera).err().unwrap();
    assert!(err.to_string().contains("transform_matrix"), "{err}");
    let err = e.avatar(&image::RgbImage::new(0, 0), &rec).err().unwrap();
    assert!(err.to_string().contains("empty"), "{err}");
    // Any other size is resized, not refused.
    assert!(e.avatar(&image::RgbImage::new(90, 70), &rec).is_ok());

    let err = Engine::open(&EngineConfig::new(demo().join("no_such.safetensors")))
        .err()
        .unwrap();
    assert!(matches!(err, AvatarError::Weights { .. }), "{err}");
    let mut cfg = EngineConfig::new(demo().join("weights.safetensors"));
    cfg.flame = FlameSource::File(demo().join("no_such_flame.pt"));
    let err = Engine::open(&cfg).err().unwrap();
    assert!(matches!(err, AvatarError::FlameAsset { .. }), "{err}");
    assert!(
        std::error::Error::source(&err).is_some(),
        "the cause is kept"
    );
    cfg.flame = FlameSource::Synthetic;
    cfg.preset = Some("huge".into());
    let err = Engine::open(&cfg).err().unwrap();
    assert!(err.to_string().contains("unknown preset"), "{err}");
}

/// bf16 products on the trained demo model: measured 61 dB and at most 2 of 255 levels on its
/// fine image (`gagavatar bench model --precision bf16`); a wrong kernel gives noise (< 20 dB).
const BF16_MIN_PSNR_DB: f64 = 45.0;
const BF16_LEVELS: i32 = 6;

#[test]
fn bf16_renders_what_f32_renders_within_its_rounding() {
    let mut cfg = EngineConfig::new(demo().join("weights.safetensors"));
    cfg.precision = gagavatar_avatar::Precision::Bf16;
    if !gagavatar_testkit::bf16_or_skip("bf16_renders_what_f32_renders_within_its_rounding") {
        let err = Engine::open(&cfg)
            .err()
            .expect("bf16 opened without AVX512-BF16");
        assert!(matches!(err, AvatarError::Precision(_)), "{err}");
        return;
    }
    let (img, rec) = source();
    let frames: Vec<Vec<u8>> = [engine(), Engine::open(&cfg).unwrap()]
        .iter()
        .map(|e| {
            let avatar = e.avatar(&img, &rec).unwrap();
            let base = avatar.codes(&rec, "source").unwrap();
            let cam = avatar.source_camera().unwrap();
            avatar
                .cpu_drive()
                .render(&codes(&base, 1.5, 0.1), &cam)
                .unwrap()
        })
        .collect();
    let levels = max_level_diff(&frames[0], &frames[1]);
    let mse = frames[0]
        .iter()
        .zip(&frames[1])
        .map(|(&a, &b)| ((a as f64 - b as f64) / 255.0).powi(2))
        .sum::<f64>()
        / frames[0].len() as f64;
    let psnr = 10.0 * (1.0 / mse.max(1e-20)).log10();
    assert!(
        psnr >= BF16_MIN_PSNR_DB && levels <= BF16_LEVELS,
        "bf16 vs f32: PSNR {psnr:.1} dB (at least {BF16_MIN_PSNR_DB}), worst {levels} levels (at most {BF16_LEVELS})"
    );
    assert_ne!(frames[0], frames[1], "bf16 changed no byte: is it running?");
}
