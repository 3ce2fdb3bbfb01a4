//! Tile binning: every visible Gaussian is listed in each 16x16 tile its rectangle touches,
//! front to back by view depth with ties broken by Gaussian index (what the release's stable
//! radix sort produces). Tiles are grouped in bands (one row of tiles each) so that forward and
//! backward can work on disjoint output rows in parallel.

use crate::project::Projected;
use crate::real::Real;
use rayon::prelude::*;

/// The tile lists of one row of tiles, in compressed-row form.
#[derive(Debug, Clone, Default)]
pub struct Band {
    /// `ids[offsets[tx]..offsets[tx + 1]]` are the Gaussians of tile `tx`, front to back.
    pub offsets: Vec<u32>,
    pub ids: Vec<u32>,
}

impl Band {
    #[inline]
    pub fn tile(&self, tx: usize) -> &[u32] {
        &self.ids[self.offsets[tx] as usize..self.offsets[tx + 1] as usize]
    }
}

#[derive(Debug, Clone, Default)]
pub struct Bins {
    pub bands: Vec<Band>,
    /// Total (tile, Gaussian) pairs.
    pub pairs: usize,
}

/// Visible Gaussians sorted front to back, ties by index (the release's stable sort), with
/// their tile rectangles (gathered once here, in parallel: read in depth order, the
/// rectangles are scattered reads that miss the cache).
pub fn depth_order<T: Real>(proj: &Projected<T>) -> Vec<(u32, [u16; 4])> {
    if std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>() {
        // A visible Gaussian's f32 depth is finite and > 0.2, so its bit pattern sorts like
        // the value; with the index below it, every key is distinct and in the wanted order.
        // Culled ones sort last (u64::MAX) and are cut off.
        let keys: Vec<u64> = proj
            .depth
            .par_iter()
            .zip(&proj.radius)
            .enumerate()
            .map(|(i, (d, &r))| {
                let bits = (d.as_f64() as f32).to_bits() as u64;
                if r > 0 {
                    bits << 32 | i as u64
                } else {
                    u64::MAX
                }
            })
            .collect();
        let visible = proj.radius.iter().filter(|&&r| r > 0).count();
        let mut sorted = radix_sort_by(keys, 32..64, |k| k);
        sorted.truncate(visible);
        return sorted
            .par_iter()
            .map(|&k| (k as u32, proj.rect[k as u32 as usize]))
            .collect();
    }
    // f64 depths: their bit patterns, with the index alongside.
    let keys: Vec<(u64, u32)> = proj
        .radius
        .iter()
        .enumerate()
        .filter(|(_, &r)| r > 0)
        .map(|(i, _)| (proj.depth[i].as_f64().to_bits(), i as u32))
        .collect();
    radix_sort_by(keys, 0..64, |e| e.0)
        .into_iter()
        .map(|(_, i)| (i, proj.rect[i as usize]))
        .collect()
}

/// Bits per radix digit.
const DIGIT: u32 = 11;

/// Stable LSD radix sort of `a` by bits `bits` of `key`, in parallel: each thread takes one
/// consecutive part of the input, counts its digits, and scatters its part to where the
/// parts before it end (so ties keep their input order). Digits where every key agrees (the
/// low bits of f32 depths widened to f64, the exponent of depths in one octave) cost one
/// count and no pass.
fn radix_sort_by<E: Copy + Default + Send + Sync>(
    mut a: Vec<E>,
    bits: std::ops::Range<u32>,
    key: impl Fn(E) -> u64 + Sync,
) -> Vec<E> {
    const B: usize = 1 << DIGIT;
    let n = a.len();
    let part = n.div_ceil(rayon::current_num_threads().max(1)).max(1);
    let mut b = vec![E::default(); n];
    let mut shift = bits.start;
    while shift < bits.end {
        let sh = shift;
        let digit = |e: E| ((key(e) >> sh) as usize) & (B - 1);
        let hists: Vec<Vec<u32>> = a
            .par_chunks(part)
            .map(|c| {
                let mut h = vec![0u32; B];
                for &e in c {
                    h[digit(e)] += 1;
                }
                h
            })
            .collect();
        shift += DIGIT;
        if (0..B).any(|d| hists.iter().map(|h| h[d] as usize).sum::<usize>() == n) {
            continue;
        }
        // The output in order is: digit 0 of part 0, of part 1, ..., digit 1 of part 0, ...
        // Split it so, and hand each part its slice per digit.
        let mut slots: Vec<Vec<&mut [E]>> = (0..hists.len()).map(|_| Vec::new()).collect();
        let mut rest: &mut [E] = &mut b;
        for d in 0..B {
            for (p, h) in hists.iter().enumerate() {
                let (head, tail) = rest.split_at_mut(h[d] as usize);
                slots[p].push(head);
                rest = tail;
            }
        }
        a.par_chunks(part)
            .zip(slots.into_par_iter())
            .for_each(|(c, mut dst)| {
                let mut at = vec![0usize; B];
                for &e in c {
                    let d = digit(e);
                    dst[d][at[d]] = e;
                    at[d] += 1;
                }
            });
        std::mem::swap(&mut a, &mut b);
    }
    a
}

pub fn bin<T: Real>(proj: &Projected<T>, grid_x: usize, grid_y: usize) -> Bins {
    let order = depth_order(proj);
    let tiles = grid_x * grid_y;
    // Each thread lists one consecutive part of the order in its own tile-major lists, so a
    // tile's list is the concatenation of the parts' lists for it, in part order.
    let part = order
        .len()
        .div_ceil(rayon::current_num_threads().max(1))
        .max(1);
    let lists: Vec<(Vec<u32>, Vec<u32>)> = order
        .par_chunks(part)
        .map(|chunk| {
            let mut offsets = vec![0u32; tiles + 1];
            for &(_, r) in chunk {
                for ty in r[2] as usize..r[3] as usize {
                    for c in &mut offsets
                        [ty * grid_x + r[0] as usize + 1..ty * grid_x + r[1] as usize + 1]
                    {
                        *c += 1;
                    }
                }
            }
            for t in 0..tiles {
                offsets[t + 1] += offsets[t];
            }
            let mut cursor = offsets.clone();
            let mut ids = vec![0u32; offsets[tiles] as usize];
            for &(g, r) in chunk {
                for ty in r[2] as usize..r[3] as usize {
                    for c in &mut cursor[ty * grid_x + r[0] as usize..ty * grid_x + r[1] as usize] {
                        ids[*c as usize] = g;
                        *c += 1;
                    }
                }
            }
            (offsets, ids)
        })
        .collect();
    let bands: Vec<Band> = (0..grid_y)
        .into_par_iter()
        .map(|ty| {
            let mut offsets = Vec::with_capacity(grid_x + 1);
            let mut ids = Vec::new();
            offsets.push(0);
            for tx in 0..grid_x {
                let t = ty * grid_x + tx;
                for (o, part_ids) in &lists {
                    ids.extend_from_slice(&part_ids[o[t] as usize..o[t + 1] as usize]);
                }
                offsets.push(ids.len() as u32);
            }
            Band { offsets, ids }
        })
        .collect();
    let pairs = bands.iter().map(|b| b.ids.len()).sum();
    Bins { bands, pairs }
}

#[cfg(test)]
mod tests {
    use super::{bin, radix_sort_by};
    use crate::project::{Projected, Splat2D};
    use crate::rng::Rng;

    /// The parallel sort against the standard library's stable sort by the same bits, with
    /// one to three parts and many ties.
    #[test]
    fn parallel_radix_sort_is_a_stable_sort() {
        let mut rng = Rng::new(5);
        for threads in 1..=3 {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for n in [0usize, 1, 7, 5000] {
                let keys: Vec<u64> = (0..n as u64)
                    .map(|i| {
                        let k = match i % 3 {
                            0 => rng.below(40) as u64,
                            1 => rng.below(1 << 20) as u64,
                            _ => (rng.range(0.2, 50.0) as f32).to_bits() as u64,
                        };
                        k << 32 | i
                    })
                    .collect();
                let mut want = keys.clone();
                want.sort_by_key(|k| k >> 32);
                let got = pool.install(|| radix_sort_by(keys, 32..64, |k| k));
                assert_eq!(got, want, "{threads} threads, {n} keys");
            }
        }
    }

    /// Tile lists against their definition: every visible Gaussian whose rectangle covers the
    /// tile, by depth, ties by index; with tied depths, culled Gaussians and rectangles at the
    /// grid's edges, for one to three threads.
    #[test]
    fn bins_are_the_depth_sorted_covering_gaussians() {
        let (gx, gy) = (7usize, 5usize);
        let mut rng = Rng::new(9);
        let n = 3000;
        let mut proj = Projected::<f32>::default();
        for _ in 0..n {
            let (x0, y0) = (rng.below(gx), rng.below(gy));
            let (x1, y1) = (x0 + 1 + rng.below(gx - x0), y0 + 1 + rng.below(gy - y0));
            let visible = rng.below(5) != 0;
            proj.g.push(Splat2D::default());
            proj.depth
                .push([1.0, 2.5, rng.range(0.3, 9.0) as f32][rng.below(3)]);
            proj.radius.push(visible as u32 * 3);
            proj.rect.push(if visible {
                [x0 as u16, x1 as u16, y0 as u16, y1 as u16]
            } else {
                [0; 4]
            });
        }
        for threads in 1..=3 {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let bins = pool.install(|| bin(&proj, gx, gy));
            let mut pairs = 0;
            for ty in 0..gy {
                for tx in 0..gx {
                    let mut want: Vec<u32> = (0..n as u32)
                        .filter(|&i| {
                            let r = proj.rect[i as usize].map(|v| v as usize);
                            proj.radius[i as usize] > 0
                                && (r[0]..r[1]).contains(&tx)
                                && (r[2]..r[3]).contains(&ty)
                        })
                        .collect();
                    want.sort_by(|&a, &b| {
                        proj.depth[a as usize].total_cmp(&proj.depth[b as usize])
                    });
                    pairs += want.len();
                    assert_eq!(
                        bins.bands[ty].tile(tx),
                        &want[..],
                        "{threads} threads, tile {tx},{ty}"
                    );
                }
            }
            assert_eq!(bins.pairs, pairs);
        }
    }

    #[test]
    fn radix_sort_is_a_stable_sort() {
        let mut rng = Rng::new(7);
        // Few distinct keys (many ties), spread over every digit, f32 depths widened to f64.
        let mut keys: Vec<(u64, u32)> = (0..5000u32)
            .map(|i| {
                let k = match i % 3 {
                    0 => rng.below(40) as u64,
                    1 => (rng.below(1 << 20) as u64) << 40,
                    _ => ((rng.range(0.2, 50.0) as f32) as f64).to_bits(),
                };
                (k, i)
            })
            .collect();
        let sorted = radix_sort_by(keys.clone(), 0..64, |e| e.0);
        // The standard library's stable sort by key alone is the reference.
        keys.sort_by_key(|e| e.0);
        assert_eq!(sorted, keys);
        assert!(radix_sort_by(Vec::<(u64, u32)>::new(), 0..64, |e| e.0).is_empty());
    }
}
