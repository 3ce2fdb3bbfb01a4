//! Exact nearest neighbours in 3-D and the lifting-distance loss (spec section 11: for every
//! scaled target FLAME vertex, the squared distance to the nearest lifted point, times 10,
//! averaged).
//!
//! The search is a k-d tree over the lifted points (rebuilt per sample: the points move every
//! step), on plain f32 host data. It is exact in floating point, not just in real arithmetic:
//! every squared distance is `dx*dx + dy*dy + dz*dz` in f32 in that order (as a brute-force scan
//! computes it), and a subtree is skipped only when its lower bound, the same expression over
//! the per-axis gaps to the subtree's exact point bounding box, is strictly greater than the
//! best distance found. Rounding is monotone, so that bound never exceeds the rounded distance
//! of any point inside; the result (distance and index; ties go to the lowest index) is the
//! brute-force one bit for bit.
//!
//! The loss then recomputes the distances with tensor ops on the selected points
//! (`index_select`), so gradients flow into the lifted points; the search itself is not
//! differentiated (the nearest index is piecewise constant).

use candle_core::{DType, Device, Tensor};
use rayon::prelude::*;

use crate::error::{input_err, Result};

/// Multiplier of the lifting-distance loss in the release.
pub const LIFTING_WEIGHT: f64 = 10.0;
/// Points per leaf: small enough to prune well, large enough to amortise the traversal.
const LEAF_SIZE: usize = 12;
/// Subtrees at least this large are built in parallel.
const PAR_BUILD_MIN: usize = 16_384;
const NONE: u32 = u32::MAX;

#[derive(Debug, Clone, Copy)]
struct Node {
    lo: [f32; 3],
    hi: [f32; 3],
    /// Leaf: the range `start..end` of the reordered points. Internal: children ids.
    start: u32,
    end: u32,
    left: u32,
    right: u32,
}

/// A k-d tree over 3-D points (exact nearest-neighbour queries, see the module docs).
#[derive(Debug, Clone)]
pub struct KdTree {
    /// The points, reordered so every node owns a contiguous range.
    pts: Vec<[f32; 3]>,
    /// Original index of each reordered point.
    ids: Vec<u32>,
    nodes: Vec<Node>,
}

#[inline]
fn dist2(q: &[f32; 3], p: &[f32; 3]) -> f32 {
    let dx = q[0] - p[0];
    let dy = q[1] - p[1];
    let dz = q[2] - p[2];
    dx * dx + dy * dy + dz * dz
}

/// Lower bound of `dist2(q, p)` over every `p` in the box `[lo, hi]` (same rounding order).
#[inline]
fn box_dist2(q: &[f32; 3], lo: &[f32; 3], hi: &[f32; 3]) -> f32 {
    let gap = |a: usize| -> f32 {
        if q[a] < lo[a] {
            lo[a] - q[a]
        } else if q[a] > hi[a] {
            q[a] - hi[a]
        } else {
            0.0
        }
    };
    let (gx, gy, gz) = (gap(0), gap(1), gap(2));
    gx * gx + gy * gy + gz * gz
}

fn bounds(items: &[([f32; 3], u32)]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for (p, _) in items {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

/// A subtree built on its own (node ids local to it, point ranges relative to its slice).
struct Built {
    nodes: Vec<Node>,
}

fn build_rec(items: &mut [([f32; 3], u32)]) -> Built {
    let (lo, hi) = bounds(items);
    let n = items.len();
    if n <= LEAF_SIZE {
        return Built {
            nodes: vec![Node {
                lo,
                hi,
                start: 0,
                end: n as u32,
                left: NONE,
                right: NONE,
            }],
        };
    }
    let axis = (0..3)
        .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
        .unwrap_or(0);
    let mid = n / 2;
    items.select_nth_unstable_by(mid, |a, b| a.0[axis].total_cmp(&b.0[axis]));
    let (l, r) = items.split_at_mut(mid);
    let (bl, br) = if n >= PAR_BUILD_MIN {
        rayon::join(|| build_rec(l), || build_rec(r))
    } else {
        (build_rec(l), build_rec(r))
    };
    // Layout: this node, then the left subtree, then the right one (ids shifted).
    let mut nodes = Vec::with_capacity(1 + bl.nodes.len() + br.nodes.len());
    let left = 1u32;
    let right = 1 + bl.nodes.len() as u32;
    nodes.push(Node {
        lo,
        hi,
        start: 0,
        end: n as u32,
        left,
        right,
    });
    for (sub, id0, p0) in [(bl, left, 0u32), (br, right, mid as u32)] {
        nodes.extend(sub.nodes.into_iter().map(|mut nd| {
            if nd.left != NONE {
                nd.left += id0;
                nd.right += id0;
            }
            nd.start += p0;
            nd.end += p0;
            nd
        }));
    }
    Built { nodes }
}

impl KdTree {
    /// Builds the tree. Errors on an empty set or a non-finite coordinate.
    pub fn new(points: &[[f32; 3]]) -> Result<Self> {
        if points.is_empty() {
            return Err(input_err("lifted points", "the point set is empty"));
        }
        if points.len() >= NONE as usize {
            return Err(input_err(
                "lifted points",
                format!("{} points exceed the u32 index range", points.len()),
            ));
        }
        check_finite(points, "lifted points")?;
        let mut items: Vec<([f32; 3], u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (*p, i as u32))
            .collect();
        let built = build_rec(&mut items);
        let (pts, ids) = items.into_iter().unzip();
        Ok(Self {
            pts,
            ids,
            nodes: built.nodes,
        })
    }

    pub fn len(&self) -> usize {
        self.pts.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pts.is_empty()
    }

    /// The nearest point to `q`: `(original index, squared distance)`; ties go to the lowest
    /// index. `q` must be finite (see [`KdTree::nearest_all`] for a checked batch query).
    pub fn nearest(&self, q: &[f32; 3]) -> (u32, f32) {
        let mut best = (NONE, f32::INFINITY);
        // Explicit stack of (node, lower bound); depth is ~log2(n / LEAF_SIZE).
        let mut stack: Vec<(u32, f32)> = Vec::with_capacity(64);
        if let Some(root) = self.nodes.first() {
            stack.push((0, box_dist2(q, &root.lo, &root.hi)));
        }
        while let Some((id, bound)) = stack.pop() {
            // `>` (not `>=`) keeps subtrees that may hold an equally near, lower-index point.
            if bound > best.1 {
                continue;
            }
            let nd = &self.nodes[id as usize];
            if nd.left == NONE {
                let (s, e) = (nd.start as usize, nd.end as usize);
                for (p, &i) in self.pts[s..e].iter().zip(&self.ids[s..e]) {
                    let d = dist2(q, p);
                    if d < best.1 || (d == best.1 && i < best.0) {
                        best = (i, d);
                    }
                }
                continue;
            }
            let (l, r) = (
                &self.nodes[nd.left as usize],
                &self.nodes[nd.right as usize],
            );
            let (bl, br) = (box_dist2(q, &l.lo, &l.hi), box_dist2(q, &r.lo, &r.hi));
            // Push the farther child first so the nearer one is searched first.
            if bl <= br {
                stack.push((nd.right, br));
                stack.push((nd.left, bl));
            } else {
                stack.push((nd.left, bl));
                stack.push((nd.right, br));
            }
        }
        best
    }

    /// [`KdTree::nearest`] for every query, in parallel. Errors on a non-finite query.
    pub fn nearest_all(&self, queries: &[[f32; 3]]) -> Result<Vec<(u32, f32)>> {
        check_finite(queries, "query points")?;
        Ok(queries
            .par_chunks(256)
            .flat_map_iter(|c| c.iter().map(|q| self.nearest(q)))
            .collect())
    }
}

fn check_finite(points: &[[f32; 3]], name: &str) -> Result<()> {
    match points.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
        Some(i) => Err(input_err(
            name,
            format!("point {i} = {:?} is not finite", points[i]),
        )),
        None => Ok(()),
    }
}

/// The brute-force reference: the same distances and tie rule as [`KdTree::nearest`].
pub fn nearest_brute_force(points: &[[f32; 3]], q: &[f32; 3]) -> Option<(u32, f32)> {
    let mut best: Option<(u32, f32)> = None;
    for (i, p) in points.iter().enumerate() {
        let d = dist2(q, p);
        if best.is_none_or(|(_, bd)| d < bd) {
            best = Some((i as u32, d));
        }
    }
    best
}

fn as_points(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

fn check_point_batch(t: &Tensor, name: &str) -> Result<(usize, usize)> {
    match t.dims() {
        &[b, n, 3] if b > 0 && n > 0 => Ok((b, n)),
        &[_, 0, 3] => Err(input_err(name, "the point set is empty")),
        other => Err(input_err(
            name,
            format!("expected a non-empty [B, N, 3] point batch, got {other:?}"),
        )),
    }
}

/// For each sample `b` and target `m`: the index (into `lifted[b]`) of the nearest lifted point
/// and the squared distance (f32 search, see the module docs). `lifted` `[B, N, 3]`, `targets`
/// `[B, M, 3]`, any float dtype and device (read back to the host, not differentiated).
pub fn nearest_indices(lifted: &Tensor, targets: &Tensor) -> Result<Vec<Vec<(u32, f32)>>> {
    let (b, n) = check_point_batch(lifted, "lifted points")?;
    let (bt, m) = check_point_batch(targets, "target points")?;
    if bt != b {
        return Err(input_err(
            "target points",
            format!("batch {bt} differs from the lifted points' {b}"),
        ));
    }
    let host = |t: &Tensor| -> Result<Vec<f32>> {
        Ok(t.detach()
            .to_dtype(DType::F32)?
            .flatten_all()?
            .to_vec1::<f32>()?)
    };
    let (lv, tv) = (host(lifted)?, host(targets)?);
    (0..b)
        .into_par_iter()
        .map(|i| {
            let tree = KdTree::new(&as_points(&lv[i * n * 3..(i + 1) * n * 3]))
                .map_err(|e| rename(e, &format!("lifted points[{i}]")))?;
            tree.nearest_all(&as_points(&tv[i * m * 3..(i + 1) * m * 3]))
                .map_err(|e| rename(e, &format!("target points[{i}]")))
        })
        .collect()
}

fn rename(e: crate::TrainError, name: &str) -> crate::TrainError {
    match e {
        crate::TrainError::Input { reason, .. } => input_err(name, reason),
        other => other,
    }
}

/// The lifting-distance loss: `10 * mean over (b, m) of |targets[b, m] - lifted[b, nn(b, m)]|^2`
/// where `nn` is the exact nearest lifted point (both dual-lifting sets together). `lifted`
/// `[B, N, 3]` (differentiable), `targets` `[B, M, 3]` (the scaled target FLAME vertices; cast
/// to `lifted`'s dtype). Returns a scalar tensor on `lifted`'s device.
pub fn lifting_loss(lifted: &Tensor, targets: &Tensor) -> Result<Tensor> {
    let nn = nearest_indices(lifted, targets)?;
    let (b, n, _) = lifted.dims3()?;
    let m = targets.dims()[1];
    if b * n > NONE as usize {
        return Err(input_err(
            "lifted points",
            format!("{b} x {n} points exceed the u32 index range"),
        ));
    }
    let flat: Vec<u32> = nn
        .iter()
        .enumerate()
        .flat_map(|(i, row)| row.iter().map(move |&(j, _)| i as u32 * n as u32 + j))
        .collect();
    let device: &Device = lifted.device();
    let idx = Tensor::from_vec(flat, b * m, device)?;
    let chosen = lifted.reshape((b * n, 3))?.index_select(&idx, 0)?;
    let t = targets
        .to_dtype(lifted.dtype())?
        .to_device(device)?
        .reshape((b * m, 3))?;
    let d2 = (t - chosen)?.sqr()?.sum(1)?;
    Ok((d2.mean_all()? * LIFTING_WEIGHT)?)
}
