//! The lifting loss on the GPU (spec section 11's `point` term,
//! `gagavatar_train::nearest::lifting_loss`): for every target point (the scaled FLAME
//! vertices), the squared distance to the nearest lifted point, times [`LIFTING_WEIGHT`],
//! averaged; and its gradient with respect to the lifted points.
//!
//! The search is exact brute force (`nearest.wgsl`: the CPU's distance expression, ties to the
//! lowest index), about `n m` distances: 0.9 G for the release's 175,232 lifted points and
//! 5,023 targets, a few milliseconds on a large GPU. The gradient of each lifted point sums the
//! targets that chose it in target order, and the loss is a fixed-order sum: the same bits on
//! every run.

use crate::device::Gpu;
use crate::error::{input_err, GpuError, Result};
use crate::kernel::{Bind, Grid, Params, Step};

const NEAREST: &str = include_str!("../shaders/nearest.wgsl");
const LIFTING: &str = include_str!("../shaders/lifting.wgsl");

/// Multiplier of the lifting loss in the release (`gagavatar_train::nearest::LIFTING_WEIGHT`).
pub const LIFTING_WEIGHT: f32 = 10.0;

/// A grid of `n / 256` workgroups along x, rows of 65535 beyond that (the kernels' indexing).
fn grid(n: usize) -> Grid {
    let groups = n.div_ceil(256).max(1) as u32;
    Grid::Fixed([groups.min(65535), groups.div_ceil(65535), 1])
}

/// The loss and its gradient for `n` lifted points and `m` targets.
pub struct GpuLiftingLoss {
    n: usize,
    m: usize,
    /// `[m, 3]`, written with [`GpuLiftingLoss::set_targets`].
    pub targets: wgpu::Buffer,
    nn: wgpu::Buffer,
    /// `[1 + 3 n]`: the loss, then dL/dlifted `[n, 3]`.
    pub out: wgpu::Buffer,
    steps: Vec<Step>,
}

impl GpuLiftingLoss {
    /// The loss of the lifted points in `lifted` (`[n, 3]` f32 on the device, e.g. the
    /// reconstruction's output) against `m` targets.
    pub fn new(gpu: &Gpu, lifted: &wgpu::Buffer, n: usize, m: usize) -> Result<Self> {
        if n == 0 || m == 0 {
            return Err(input_err(
                "lifting loss",
                format!("{n} lifted points and {m} targets: both must be at least one"),
            ));
        }
        if n >= u32::MAX as usize / 3 || m >= u32::MAX as usize / 3 {
            return Err(GpuError::Unsupported(format!(
                "the lifting loss of {n} points and {m} targets"
            )));
        }
        if lifted.size() < 12 * n as u64 {
            return Err(input_err(
                "lifted points",
                format!("a {}-byte buffer for {n} points", lifted.size()),
            ));
        }
        let targets = gpu.buffer("lifting targets", 12 * m as u64);
        let nn = gpu.buffer("lifting nearest", 4 * m as u64);
        let d2 = gpu.buffer("lifting distances", 4 * m as u64);
        let out = gpu.buffer("lifting loss and gradient", 4 * (1 + 3 * n) as u64);
        let k = gpu.kernel(
            "nearest",
            NEAREST,
            &[],
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
                Bind::ReadWrite,
            ],
        )?;
        let u = gpu.uniform("nearest", &Params::new().u(n as u32).u(m as u32));
        let search = Step::new(
            k.clone(),
            gpu.bind(&k, &[&u, lifted, &targets, &nn, &d2])?,
            grid(m),
        );
        let u = gpu.uniform(
            "lifting",
            &Params::new()
                .u(n as u32)
                .u(m as u32)
                .f(LIFTING_WEIGHT / m as f32),
        );
        let mut binds = vec![Bind::Uniform];
        binds.extend([Bind::Read; 4]);
        binds.push(Bind::ReadWrite);
        let mut parts = Vec::new();
        for (grad, g) in [(false, Grid::Fixed([1, 1, 1])), (true, grid(n))] {
            let k = gpu.kernel("lifting", LIFTING, &[("GRAD", grad.to_string())], &binds)?;
            let bind = gpu.bind(&k, &[&u, lifted, &targets, &nn, &d2, &out])?;
            parts.push(Step::new(k, bind, g));
        }
        let mut steps = vec![search];
        steps.extend(parts);
        Ok(Self {
            n,
            m,
            targets,
            nn,
            out,
            steps,
        })
    }

    /// Writes the targets `[m, 3]`.
    pub fn set_targets(&self, gpu: &Gpu, targets: &[f32]) -> Result<()> {
        if targets.len() != 3 * self.m {
            return Err(input_err(
                "lifting targets",
                format!("expected {} values, got {}", 3 * self.m, targets.len()),
            ));
        }
        if let Some(i) = targets.iter().position(|v| !v.is_finite()) {
            return Err(input_err(
                "lifting targets",
                format!("value {i} is not finite"),
            ));
        }
        gpu.queue
            .write_buffer(&self.targets, 0, bytemuck::cast_slice(targets));
        Ok(())
    }

    /// The search, the loss and the gradient, in order.
    pub fn steps(&self) -> &[Step] {
        &self.steps
    }

    /// The loss and dL/dlifted `[n, 3]` after the steps ran.
    pub fn read(&self, gpu: &Gpu) -> Result<(f32, Vec<f32>)> {
        let all = gpu.read_f32(&self.out, 1 + 3 * self.n)?;
        Ok((all[0], all[1..].to_vec()))
    }

    /// Each target's nearest lifted point after the steps ran.
    pub fn read_nearest(&self, gpu: &Gpu) -> Result<Vec<u32>> {
        gpu.read_u32(&self.nn, self.m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::gpu;
    use candle_core::{Device, Tensor, Var};
    use gagavatar_splat::testscene::Rng;

    /// The loss and each gradient entry relative to the largest: only the summation orders
    /// differ from the CPU's (and a driver may fuse the distance's multiply-adds).
    const LIFTING_RTOL: f64 = 1e-5;

    fn points(rng: &mut Rng, k: usize, spread: f64) -> Vec<f32> {
        (0..3 * k)
            .map(|_| rng.range(-spread, spread) as f32)
            .collect()
    }

    /// Against `gagavatar_train::nearest` (k-d tree search, candle autograd for the gradient),
    /// with more lifted points than one tile and targets than one workgroup, several targets
    /// sharing a nearest point, and a target on a lifted point.
    #[test]
    fn lifting_loss_and_gradient_match_the_cpu() {
        let Some(g) = gpu() else { return };
        let mut rng = Rng::new(17);
        for (n, m) in [(1usize, 3usize), (700, 300), (3000, 1100)] {
            let lifted = points(&mut rng, n, 1.0);
            let mut targets = points(&mut rng, m, 1.2);
            targets[..3].copy_from_slice(&lifted[3 * (n / 2)..3 * (n / 2) + 3]);
            let buf = g.buffer_with("lifted", &lifted);
            let loss = GpuLiftingLoss::new(g, &buf, n, m).unwrap();
            loss.set_targets(g, &targets).unwrap();
            g.submit(loss.steps());
            let (got_loss, got_grad) = loss.read(g).unwrap();
            let got_nn = loss.read_nearest(g).unwrap();

            let dev = Device::Cpu;
            let l = Var::from_tensor(&Tensor::from_vec(lifted.clone(), (1, n, 3), &dev).unwrap())
                .unwrap();
            let t = Tensor::from_vec(targets.clone(), (1, m, 3), &dev).unwrap();
            let want_nn = gagavatar_train::nearest::nearest_indices(l.as_tensor(), &t).unwrap();
            for (k, (&(want, _), got)) in want_nn[0].iter().zip(&got_nn).enumerate() {
                assert_eq!(*got, want, "n {n}, m {m}: target {k}'s nearest");
            }
            assert_eq!(got_nn[0] as usize, n / 2, "the target on a lifted point");
            let want = gagavatar_train::nearest::lifting_loss(l.as_tensor(), &t).unwrap();
            let want_loss = want.to_scalar::<f32>().unwrap();
            let grads = want.backward().unwrap();
            let want_grad: Vec<f32> = grads
                .get(l.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let d = (got_loss as f64 - want_loss as f64).abs();
            eprintln!("n {n}, m {m}: loss {got_loss} (CPU {want_loss}, difference {d:e})");
            assert!(
                d <= LIFTING_RTOL * want_loss.abs() as f64,
                "n {n}, m {m}: loss expected {want_loss}, got {got_loss}"
            );
            let scale = want_grad.iter().fold(0f64, |a, v| a.max(v.abs() as f64));
            for (i, (w, gv)) in want_grad.iter().zip(&got_grad).enumerate() {
                let d = (*w as f64 - *gv as f64).abs();
                assert!(
                    d <= LIFTING_RTOL * scale,
                    "n {n}, m {m}: gradient {i}: expected {w}, got {gv} (difference {d:e})"
                );
            }
            let shared = {
                let mut seen = std::collections::HashSet::new();
                got_nn.iter().filter(|j| !seen.insert(**j)).count()
            };
            if n > 1 {
                assert!(shared > 0, "n {n}, m {m}: no lifted point was chosen twice");
            }
        }
    }

    #[test]
    fn the_weight_is_the_trainers() {
        assert_eq!(
            LIFTING_WEIGHT as f64,
            gagavatar_train::nearest::LIFTING_WEIGHT
        );
    }

    #[test]
    fn bad_lifting_inputs_are_errors() {
        let Some(g) = gpu() else { return };
        let buf = g.buffer_with("lifted", &[0f32; 6]);
        assert!(GpuLiftingLoss::new(g, &buf, 0, 3).is_err());
        assert!(GpuLiftingLoss::new(g, &buf, 2, 0).is_err());
        assert!(
            GpuLiftingLoss::new(g, &buf, 3, 1).is_err(),
            "a buffer too small"
        );
        let loss = GpuLiftingLoss::new(g, &buf, 2, 2).unwrap();
        assert!(loss.set_targets(g, &[0.0; 5]).is_err());
        assert!(loss
            .set_targets(g, &[0.0, 0.0, f32::NAN, 0.0, 0.0, 0.0])
            .is_err());
    }
}
