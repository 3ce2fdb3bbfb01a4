//! The AVX-512 kernels must give bit-identical images and gradients to the plain-array ones.
//! Alone in its own test binary because it toggles a process-wide environment variable.

use candle_core::{DType, Device, Tensor, Var};
use gagavatar_splat::testscene::{avatar_scene, Regime};
use gagavatar_splat::{splat, Camera, Gaussians};

/// The image followed by the gradients of every input for a weighted-sum loss.
fn render() -> Vec<f32> {
    let (scene, _) = avatar_scene(40, 500, 32, Regime::Small, 5);
    let cam = Camera::from_transform_matrix(
        &Camera::look_at_origin_matrix(9.0, 0.2, -0.1),
        12.0,
        100,
        90,
    )
    .unwrap();
    let vars: Vec<Var> = scene
        .to_tensors(&Device::Cpu)
        .unwrap()
        .iter()
        .map(|t| Var::from_tensor(t).unwrap())
        .collect();
    let tensors: [Tensor; 5] = std::array::from_fn(|i| vars[i].as_tensor().clone());
    let bg = Tensor::ones(32, DType::F32, &Device::Cpu).unwrap();
    let out = splat(&Gaussians::from_tensors(&tensors), &bg, &[cam]).unwrap();
    let weights = Tensor::arange(0f32, out.image.elem_count() as f32, &Device::Cpu)
        .unwrap()
        .sin()
        .unwrap()
        .reshape(out.image.shape())
        .unwrap();
    let grads = (&out.image * weights)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let mut all: Vec<f32> = out.image.flatten_all().unwrap().to_vec1().unwrap();
    for v in &vars {
        let g = grads
            .get(v.as_tensor())
            .expect("every input has a gradient");
        all.extend(g.flatten_all().unwrap().to_vec1::<f32>().unwrap());
    }
    all
}

#[test]
fn simd_and_portable_paths_are_bit_identical() {
    // Without AVX-512 both renders take the portable path and the comparison proves nothing.
    if !gagavatar_testkit::avx512_or_skip("simd_and_portable_paths_are_bit_identical") {
        return;
    }
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
        "AVX-512 and portable paths compared: {} values bit-identical",
        fast.len()
    );
}
