//! The AVX-512 row kernel must give bit-identical images to the portable one. Alone in its own
//! test binary because it toggles a process-wide environment variable.

use candle_core::{DType, Device, Tensor};
use gagavatar_splat::testscene::{avatar_scene, Regime};
use gagavatar_splat::{splat, Camera, Gaussians};

fn render() -> Vec<f32> {
    let (scene, _) = avatar_scene(40, 500, 32, Regime::Small, 5);
    let cam = Camera::from_transform_matrix(
        &Camera::look_at_origin_matrix(9.0, 0.2, -0.1),
        12.0,
        100,
        90,
    )
    .unwrap();
    let tensors = scene.to_tensors(&Device::Cpu).unwrap();
    let bg = Tensor::ones(32, DType::F32, &Device::Cpu).unwrap();
    let out = splat(&Gaussians::from_tensors(&tensors), &bg, &[cam]).unwrap();
    out.image.flatten_all().unwrap().to_vec1().unwrap()
}

#[test]
fn simd_and_portable_rows_are_bit_identical() {
    std::env::remove_var("GAGAVATAR_NO_AVX512");
    let fast = render();
    std::env::set_var("GAGAVATAR_NO_AVX512", "1");
    let portable = render();
    std::env::remove_var("GAGAVATAR_NO_AVX512");
    assert!(
        fast.iter().any(|&v| v != 1.0),
        "the scene must render something"
    );
    for (i, (a, b)) in fast.iter().zip(&portable).enumerate() {
        assert_eq!(
            a.to_bits(),
            b.to_bits(),
            "index {i}: portable {b}, simd {a}"
        );
    }
    println!(
        "AVX-512F available: {}",
        std::arch::is_x86_feature_detected!("avx512f")
    );
}
