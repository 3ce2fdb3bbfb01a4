//! The rendering half of a training step on the GPU, for one sample: the Gaussians splatted
//! from the target's camera (the training forward, [`GpuSplatGrad`]), the neural renderer's
//! training forward on the splatted image ([`GpuRendererGrad`]), the loss's image and head-box
//! terms ([`GpuImageLosses`]), then back: the renderer's backward (every renderer parameter's
//! gradient and the splatted image's), that image gradient added to the loss's own, and the
//! splatting's backward to every Gaussian's gradients. What the reconstruction networks would
//! receive next (the Gaussians' gradients) is [`GpuSplatGrad::read`]'s.

use gagavatar_splat::Camera;

use crate::device::Gpu;
use crate::error::{input_err, Result};
use crate::grad::crop::CropBox;
use crate::grad::image_loss::{GpuImageLosses, ImageTerms};
use crate::grad::renderer::GpuRendererGrad;
use crate::grad::splat::GpuSplatGrad;
use crate::kernel::{linear_grid, Bind, Params, Step};
use crate::splat::GpuSplat;

const ADD: &str = include_str!("../shaders/add.wgsl");

/// Runs the rendering half of a training step for `cam` against the target `gt` (`[3, S, S]`
/// on the device) with the head box `head_box` resized to `box_size`, and returns the loss's
/// image terms; the gradients are left in `renderer`'s parameter buffers and `splat_grad`'s.
/// The pair buffers grow (and `splat_grad` is rebuilt) as the forward needs.
#[allow(clippy::too_many_arguments)]
pub fn render_step(
    gpu: &Gpu,
    splat: &mut GpuSplat,
    splat_grad: &mut GpuSplatGrad,
    renderer: &GpuRendererGrad,
    cam: &Camera,
    gt: &wgpu::Buffer,
    head_box: CropBox,
    box_size: usize,
) -> Result<ImageTerms> {
    let (c, h, w) = (splat.channels, splat.height, splat.width);
    if renderer.size != w || renderer.size != h || c * h * w * 4 > renderer.input.size() as usize {
        return Err(input_err(
            "render step",
            format!(
                "a {c}-channel {w}x{h} splat for a {}x{} renderer of {} input bytes",
                renderer.size,
                renderer.size,
                renderer.input.size()
            ),
        ));
    }
    let image_bytes = 4 * (c * h * w) as u64;
    // Forward: the splatting (until its pairs fit), the renderer on the splatted image.
    splat_grad.forward(gpu, splat, cam)?;
    let mut enc = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("splatted image to the renderer"),
        });
    enc.copy_buffer_to_buffer(&splat.image, 0, &renderer.input, 0, image_bytes);
    gpu.queue.submit([enc.finish()]);
    gpu.submit(renderer.forward_steps());

    // The loss: its own gradient of the splatted image (zeros past the RGB channels), and the
    // renderer's output gradient.
    let d_loss = gpu.buffer("dL/dcoarse (loss terms)", image_bytes);
    let losses = GpuImageLosses::new(
        gpu,
        (c, h, w),
        head_box,
        box_size,
        &splat.image,
        &renderer.output,
        gt,
        &d_loss,
        &renderer.grad_output,
    )?;
    gpu.submit(losses.steps());

    // Back: the renderer, the two gradients of the splatted image summed, the splatting.
    gpu.submit(renderer.backward_steps());
    let k = gpu.kernel(
        "add",
        ADD,
        &[],
        &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
    )?;
    let n = c * h * w;
    let u = gpu.uniform("add", &Params::new().u(n as u32));
    let add = Step::new(
        k.clone(),
        gpu.bind(
            &k,
            &[&u, &d_loss, &renderer.grad_input, &splat_grad.grad_image],
        )?,
        linear_grid(n, 256),
    );
    gpu.submit(std::slice::from_ref(&add));
    splat_grad.submit_backward(gpu);
    losses.read(gpu)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grad::renderer_tests::seeded_renderer;
    use crate::splat::SplatInputs;
    use crate::testutil::{assert_close_rel, gpu};
    use crate::Tuning;
    use candle_core::{Device, Tensor, Var};
    use gagavatar_net::style_unet::Noise;
    use gagavatar_net::ModelConfig;
    use gagavatar_splat::testscene::{avatar_scene, Regime, Rng};
    use gagavatar_splat::{splat, Gaussians};
    use gagavatar_train::{LossConfig, LossInputs, TrainLosses};

    /// Every gradient relative to its array's largest: the pieces' own bounds chained (the
    /// worst measured on lavapipe is 8e-6, a decoder weight whose gradients are ~1e-5), with
    /// room for a pixel whose transmittance stop a driver rounds the other way.
    const STEP_RTOL: f64 = 1e-4;

    fn check(what: &str, want: &[f32], got: &[f32]) {
        assert_close_rel(what, want, got, STEP_RTOL);
    }

    /// The tiny preset's renderer and an avatar-like scene at its 64x64 and 32 channels: the
    /// loss terms and the gradients of every Gaussian attribute and renderer parameter
    /// against candle's autograd through `splat`, `StyleUNet` and `TrainLosses`.
    #[test]
    fn render_step_matches_candle_autograd() {
        let Some(g) = gpu() else { return };
        let cfg = ModelConfig::tiny();
        let s = cfg.image_size;
        let (scene, _) = avatar_scene(20, 300, cfg.color_dim, Regime::Small, 5);
        let tm = Camera::look_at_origin_matrix(9.0, 0.2, -0.1);
        let cam = Camera::from_transform_matrix(&tm, 12.0, s, s).unwrap();
        let bg = vec![0f32; cfg.color_dim];
        let mut rng = Rng::new(9);
        let gt: Vec<f32> = (0..3 * s * s).map(|_| rng.range(0.0, 1.0) as f32).collect();
        let bbox = [0.3f32, 0.25, 0.7, 0.8];
        let box_size = 32;
        let hb = gagavatar_train::head_box(bbox, s, s).unwrap();
        let (unet, vars, host) = seeded_renderer(&cfg, 77);

        // GPU.
        let inputs = SplatInputs::from_scene(&scene, &bg);
        let mut sp = GpuSplat::new(g, &Tuning::default(), &inputs, None, 0, s, s).unwrap();
        let mut sg = GpuSplatGrad::new(g, &sp).unwrap();
        let weights = |key: &str| {
            host.get(key)
                .cloned()
                .ok_or_else(|| crate::GpuError::Weights(format!("no {key}")))
        };
        let r = GpuRendererGrad::new(g, &Tuning::default(), &cfg, &weights).unwrap();
        let gt_buf = g.buffer_with("target", &gt);
        let b = CropBox {
            x0: hb.x0,
            y0: hb.y0,
            x1: hb.x1,
            y1: hb.y1,
        };
        let terms = render_step(g, &mut sp, &mut sg, &r, &cam, &gt_buf, b, box_size).unwrap();
        let got = sg.read(g).unwrap();
        let got_r: std::collections::HashMap<String, Vec<f32>> =
            r.read_grads(g).unwrap().into_iter().collect();

        // CPU.
        let dev = Device::Cpu;
        let t = scene.to_tensors(&dev).unwrap();
        let gv: Vec<Var> = t.iter().map(|x| Var::from_tensor(x).unwrap()).collect();
        let gt5: [Tensor; 5] = std::array::from_fn(|i| gv[i].as_tensor().clone());
        let bgt = Tensor::from_vec(bg.clone(), bg.len(), &dev).unwrap();
        let out = splat(
            &Gaussians::from_tensors(&gt5),
            &bgt,
            std::slice::from_ref(&cam),
        )
        .unwrap();
        let fine = unet.forward(&out.image, Noise::Fixed).unwrap();
        let gtt = Tensor::from_vec(gt, (1, 3, s, s), &dev).unwrap();
        let bb = Tensor::from_vec(bbox.to_vec(), (1, 4), &dev).unwrap();
        let pts = Tensor::zeros((1, 1, 3), candle_core::DType::F32, &dev).unwrap();
        let cfg_l = LossConfig {
            box_size,
            lifting: false,
            percep_weight: 0.0,
        };
        let want = TrainLosses::new(cfg_l, None)
            .compute(&LossInputs {
                coarse: &out.image,
                fine: &fine,
                gt: &gtt,
                bbox: &bb,
                lifted: &pts,
                targets: &pts,
            })
            .unwrap();
        for (what, w, gv) in [
            ("img", want.img.value, terms.img),
            ("box", want.box_l1.value, terms.box_l1),
        ] {
            let d = (w - gv as f64).abs();
            eprintln!("{what}: GPU {gv}, CPU {w} (difference {d:e})");
            assert!(d <= 1e-4 * w.abs(), "{what}: expected {w}, got {gv}");
        }
        let grads = want.total.tensor.backward().unwrap();
        let flat = |v: &Var| -> Vec<f32> {
            grads
                .get(v.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        };
        let n = scene.len();
        check("d features", &flat(&gv[1]), &got.features);
        // [N, 11] rows: mean (3), opacity, scale (3), quaternion (4).
        for (what, var, first, width) in [
            ("d means", &gv[0], 0, 3),
            ("d opacities", &gv[2], 3, 1),
            ("d scales", &gv[3], 4, 3),
            ("d rotations", &gv[4], 7, 4),
        ] {
            let rows: Vec<f32> = (0..n)
                .flat_map(|i| (0..width).map(move |k| (i, k)))
                .map(|(i, k)| got.geom[i * 11 + first + k])
                .collect();
            check(what, &flat(var), &rows);
        }
        let mut checked = 0;
        for (key, var) in &vars {
            if let Some(gpu_grad) = got_r.get(key) {
                check(&format!("d {key}"), &flat(var), gpu_grad);
                checked += 1;
            }
        }
        assert!(checked > 100, "only {checked} renderer parameters compared");
    }
}
