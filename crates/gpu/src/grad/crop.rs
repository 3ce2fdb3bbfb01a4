//! The head-box crop and resize of the box losses on the GPU
//! (`gagavatar_train::head_box::crop_resize`: rows `y0..y1`, columns `x0..x1` of an image
//! resized to `out x out` with the antialiased bilinear resize) and its backward, which adds
//! the crop's gradient into the whole image's.
//!
//! The forward is `resize_taps.wgsl` (the reconstruction's photo resizes) on the CPU's own tap
//! tables with the crop's origin added to their starts. The backward is the transposed resize,
//! columns then rows (`resize_transpose.wgsl`), through tables transposed on the host: the box
//! changes with every sample, so the steps are built per sample (small tables, no kernels
//! compiled after the first).

use gagavatar_ops::resample::{ResizeMode, Taps};

use crate::device::Gpu;
use crate::error::{input_err, Result};
use crate::kernel::{linear_grid, Bind, Params, Step};

const RESIZE_TAPS: &str = include_str!("../shaders/resize_taps.wgsl");
const RESIZE_TRANSPOSE: &str = include_str!("../shaders/resize_transpose.wgsl");

/// An integer pixel crop: rows `y0..y1`, columns `x0..x1` (end exclusive).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CropBox {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

/// The transposed band of `taps` (input index -> its outputs): CSR offsets (`input + 1`),
/// output indices and weights (zero weights left out).
fn transpose(taps: &Taps, input: usize) -> (Vec<u32>, Vec<u32>, Vec<f32>) {
    let mut lists: Vec<Vec<(u32, f32)>> = vec![Vec::new(); input];
    for (o, &s) in taps.start.iter().enumerate() {
        for b in 0..taps.n {
            let w = taps.w[o * taps.n + b];
            if w != 0.0 && s + b < input {
                lists[s + b].push((o as u32, w as f32));
            }
        }
    }
    let mut first = Vec::with_capacity(input + 1);
    let (mut outs, mut weights) = (Vec::new(), Vec::new());
    first.push(0);
    for l in lists {
        for (o, w) in l {
            outs.push(o);
            weights.push(w);
        }
        first.push(outs.len() as u32);
    }
    // A binding cannot be empty (first[] then lists no entry).
    if outs.is_empty() {
        outs.push(0);
        weights.push(0.0);
    }
    (first, outs, weights)
}

/// One sample's crop-and-resize of `[C, H, W]` images and its backward.
pub struct GpuCropResize {
    forward: Step,
    backward: Vec<Step>,
}

impl GpuCropResize {
    /// The crop `b` of `image` `[c, h, w]` resized into `out` `[c, size, size]`. With
    /// `grad = Some((grad_out, grad_image))` also the backward, which reads dL/d`out` from
    /// `grad_out` and adds dL/d`image` into `grad_image` `[c, h, w]`; without it (an image that
    /// needs no gradient, such as the target) [`GpuCropResize::backward`] is empty.
    pub fn new(
        gpu: &Gpu,
        (c, h, w): (usize, usize, usize),
        b: CropBox,
        size: usize,
        (image, out): (&wgpu::Buffer, &wgpu::Buffer),
        grad: Option<(&wgpu::Buffer, &wgpu::Buffer)>,
    ) -> Result<Self> {
        if b.x1 <= b.x0 || b.y1 <= b.y0 || b.x1 > w || b.y1 > h {
            return Err(input_err(
                "crop box",
                format!("{b:?} is empty or outside the {h}x{w} image"),
            ));
        }
        if c == 0 || size == 0 {
            return Err(input_err(
                "crop",
                format!("{c} channels resized to {size}x{size}"),
            ));
        }
        let mut sized = vec![("image", image, c * h * w), ("crop", out, c * size * size)];
        if let Some((grad_out, grad_image)) = grad {
            sized.push(("dL/dcrop", grad_out, c * size * size));
            sized.push(("dL/dimage", grad_image, c * h * w));
        }
        for (name, buf, floats) in sized {
            if buf.size() < 4 * floats as u64 {
                return Err(input_err(
                    name,
                    format!("a {}-byte buffer for {floats} values", buf.size()),
                ));
            }
        }
        let (cw, ch) = (b.x1 - b.x0, b.y1 - b.y0);
        let ty = Taps::new(ch, size, ResizeMode::Antialias);
        let tx = Taps::new(cw, size, ResizeMode::Antialias);

        // Forward: the taps with the crop's origin in their starts, on the whole image.
        let starts: Vec<u32> = ty
            .start
            .iter()
            .map(|s| (s + b.y0) as u32)
            .chain(tx.start.iter().map(|s| (s + b.x0) as u32))
            .collect();
        let weights: Vec<f32> = ty.w.iter().chain(&tx.w).map(|&v| v as f32).collect();
        let starts = gpu.buffer_with("crop taps: starts", &starts);
        let weights = gpu.buffer_with("crop taps: weights", &weights);
        let k = gpu.kernel(
            "resize_taps",
            RESIZE_TAPS,
            &[("NORMALIZE", "false".to_string())],
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
            ],
        )?;
        let mut p = Params::new()
            .u(c as u32)
            .u(h as u32)
            .u(w as u32)
            .u(size as u32)
            .u(size as u32)
            .u(ty.n as u32)
            .u(tx.n as u32)
            .u(0)
            .u(size as u32)
            .u(0)
            .u((size * ty.n) as u32)
            .u(0)
            .u(0)
            .u(0)
            .u(0)
            .u(0);
        for v in [0.0f32, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0] {
            p = p.f(v);
        }
        let u = gpu.uniform("crop resize", &p);
        let forward = Step::new(
            k.clone(),
            gpu.bind(&k, &[&u, image, &starts, &weights, out])?,
            linear_grid(c * size * size, 256),
        )
        .with_note(format!("crop {cw}x{ch} -> {size}"));

        // Backward: columns (dL/dcrop -> t [c, size, cw]), then rows, added into the image's.
        let mut backward = Vec::new();
        let Some((grad_out, grad_image)) = grad else {
            return Ok(Self { forward, backward });
        };
        let t = gpu.buffer("crop backward: columns", 4 * (c * size * cw) as u64);
        for (axis_x, taps, input, a, src, dst) in [
            (true, &tx, cw, size, grad_out, &t),
            (false, &ty, ch, cw, &t, grad_image),
        ] {
            let (first, outs, wts) = transpose(taps, input);
            let first = gpu.buffer_with("crop backward: first", &first);
            let outs = gpu.buffer_with("crop backward: outputs", &outs);
            let wts = gpu.buffer_with("crop backward: weights", &wts);
            let k = gpu.kernel(
                "resize_transpose",
                RESIZE_TRANSPOSE,
                &[("AXIS_X", axis_x.to_string())],
                &[
                    Bind::Uniform,
                    Bind::Read,
                    Bind::Read,
                    Bind::Read,
                    Bind::Read,
                    Bind::ReadWrite,
                ],
            )?;
            let u = gpu.uniform(
                "crop backward",
                &Params::new()
                    .u(c as u32)
                    .u(a as u32)
                    .u(size as u32)
                    .u(input as u32)
                    .u(w as u32)
                    .u(h as u32)
                    .u(b.x0 as u32)
                    .u(b.y0 as u32),
            );
            let n = if axis_x { c * size * cw } else { c * ch * cw };
            backward.push(Step::new(
                k.clone(),
                gpu.bind(&k, &[&u, src, &first, &outs, &wts, dst])?,
                linear_grid(n, 256),
            ));
        }
        Ok(Self { forward, backward })
    }

    /// The crop and resize.
    pub fn forward(&self) -> &Step {
        &self.forward
    }

    /// Its backward (adds into the image's gradient).
    pub fn backward(&self) -> &[Step] {
        &self.backward
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::gpu;
    use candle_core::{Device, Tensor, Var};
    use gagavatar_splat::testscene::Rng;
    use gagavatar_train::head_box::{crop_resize, HeadBox};

    /// The crop and its gradient against candle's (the CPU resize's own tables in f64 there,
    /// rounded to f32 here; the sums' order differs).
    const CROP_TOL: f64 = 1e-5;

    fn assert_close(what: &str, want: &[f32], got: &[f32], tol: f64) {
        assert_eq!(want.len(), got.len(), "{what}: lengths");
        let scale = want.iter().fold(1f64, |m, v| m.max(v.abs() as f64));
        for (i, (a, b)) in want.iter().zip(got).enumerate() {
            let d = (*a as f64 - *b as f64).abs();
            assert!(
                d <= tol * scale,
                "{what}: index {i}: expected {a}, got {b} (difference {d:e})"
            );
        }
    }

    /// Upsampling and downsampling crops, one touching the image's corner, one pixel wider
    /// than high (the release's truncation does that), against candle's autograd through
    /// `crop_resize`; the backward adds to what the image's gradient held.
    #[test]
    fn crop_resize_and_its_gradient_match_the_cpu() {
        let Some(g) = gpu() else { return };
        let mut rng = Rng::new(3);
        let (c, h, w) = (3, 40, 52);
        for (b, size) in [
            (
                CropBox {
                    x0: 10,
                    y0: 5,
                    x1: 31,
                    y1: 25,
                },
                48,
            ),
            (
                CropBox {
                    x0: 0,
                    y0: 0,
                    x1: 52,
                    y1: 40,
                },
                17,
            ),
            (
                CropBox {
                    x0: 30,
                    y0: 20,
                    x1: 52,
                    y1: 40,
                },
                22,
            ),
        ] {
            let img: Vec<f32> = (0..c * h * w).map(|_| rng.range(0.0, 1.0) as f32).collect();
            let dl: Vec<f32> = (0..c * size * size)
                .map(|_| rng.range(-1.0, 1.0) as f32)
                .collect();
            let before: Vec<f32> = (0..c * h * w)
                .map(|_| rng.range(-1.0, 1.0) as f32)
                .collect();
            let image = g.buffer_with("image", &img);
            let out = g.buffer("crop", 4 * (c * size * size) as u64);
            let grad_out = g.buffer_with("dL/dcrop", &dl);
            let grad_image = g.buffer_with("dL/dimage", &before);
            let cr = GpuCropResize::new(
                g,
                (c, h, w),
                b,
                size,
                (&image, &out),
                Some((&grad_out, &grad_image)),
            )
            .unwrap();
            g.submit(std::slice::from_ref(cr.forward()));
            g.submit(cr.backward());
            let got_crop = g.read_f32(&out, c * size * size).unwrap();
            let got_grad = g.read_f32(&grad_image, c * h * w).unwrap();

            let dev = Device::Cpu;
            let x = Var::from_tensor(&Tensor::from_vec(img, (1, c, h, w), &dev).unwrap()).unwrap();
            let hb = HeadBox {
                x0: b.x0,
                y0: b.y0,
                x1: b.x1,
                y1: b.y1,
            };
            let crop = crop_resize(x.as_tensor(), &[hb], size).unwrap();
            let want_crop: Vec<f32> = crop.flatten_all().unwrap().to_vec1().unwrap();
            let dl = Tensor::from_vec(dl, (1, c, size, size), &dev).unwrap();
            let grads = (crop * dl).unwrap().sum_all().unwrap().backward().unwrap();
            let want_grad: Vec<f32> = grads
                .get(x.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let want_total: Vec<f32> = want_grad.iter().zip(&before).map(|(a, b)| a + b).collect();
            assert_close(
                &format!("{b:?} -> {size}: crop"),
                &want_crop,
                &got_crop,
                CROP_TOL,
            );
            assert_close(
                &format!("{b:?} -> {size}: dL/dimage"),
                &want_total,
                &got_grad,
                CROP_TOL,
            );
        }
    }

    #[test]
    fn bad_crops_are_errors() {
        let Some(g) = gpu() else { return };
        let buf = g.buffer("b", 4 * 3 * 8 * 8);
        let b = |x0, y0, x1, y1| CropBox { x0, y0, x1, y1 };
        for bad in [b(3, 0, 3, 4), b(0, 5, 4, 2), b(0, 0, 9, 4), b(0, 0, 4, 9)] {
            assert!(
                GpuCropResize::new(g, (3, 8, 8), bad, 4, (&buf, &buf), Some((&buf, &buf))).is_err(),
                "{bad:?}"
            );
        }
        let small = g.buffer("small", 16);
        assert!(GpuCropResize::new(
            g,
            (3, 8, 8),
            b(0, 0, 4, 4),
            4,
            (&small, &buf),
            Some((&buf, &buf))
        )
        .is_err());
    }
}
