//! Linear blend skinning as one fused CPU kernel (a candle custom op with its own backward).
//!
//! Written with tensor ops, skinning needs either `[B, V, 4, 4]` per-vertex transforms or a
//! `[B, V, 15]` per-joint intermediate plus several full passes over it; with 5023 vertices and
//! 100 frames those passes, not the arithmetic, dominated the whole forward. Here each output
//! vertex is computed in registers: blend the five 3x4 joint transforms with the vertex's
//! weights, apply the result, scale. The backward is hand-written too, and checked against
//! finite differences by the crate's gradient tests.
//!
//! Only the CPU has a kernel; other devices use the tensor-op formulation in `lbs.rs`.

use candle_core::{
    CpuStorage, CustomOp2, DType, Layout, Result as CandleResult, Shape, Tensor, WithDType,
};
use rayon::prelude::*;
use std::sync::Arc;

use crate::asset::NUM_JOINTS;

/// Values per joint transform: a row-major 3x4 `[R | t]`.
pub const TRANSFORM_LEN: usize = 12;
const JOINT_BLOCK: usize = NUM_JOINTS * TRANSFORM_LEN;
/// Below this many vertices in the batch (one or two frames), threading costs more than it saves,
/// so small batches run on the calling thread.
const PARALLEL_MIN_VERTICES: usize = 8192;

/// `vertices[b, v] = scale * (sum_j w[v, j] A[b, j]) [v_posed[b, v]; 1]`.
///
/// Inputs to `apply`: `v_posed` `[B, V, 3]` and `transforms` `[B, 5, 12]`, contiguous, same dtype
/// (f32 or f64). The weights are constants of the model, kept here in both dtypes so no call
/// converts them.
#[derive(Debug, Clone)]
pub struct Skinning {
    n_vertices: usize,
    weights_f32: Vec<f32>,
    weights_f64: Vec<f64>,
    scale: f64,
}

impl Skinning {
    /// `weights` is `[V, 5]` row-major.
    pub fn new(weights: &[f32], scale: f64) -> Self {
        Self {
            n_vertices: weights.len() / NUM_JOINTS,
            weights_f32: weights.to_vec(),
            weights_f64: weights.iter().map(|&w| w as f64).collect(),
            scale,
        }
    }

    fn batch(&self, v_len: usize, a_len: usize) -> CandleResult<usize> {
        let per = self.n_vertices * 3;
        let b = a_len / JOINT_BLOCK;
        if per == 0 || v_len != b * per || a_len != b * JOINT_BLOCK {
            candle_core::bail!(
                "skinning: {v_len} vertex values and {a_len} transform values do not fit \
                 [B, {}, 3] and [B, {NUM_JOINTS}, {TRANSFORM_LEN}]",
                self.n_vertices
            );
        }
        Ok(b)
    }
}

/// The op as candle wants it for `apply_op2_arc`, shared so calls and model clones don't copy the
/// weights.
#[derive(Clone)]
pub struct SharedSkinning(Arc<Box<dyn CustomOp2 + Send + Sync>>);

impl SharedSkinning {
    pub fn new(op: Skinning) -> Self {
        Self(Arc::new(Box::new(op)))
    }

    pub fn op(&self) -> Arc<Box<dyn CustomOp2 + Send + Sync>> {
        self.0.clone()
    }
}

impl std::fmt::Debug for SharedSkinning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.0.name())
    }
}

fn contiguous<'a, T>(data: &'a [T], layout: &Layout, what: &str) -> CandleResult<&'a [T]> {
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => candle_core::bail!("skinning: {what} must be contiguous"),
    }
}

/// The blended 3x4 transform of one vertex.
#[inline(always)]
fn blend<T: WithDType>(w: &[T], a: &[T; JOINT_BLOCK]) -> [T; TRANSFORM_LEN] {
    let mut m = [T::from_f64(0.0); TRANSFORM_LEN];
    for (aj, &wj) in a.chunks_exact(TRANSFORM_LEN).zip(w) {
        for (mk, &ak) in m.iter_mut().zip(aj) {
            *mk += wj * ak;
        }
    }
    m
}

fn frame_transforms<T: WithDType>(a: &[T], b: usize) -> &[T; JOINT_BLOCK] {
    // `batch` checked the length, so the slice always has the block's size.
    a[b * JOINT_BLOCK..(b + 1) * JOINT_BLOCK]
        .try_into()
        .unwrap_or_else(|_| unreachable!("transform block of a checked batch"))
}

/// Skins one frame: `out` and `v` are its `[V, 3]` slices.
///
/// Most vertices hang on one or two of the five joints, so zero weights are skipped: for finite
/// transforms that is exact (adding `0 * a` never changes the sum). A frame with a non-finite
/// transform takes the dense loop, so NaN and infinity spread exactly as in the matrix form.
fn forward_frame<T: WithDType>(out: &mut [T], v: &[T], a: &[T; JOINT_BLOCK], w: &[T], scale: T) {
    let zero = T::from_f64(0.0);
    let sparse = a.iter().all(|x| x.to_f64().is_finite());
    for ((o, p), wv) in out
        .chunks_exact_mut(3)
        .zip(v.chunks_exact(3))
        .zip(w.chunks_exact(NUM_JOINTS))
    {
        let m = if sparse {
            let mut m = [zero; TRANSFORM_LEN];
            for (aj, &wj) in a.chunks_exact(TRANSFORM_LEN).zip(wv) {
                if wj != zero {
                    for (mk, &ak) in m.iter_mut().zip(aj) {
                        *mk += wj * ak;
                    }
                }
            }
            m
        } else {
            blend(wv, a)
        };
        for (oc, r) in o.iter_mut().zip(m.chunks_exact(4)) {
            *oc = (r[0] * p[0] + r[1] * p[1] + r[2] * p[2] + r[3]) * scale;
        }
    }
}

fn forward<T: WithDType>(v: &[T], a: &[T], w: &[T], nv: usize, scale: f64) -> Vec<T> {
    let scale = T::from_f64(scale);
    let mut out = vec![T::from_f64(0.0); v.len()];
    let per = nv * 3;
    let run = |(b, o): (usize, &mut [T])| {
        forward_frame(
            o,
            &v[b * per..(b + 1) * per],
            frame_transforms(a, b),
            w,
            scale,
        )
    };
    if v.len() / 3 < PARALLEL_MIN_VERTICES {
        out.chunks_exact_mut(per).enumerate().for_each(run);
    } else {
        // One task per frame: frames are large enough (5023 vertices) to amortise scheduling.
        out.par_chunks_exact_mut(per).enumerate().for_each(run);
    }
    out
}

/// Gradients of one frame: `grad_v` (`[V, 3]`) and `grad_a` (`[5, 12]`), given the output
/// gradient `g` (`[V, 3]`).
#[allow(clippy::too_many_arguments)] // one frame's slices of each operand, all needed
fn backward_frame<T: WithDType>(
    grad_v: &mut [T],
    grad_a: &mut [T],
    v: &[T],
    a: &[T; JOINT_BLOCK],
    g: &[T],
    w: &[T],
    nv: usize,
    scale: T,
) {
    for vi in 0..nv {
        let wv = &w[vi * NUM_JOINTS..(vi + 1) * NUM_JOINTS];
        let m = blend(wv, a);
        let p = &v[vi * 3..vi * 3 + 3];
        let gs = [
            g[vi * 3] * scale,
            g[vi * 3 + 1] * scale,
            g[vi * 3 + 2] * scale,
        ];
        for k in 0..3 {
            grad_v[vi * 3 + k] = m[k] * gs[0] + m[4 + k] * gs[1] + m[8 + k] * gs[2];
        }
        let ph = [p[0], p[1], p[2], T::from_f64(1.0)];
        // d out_c / d A[j, c, k] = w_j * ph_k: the outer product gs x ph, weighted per joint.
        let mut outer = [T::from_f64(0.0); TRANSFORM_LEN];
        for c in 0..3 {
            for k in 0..4 {
                outer[c * 4 + k] = gs[c] * ph[k];
            }
        }
        for (j, &wj) in wv.iter().enumerate() {
            let ga = &mut grad_a[j * TRANSFORM_LEN..(j + 1) * TRANSFORM_LEN];
            for (gak, &ok) in ga.iter_mut().zip(&outer) {
                *gak += wj * ok;
            }
        }
    }
}

fn backward<T: WithDType>(
    v: &[T],
    a: &[T],
    g: &[T],
    w: &[T],
    nv: usize,
    scale: f64,
) -> (Vec<T>, Vec<T>) {
    let scale = T::from_f64(scale);
    let b = a.len() / JOINT_BLOCK;
    let mut grad_v = vec![T::from_f64(0.0); v.len()];
    let mut grad_a = vec![T::from_f64(0.0); a.len()];
    let per = nv * 3;
    let run = |(fi, (gv, ga)): (usize, (&mut [T], &mut [T]))| {
        backward_frame(
            gv,
            ga,
            &v[fi * per..(fi + 1) * per],
            frame_transforms(a, fi),
            &g[fi * per..(fi + 1) * per],
            w,
            nv,
            scale,
        )
    };
    if b * nv < PARALLEL_MIN_VERTICES {
        grad_v
            .chunks_exact_mut(per)
            .zip(grad_a.chunks_exact_mut(JOINT_BLOCK))
            .enumerate()
            .for_each(run);
    } else {
        grad_v
            .par_chunks_exact_mut(per)
            .zip(grad_a.par_chunks_exact_mut(JOINT_BLOCK))
            .enumerate()
            .for_each(run);
    }
    (grad_v, grad_a)
}

impl CustomOp2 for Skinning {
    fn name(&self) -> &'static str {
        "flame-skinning"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> CandleResult<(CpuStorage, Shape)> {
        let nv = self.n_vertices;
        let out_shape = l1.shape().clone();
        match (s1, s2) {
            (CpuStorage::F32(v), CpuStorage::F32(a)) => {
                let (v, a) = (
                    contiguous(v, l1, "v_posed")?,
                    contiguous(a, l2, "transforms")?,
                );
                self.batch(v.len(), a.len())?;
                let out = forward(v, a, &self.weights_f32, nv, self.scale);
                Ok((CpuStorage::F32(out), out_shape))
            }
            (CpuStorage::F64(v), CpuStorage::F64(a)) => {
                let (v, a) = (
                    contiguous(v, l1, "v_posed")?,
                    contiguous(a, l2, "transforms")?,
                );
                self.batch(v.len(), a.len())?;
                let out = forward(v, a, &self.weights_f64, nv, self.scale);
                Ok((CpuStorage::F64(out), out_shape))
            }
            _ => candle_core::bail!("skinning: runs on two f32 or two f64 inputs"),
        }
    }

    fn bwd(
        &self,
        v_posed: &Tensor,
        transforms: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> CandleResult<(Option<Tensor>, Option<Tensor>)> {
        let nv = self.n_vertices;
        let dev = v_posed.device();
        let flat = |t: &Tensor| t.flatten_all();
        let (gv, ga) = match v_posed.dtype() {
            DType::F32 => {
                let v = flat(v_posed)?.to_vec1::<f32>()?;
                let a = flat(transforms)?.to_vec1::<f32>()?;
                let g = flat(grad)?.to_dtype(DType::F32)?.to_vec1::<f32>()?;
                self.batch(v.len(), a.len())?;
                let (gv, ga) = backward(&v, &a, &g, &self.weights_f32, nv, self.scale);
                (
                    Tensor::from_vec(gv, v_posed.shape(), dev)?,
                    Tensor::from_vec(ga, transforms.shape(), dev)?,
                )
            }
            DType::F64 => {
                let v = flat(v_posed)?.to_vec1::<f64>()?;
                let a = flat(transforms)?.to_vec1::<f64>()?;
                let g = flat(grad)?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
                self.batch(v.len(), a.len())?;
                let (gv, ga) = backward(&v, &a, &g, &self.weights_f64, nv, self.scale);
                (
                    Tensor::from_vec(gv, v_posed.shape(), dev)?,
                    Tensor::from_vec(ga, transforms.shape(), dev)?,
                )
            }
            dt => candle_core::bail!("skinning: no backward for {dt:?}"),
        };
        Ok((Some(gv), Some(ga)))
    }
}
