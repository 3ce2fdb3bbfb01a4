//! The public splatting entry point: a candle custom op with a backward, so a loss on the image
//! back-propagates into whatever produced the Gaussians.

use crate::binning::{bin, Bins};
use crate::camera::Camera;
use crate::error::{Result, SplatError};
use crate::project::{project, project_backward, CamK, Projected, GEOM};
use crate::raster::{backward, forward, Frame, PixelState};
use crate::real::Real;
use candle_core::{CpuStorage, DType, Device, Layout, Shape, Tensor};
use rayon::prelude::*;
use std::sync::{Arc, Mutex};

/// The Gaussians of a batch, one set per camera. Shapes are `[B, N, k]` (or `[N, k]` for a
/// single set): means k=3, features k=C, opacities k=1 (already activated, in [0, 1]),
/// scales k=3 (already activated), rotations k=4 as `(r, x, y, z)`, used unnormalised.
pub struct Gaussians<'a> {
    pub means: &'a Tensor,
    pub features: &'a Tensor,
    pub opacities: &'a Tensor,
    pub scales: &'a Tensor,
    pub rotations: &'a Tensor,
}

impl<'a> Gaussians<'a> {
    /// Borrows `[means, features, opacities, scales, rotations]`, the order of
    /// [`crate::GaussianScene::to_tensors`].
    pub fn from_tensors(t: &'a [Tensor; 5]) -> Self {
        let [means, features, opacities, scales, rotations] = t;
        Self {
            means,
            features,
            opacities,
            scales,
            rotations,
        }
    }
}

/// What a splat returns.
#[derive(Debug, Clone)]
pub struct SplatOutput {
    /// `[B, C, H, W]` = composited features + transmittance x background; differentiable.
    pub image: Tensor,
    /// `[B, H, W]` final transmittance (detached).
    pub transmittance: Tensor,
    /// `[B, N]` u32 screen radius in pixels, 0 for culled Gaussians (detached).
    pub radii: Tensor,
    /// (tile, Gaussian) pairs per batch item.
    pub tile_pairs: Vec<usize>,
}

struct ItemState<T> {
    proj: Projected<T>,
    bins: Bins,
    pix: PixelState<T>,
}

enum Saved {
    F32(Vec<ItemState<f32>>),
    F64(Vec<ItemState<f64>>),
}

struct SplatOp {
    cameras: Vec<Camera>,
    n: usize,
    c: usize,
    state: Arc<Mutex<Option<Saved>>>,
}

fn slice<'a, T: Real>(s: &'a CpuStorage, l: &Layout) -> candle_core::Result<&'a [T]> {
    let data = s.as_slice::<T>()?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => candle_core::bail!("gagavatar-splat: inputs must be contiguous"),
    }
}

impl SplatOp {
    /// Batch item `b`'s view of the packed inputs.
    fn frame<'a, T: Real>(
        &self,
        b: usize,
        proj: &'a Projected<T>,
        bins: &'a Bins,
        feats: &'a [T],
        bg: &'a [T],
    ) -> Frame<'a, T> {
        let (n, c, cam) = (self.n, self.c, &self.cameras[b]);
        Frame {
            proj,
            bins,
            features: &feats[b * n * c..(b + 1) * n * c],
            channels: c,
            background: &bg[b * c..(b + 1) * c],
            width: cam.width,
            height: cam.height,
        }
    }

    fn run_forward<T: Real>(
        &self,
        geom: &[T],
        feats: &[T],
        bg: &[T],
    ) -> (Vec<T>, Vec<ItemState<T>>) {
        let n = self.n;
        let mut image = Vec::new();
        let mut states = Vec::with_capacity(self.cameras.len());
        for (b, cam) in self.cameras.iter().enumerate() {
            let k = CamK::<T>::new(cam);
            let geom_b = &geom[b * n * GEOM..(b + 1) * n * GEOM];
            let proj = project(&k, geom_b);
            let bins = bin(&proj, k.grid_x, k.grid_y);
            let frame = self.frame(b, &proj, &bins, feats, bg);
            let (img, pix) = forward(&frame);
            // The first (often only) item's image is kept as it is, not copied.
            if image.is_empty() {
                image = img;
            } else {
                image.extend_from_slice(&img);
            }
            states.push(ItemState { proj, bins, pix });
        }
        (image, states)
    }

    fn run_backward<T: Real>(
        &self,
        states: &[ItemState<T>],
        geom: &[T],
        feats: &[T],
        bg: &[T],
        grad: &[T],
    ) -> (Vec<T>, Vec<T>, Vec<T>) {
        let (n, c) = (self.n, self.c);
        let mut d_geom = crate::raster::zeros(geom.len(), T::ZERO);
        let mut d_feat = Vec::new();
        let mut d_bg = Vec::with_capacity(bg.len());
        let mut off = 0;
        for (b, (cam, st)) in self.cameras.iter().zip(states).enumerate() {
            let k = CamK::<T>::new(cam);
            let size = c * cam.width * cam.height;
            let frame = self.frame(b, &st.proj, &st.bins, feats, bg);
            let g2 = backward(&frame, &st.pix, &grad[off..off + size], n);
            off += size;
            let geom_b = &geom[b * n * GEOM..(b + 1) * n * GEOM];
            project_backward(
                &k,
                geom_b,
                &g2.screen,
                &st.proj.radius,
                &mut d_geom[b * n * GEOM..(b + 1) * n * GEOM],
            );
            // The first (often only) item's gradient is kept as it is, not copied.
            if d_feat.is_empty() {
                d_feat = g2.features;
            } else {
                d_feat.extend_from_slice(&g2.features);
            }
            d_bg.extend_from_slice(&g2.background);
        }
        (d_geom, d_feat, d_bg)
    }
}

impl SplatOp {
    /// Runs the backward on `[geom, features, background, grad]` (borrowed from their CPU
    /// storage when contiguous, copied otherwise, e.g. a broadcast gradient) and wraps the three
    /// gradients as tensors shaped like the op's inputs.
    fn backward_tensors<T: Real>(
        &self,
        states: &[ItemState<T>],
        args: [&Tensor; 4],
    ) -> candle_core::Result<(Tensor, Tensor, Tensor)> {
        // Copies first, then read guards on the rest, so no lock is held while copying.
        let mut owned: [Option<Vec<T>>; 4] = Default::default();
        for (o, t) in owned.iter_mut().zip(args) {
            if !t.is_contiguous() || !t.device().is_cpu() {
                *o = Some(t.flatten_all()?.to_vec1::<T>()?);
            }
        }
        let guards = args.map(|t| t.storage_and_layout());
        let mut host: Vec<&[T]> = Vec::with_capacity(4);
        for ((own, (storage, layout)), t) in owned.iter().zip(&guards).zip(args) {
            host.push(match (own, &**storage) {
                (Some(v), _) => v.as_slice(),
                (None, candle_core::Storage::Cpu(cpu)) => slice(cpu, layout)?,
                (None, _) => candle_core::bail!(
                    "gagavatar-splat: gradient input {:?} is not on the CPU",
                    t.shape()
                ),
            });
        }
        let (g, f, b) = self.run_backward::<T>(states, host[0], host[1], host[2], host[3]);
        drop(host);
        drop(guards);
        let [geom, feats, bg, _] = args;
        let dev = geom.device();
        Ok((
            Tensor::from_vec(g, geom.shape(), dev)?,
            Tensor::from_vec(f, feats.shape(), dev)?,
            Tensor::from_vec(b, bg.shape(), dev)?,
        ))
    }
}

impl candle_core::CustomOp3 for SplatOp {
    fn name(&self) -> &'static str {
        "gagavatar-splat"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let cam = &self.cameras[0];
        let shape = Shape::from((self.cameras.len(), self.c, cam.height, cam.width));
        let (storage, saved) = match s1 {
            CpuStorage::F32(_) => {
                let (img, st) =
                    self.run_forward::<f32>(slice(s1, l1)?, slice(s2, l2)?, slice(s3, l3)?);
                (CpuStorage::F32(img), Saved::F32(st))
            }
            CpuStorage::F64(_) => {
                let (img, st) =
                    self.run_forward::<f64>(slice(s1, l1)?, slice(s2, l2)?, slice(s3, l3)?);
                (CpuStorage::F64(img), Saved::F64(st))
            }
            _ => candle_core::bail!("gagavatar-splat: splatting runs in f32 or f64"),
        };
        *self.state.lock().map_err(|_| lock_err())? = Some(saved);
        Ok((storage, shape))
    }

    fn bwd(
        &self,
        arg1: &Tensor,
        arg2: &Tensor,
        arg3: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let guard = self.state.lock().map_err(|_| lock_err())?;
        let Some(saved) = guard.as_ref() else {
            candle_core::bail!("gagavatar-splat: backward called without a forward");
        };
        let args = [arg1, arg2, arg3, grad_res];
        let (g, f, b) = match saved {
            Saved::F32(st) => self.backward_tensors::<f32>(st, args)?,
            Saved::F64(st) => self.backward_tensors::<f64>(st, args)?,
        };
        Ok((Some(g), Some(f), Some(b)))
    }
}

fn lock_err() -> candle_core::Error {
    candle_core::Error::Msg("gagavatar-splat: state lock poisoned".into())
}

/// Brings `[N, k]` or `[B, N, k]` to `[B, N, k]` and checks `k`.
fn batched(t: &Tensor, name: &'static str, k: Option<usize>) -> Result<Tensor> {
    let t = match t.rank() {
        2 => t.unsqueeze(0)?,
        3 => t.clone(),
        _ => {
            return Err(SplatError::Shape {
                name,
                got: t.dims().to_vec(),
                expected: "[N, k] or [B, N, k]".into(),
            })
        }
    };
    if let Some(k) = k {
        if t.dim(2)? != k {
            return Err(SplatError::Shape {
                name,
                got: t.dims().to_vec(),
                expected: format!("[B, N, {k}]"),
            });
        }
    }
    Ok(t)
}

fn check_finite(t: &Tensor, name: &'static str) -> Result<()> {
    let (storage, layout) = t.storage_and_layout();
    let fast = match (&*storage, layout.contiguous_offsets()) {
        (candle_core::Storage::Cpu(CpuStorage::F32(v)), Some((a, b))) => Some(all_finite(&v[a..b])),
        (candle_core::Storage::Cpu(CpuStorage::F64(v)), Some((a, b))) => Some(all_finite(&v[a..b])),
        _ => None,
    };
    drop(storage);
    if fast == Some(true) {
        return Ok(());
    }
    let v: Vec<f64> = t.flatten_all()?.to_dtype(DType::F64)?.to_vec1()?;
    if let Some((index, &value)) = v.iter().enumerate().find(|(_, x)| !x.is_finite()) {
        return Err(SplatError::NonFinite { name, index, value });
    }
    Ok(())
}

/// Whether every value is finite, without allocating: `x - x` is 0 exactly for finite `x`,
/// and counting the zeros (rather than stopping at the first miss) lets the loop vectorise.
fn all_finite<T: Real>(v: &[T]) -> bool {
    #[allow(clippy::eq_op)]
    v.par_chunks(1 << 16).all(|c| {
        c.iter()
            .map(|&x| (x - x == T::ZERO) as usize)
            .sum::<usize>()
            == c.len()
    })
}

/// Splats each Gaussian set with its camera. All cameras must share one image size.
/// `background` is `[C]` (shared) or `[B, C]`.
pub fn splat(g: &Gaussians, background: &Tensor, cameras: &[Camera]) -> Result<SplatOutput> {
    let means = batched(g.means, "means", Some(3))?;
    let b = means.dim(0)?;
    let n = means.dim(1)?;
    let features = batched(g.features, "features", None)?;
    let c = features.dim(2)?;
    let opac = batched(g.opacities, "opacities", Some(1))?;
    let scales = batched(g.scales, "scales", Some(3))?;
    let rots = batched(g.rotations, "rotations", Some(4))?;
    for (t, name) in [
        (&features, "features"),
        (&opac, "opacities"),
        (&scales, "scales"),
        (&rots, "rotations"),
    ] {
        if t.dim(0)? != b || t.dim(1)? != n {
            return Err(SplatError::Shape {
                name,
                got: t.dims().to_vec(),
                expected: format!("[{b}, {n}, k] like means"),
            });
        }
    }
    if c == 0 {
        return Err(SplatError::Shape {
            name: "features",
            got: features.dims().to_vec(),
            expected: "at least one channel".into(),
        });
    }
    let background = match background.dims() {
        [k] if *k == c => background
            .unsqueeze(0)?
            .broadcast_as((b, c))?
            .contiguous()?,
        _ => background.clone(),
    };
    if background.dims() != [b, c] {
        return Err(SplatError::Shape {
            name: "background",
            got: background.dims().to_vec(),
            expected: format!("[{c}] or [{b}, {c}]"),
        });
    }
    if cameras.len() != b {
        return Err(SplatError::Batch(format!(
            "{} cameras for {b} Gaussian sets",
            cameras.len()
        )));
    }
    let (w, h) = (cameras[0].width, cameras[0].height);
    if cameras.iter().any(|cam| cam.width != w || cam.height != h) {
        return Err(SplatError::Batch(
            "all cameras of a batch must share one image size".into(),
        ));
    }
    let dtype = means.dtype();
    if !matches!(dtype, DType::F32 | DType::F64) {
        return Err(SplatError::DType(dtype));
    }
    for t in [&features, &opac, &scales, &rots, &background] {
        if t.dtype() != dtype {
            return Err(SplatError::MixedDType(dtype, t.dtype()));
        }
        if !matches!(t.device(), Device::Cpu) {
            return Err(SplatError::Device(t.device().location()));
        }
    }
    if !matches!(means.device(), Device::Cpu) {
        return Err(SplatError::Device(means.device().location()));
    }
    for (t, name) in [
        (&means, "means"),
        (&features, "features"),
        (&opac, "opacities"),
        (&scales, "scales"),
        (&rots, "rotations"),
        (&background, "background"),
    ] {
        check_finite(t, name)?;
    }
    // `[B, 11 N]`: per item, the four blocks of [`GEOM`].
    let flat = [&means, &opac, &scales, &rots]
        .into_iter()
        .map(|t| t.flatten_from(1))
        .collect::<candle_core::Result<Vec<_>>>()?;
    let geom = Tensor::cat(&flat, 1)?.contiguous()?;
    let features = features.contiguous()?;
    let background = background.contiguous()?;
    let state = Arc::new(Mutex::new(None));
    let op = SplatOp {
        cameras: cameras.to_vec(),
        n,
        c,
        state: state.clone(),
    };
    let image = geom.apply_op3(&features, &background, op)?;
    let guard = state.lock().map_err(|_| lock_err())?;
    let (transmittance, radii, tile_pairs) = match guard.as_ref() {
        Some(Saved::F32(st)) => aux(st, (b, h, w), dtype)?,
        Some(Saved::F64(st)) => aux(st, (b, h, w), dtype)?,
        None => return Err(SplatError::Candle(lock_err())),
    };
    Ok(SplatOutput {
        image,
        transmittance,
        radii,
        tile_pairs,
    })
}

fn aux<T: Real>(
    st: &[ItemState<T>],
    (b, h, w): (usize, usize, usize),
    dtype: DType,
) -> Result<(Tensor, Tensor, Vec<usize>)> {
    let t: Vec<T> = st
        .iter()
        .flat_map(|s| s.pix.final_t.iter().copied())
        .collect();
    let r: Vec<u32> = st
        .iter()
        .flat_map(|s| s.proj.radius.iter().copied())
        .collect();
    let n = r.len() / b.max(1);
    Ok((
        Tensor::from_vec(t, (b, h, w), &Device::Cpu)?.to_dtype(dtype)?,
        Tensor::from_vec(r, (b, n), &Device::Cpu)?,
        st.iter().map(|s| s.bins.pairs).collect(),
    ))
}
