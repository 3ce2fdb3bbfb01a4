//! The training loss's image terms on the GPU (spec section 11, `gagavatar_train::losses`):
//! `img = 0.5 (L1(coarse_rgb, gt) + L1(fine, gt))` and `box = 0.5 (L1(coarse_rgb crop, gt crop)
//! + L1(fine crop, gt crop))` on the target's head box resized to `box_size`, with `L1` the
//! mean absolute difference and PyTorch's `sign(0) = 0` gradient. Their values, and their
//! gradients with respect to the splatted image (its first three channels; the splatting
//! backward reads the whole `[C, H, W]`) and the renderer's output.
//!
//! The box changes with every sample, so the steps are built per sample ([`GpuImageLosses::new`]
//! is cheap once the kernels are compiled).

use crate::conv::At;
use crate::device::Gpu;
use crate::error::{input_err, Result};
use crate::grad::crop::{CropBox, GpuCropResize};
use crate::grad::layers::{l1_grad, l1_sum};
use crate::grad::perceptual::CropBuffers;
use crate::kernel::Step;

/// The terms' values: `img`, `box`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageTerms {
    pub img: f32,
    pub box_l1: f32,
}

/// One sample's image terms.
pub struct GpuImageLosses {
    /// `[4]`: the four L1 means, each already halved (img coarse, img fine, box coarse, box
    /// fine).
    values: wgpu::Buffer,
    /// The forward, the values and the gradients, then (from `backward_at`) the crops'
    /// backward.
    steps: Vec<Step>,
    backward_at: usize,
    /// The crops and the two predictions' crop gradients (the box terms' written by the
    /// forward steps, read by the crops' backward).
    pub crops: CropBuffers,
}

impl GpuImageLosses {
    /// The terms for `coarse` `[c, h, w]` (c >= 3), `fine` and `gt` `[3, h, w]`, the head box
    /// `b` resized to `box_size`; gradients into `d_coarse` (its first three channels are
    /// written, the others left as they are: zeros for a buffer made for it) and `d_fine`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        gpu: &Gpu,
        (c, h, w): (usize, usize, usize),
        b: CropBox,
        box_size: usize,
        coarse: &wgpu::Buffer,
        fine: &wgpu::Buffer,
        gt: &wgpu::Buffer,
        d_coarse: &wgpu::Buffer,
        d_fine: &wgpu::Buffer,
    ) -> Result<Self> {
        let crops = CropBuffers::new(gpu, box_size);
        Self::with_crops(gpu, (c, h, w), b, crops, coarse, fine, gt, d_coarse, d_fine)
    }

    /// [`GpuImageLosses::new`] with the crops in `crops` (of its size: the box size), which a
    /// caller keeps from sample to sample and shares with the perceptual term.
    #[allow(clippy::too_many_arguments)]
    pub fn with_crops(
        gpu: &Gpu,
        (c, h, w): (usize, usize, usize),
        b: CropBox,
        crops: CropBuffers,
        coarse: &wgpu::Buffer,
        fine: &wgpu::Buffer,
        gt: &wgpu::Buffer,
        d_coarse: &wgpu::Buffer,
        d_fine: &wgpu::Buffer,
    ) -> Result<Self> {
        let box_size = crops.size;
        if c < 3 {
            return Err(input_err(
                "coarse image",
                format!("{c} channels (the loss reads the first 3)"),
            ));
        }
        let n = 3 * h * w;
        for (name, buf, floats) in [
            ("coarse image", coarse, c * h * w),
            ("fine image", fine, n),
            ("target image", gt, n),
            ("dL/dcoarse", d_coarse, c * h * w),
            ("dL/dfine", d_fine, n),
        ] {
            if buf.size() < 4 * floats as u64 {
                return Err(input_err(
                    name,
                    format!("a {}-byte buffer for {floats} values", buf.size()),
                ));
            }
        }
        let ns = crops.floats();
        let (cc, fc, gc) = (&crops.coarse, &crops.fine, &crops.target);
        let (dcc, dfc) = (&crops.grad_coarse, &crops.grad_fine);
        let values = gpu.buffer("image loss terms", 16);
        let img_scale = 0.5 / n as f32;
        let box_scale = 0.5 / ns as f32;
        let dims = (3, h, w);
        let crop = |images, grad| GpuCropResize::new(gpu, dims, b, box_size, images, grad);
        let crop_c = crop((coarse, cc), Some((dcc, d_coarse)))?;
        let crop_f = crop((fine, fc), Some((dfc, d_fine)))?;
        // The target has no gradient.
        let crop_g = crop((gt, gc), None)?;
        let at = At::new;
        let mut steps = vec![
            crop_c.forward().clone(),
            crop_f.forward().clone(),
            crop_g.forward().clone(),
            l1_sum(gpu, n, at(coarse), at(gt), img_scale, &values, 0)?,
            l1_sum(gpu, n, at(fine), at(gt), img_scale, &values, 1)?,
            l1_sum(gpu, ns, at(cc), at(gc), box_scale, &values, 2)?,
            l1_sum(gpu, ns, at(fc), at(gc), box_scale, &values, 3)?,
            // The whole-image terms write the gradients, the box terms add to them.
            l1_grad(gpu, n, at(coarse), at(gt), img_scale, at(d_coarse))?,
            l1_grad(gpu, n, at(fine), at(gt), img_scale, at(d_fine))?,
            l1_grad(gpu, ns, at(cc), at(gc), box_scale, at(dcc))?,
            l1_grad(gpu, ns, at(fc), at(gc), box_scale, at(dfc))?,
        ];
        let backward_at = steps.len();
        steps.extend(crop_c.backward().iter().cloned());
        steps.extend(crop_f.backward().iter().cloned());
        Ok(Self {
            values,
            steps,
            backward_at,
            crops,
        })
    }

    /// The forward, the values and the gradients, in order.
    pub fn steps(&self) -> &[Step] {
        &self.steps
    }

    /// The crops, the values and the gradients of the crops (no image gradient yet): a term
    /// computed elsewhere from the crops (the perceptual distance) adds its gradients with
    /// [`Self::add_crop_grads`] before [`Self::backward_steps`].
    pub fn forward_steps(&self) -> &[Step] {
        &self.steps[..self.backward_at]
    }

    /// The crops' backward into the images' gradients (after [`Self::forward_steps`]).
    pub fn backward_steps(&self) -> &[Step] {
        &self.steps[self.backward_at..]
    }

    /// The crops `[3, box, box]` (coarse RGB, fine) after the forward.
    pub fn read_crops(&self, gpu: &Gpu) -> Result<[Vec<f32>; 2]> {
        let n = self.crops.floats();
        Ok([
            gpu.read_f32(&self.crops.coarse, n)?,
            gpu.read_f32(&self.crops.fine, n)?,
        ])
    }

    /// Adds another term's gradients of the two crops to the box terms' (between the forward
    /// and the backward).
    pub fn add_crop_grads(&self, gpu: &Gpu, coarse: &[f32], fine: &[f32]) -> Result<()> {
        let n = self.crops.floats();
        for (name, buf, extra) in [
            ("dL/dcoarse crop", &self.crops.grad_coarse, coarse),
            ("dL/dfine crop", &self.crops.grad_fine, fine),
        ] {
            if extra.len() != n {
                return Err(input_err(
                    name,
                    format!("{} values, expected {n}", extra.len()),
                ));
            }
            let mut g = gpu.read_f32(buf, n)?;
            for (a, b) in g.iter_mut().zip(extra) {
                *a += b;
            }
            gpu.queue.write_buffer(buf, 0, bytemuck::cast_slice(&g));
        }
        Ok(())
    }

    /// The terms after the steps ran.
    pub fn read(&self, gpu: &Gpu) -> Result<ImageTerms> {
        let v = gpu.read_f32(&self.values, 4)?;
        Ok(ImageTerms {
            img: v[0] + v[1],
            box_l1: v[2] + v[3],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::gpu;
    use candle_core::{Device, Tensor, Var};
    use gagavatar_splat::testscene::Rng;
    use gagavatar_train::{LossConfig, LossInputs, TrainLosses};

    /// The terms and every gradient against the CPU loss through candle's autograd: the same
    /// operations, other summation orders.
    const LOSS_RTOL: f64 = 1e-5;

    /// A 5-channel splatted image, a head box from a bbox as the trainer computes it, some
    /// pixels equal to the target's (sign(0) = 0 there), against `TrainLosses` with the
    /// perceptual and lifting terms off.
    #[test]
    fn image_terms_and_gradients_match_the_cpu_loss() {
        let Some(g) = gpu() else { return };
        let mut rng = Rng::new(8);
        let (c, h, w, size) = (5, 36, 44, 24);
        let mut rand =
            |k: usize| -> Vec<f32> { (0..k).map(|_| rng.range(0.0, 1.0) as f32).collect() };
        let gt = rand(3 * h * w);
        let mut coarse = rand(c * h * w);
        let fine = rand(3 * h * w);
        coarse[..40].copy_from_slice(&gt[..40]);
        let bbox = [0.3f32, 0.25, 0.7, 0.8];
        let hb = gagavatar_train::head_box(bbox, h, w).unwrap();
        let b = CropBox {
            x0: hb.x0,
            y0: hb.y0,
            x1: hb.x1,
            y1: hb.y1,
        };
        let bufs = [&coarse, &fine, &gt].map(|v| g.buffer_with("image", v));
        let d_coarse = g.buffer_with("dL/dcoarse", &vec![0f32; c * h * w]);
        let d_fine = g.buffer("dL/dfine", 4 * (3 * h * w) as u64);
        let losses = GpuImageLosses::new(
            g,
            (c, h, w),
            b,
            size,
            &bufs[0],
            &bufs[1],
            &bufs[2],
            &d_coarse,
            &d_fine,
        )
        .unwrap();
        g.submit(losses.steps());
        let got = losses.read(g).unwrap();
        let got_dc = g.read_f32(&d_coarse, c * h * w).unwrap();
        let got_df = g.read_f32(&d_fine, 3 * h * w).unwrap();

        let dev = Device::Cpu;
        let var = |v: &[f32], ch: usize| {
            Var::from_tensor(&Tensor::from_vec(v.to_vec(), (1, ch, h, w), &dev).unwrap()).unwrap()
        };
        let (vc, vf) = (var(&coarse, c), var(&fine, 3));
        let gtt = Tensor::from_vec(gt, (1, 3, h, w), &dev).unwrap();
        let bb = Tensor::from_vec(bbox.to_vec(), (1, 4), &dev).unwrap();
        let pts = Tensor::zeros((1, 1, 3), candle_core::DType::F32, &dev).unwrap();
        let cfg = LossConfig {
            box_size: size,
            lifting: false,
            percep_weight: 0.0,
        };
        let terms = TrainLosses::new(cfg, None)
            .compute(&LossInputs {
                coarse: vc.as_tensor(),
                fine: vf.as_tensor(),
                gt: &gtt,
                bbox: &bb,
                lifted: &pts,
                targets: &pts,
            })
            .unwrap();
        assert_eq!(terms.boxes[0], hb);
        for (what, want, got) in [
            ("img", terms.img.value, got.img),
            ("box", terms.box_l1.value, got.box_l1),
        ] {
            let d = (want - got as f64).abs();
            eprintln!("{what}: GPU {got}, CPU {want} (difference {d:e})");
            assert!(
                d <= LOSS_RTOL * want.abs(),
                "{what}: expected {want}, got {got}"
            );
        }
        let grads = terms.total.tensor.backward().unwrap();
        for (what, v, got) in [("dL/dcoarse", &vc, &got_dc), ("dL/dfine", &vf, &got_df)] {
            let want: Vec<f32> = grads
                .get(v.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let scale = want.iter().fold(0f64, |m, x| m.max(x.abs() as f64));
            for (i, (a, b)) in want.iter().zip(got.iter()).enumerate() {
                let d = (*a as f64 - *b as f64).abs();
                assert!(
                    d <= LOSS_RTOL * scale,
                    "{what}: index {i}: expected {a}, got {b} (difference {d:e})"
                );
            }
        }
        // Channels past the RGB and the pixels equal to the target carry no gradient.
        assert!(got_dc[3 * h * w..].iter().all(|&v| v == 0.0));
    }
}
