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

/// Visible Gaussians sorted front to back (ties by index), with their tile rectangles.
pub fn depth_order<T: Real>(proj: &Projected<T>) -> Vec<(u32, [u16; 4])> {
    // Depths of visible Gaussians are finite and > 0.2, so their f64 bit patterns sort like the
    // values. The keys start in index order and the radix sort is stable, so ties keep index
    // order (the release's stable sort).
    let keys: Vec<(u64, u32)> = proj
        .radius
        .iter()
        .enumerate()
        .filter(|(_, &r)| r > 0)
        .map(|(i, _)| (proj.depth[i].as_f64().to_bits(), i as u32))
        .collect();
    radix_sort(keys)
        .into_iter()
        .map(|(_, i)| (i, proj.rect[i as usize]))
        .collect()
}

/// Bits per radix digit.
const DIGIT: u32 = 11;

/// Stable LSD radix sort by key. Digits where every key agrees (the low bits of f32 depths
/// widened to f64, the exponent of depths in one octave) cost one histogram and no pass.
fn radix_sort(mut a: Vec<(u64, u32)>) -> Vec<(u64, u32)> {
    const B: usize = 1 << DIGIT;
    let digits = 64u32.div_ceil(DIGIT) as usize;
    let mut hist = vec![[0u32; B]; digits];
    for &(k, _) in &a {
        for (d, h) in hist.iter_mut().enumerate() {
            h[((k >> (d as u32 * DIGIT)) as usize) & (B - 1)] += 1;
        }
    }
    let mut b = vec![(0u64, 0u32); a.len()];
    for (d, h) in hist.iter().enumerate() {
        if h.iter().any(|&c| c as usize == a.len()) {
            continue;
        }
        let mut at = [0u32; B];
        let mut sum = 0;
        for (o, &c) in at.iter_mut().zip(h) {
            *o = sum;
            sum += c;
        }
        let shift = d as u32 * DIGIT;
        for &e in &a {
            let slot = &mut at[((e.0 >> shift) as usize) & (B - 1)];
            b[*slot as usize] = e;
            *slot += 1;
        }
        std::mem::swap(&mut a, &mut b);
    }
    a
}

pub fn bin<T: Real>(proj: &Projected<T>, grid_x: usize, grid_y: usize) -> Bins {
    let order = depth_order(proj);
    // Hand each band the Gaussians whose rectangle covers it, keeping depth order.
    let mut members: Vec<Vec<(u32, [u16; 4])>> = vec![Vec::new(); grid_y];
    for &(g, r) in &order {
        for band in &mut members[r[2] as usize..r[3] as usize] {
            band.push((g, r));
        }
    }
    let bands: Vec<Band> = members
        .into_par_iter()
        .map(|members| {
            let mut counts = vec![0u32; grid_x + 1];
            for (_, r) in &members {
                for c in &mut counts[r[0] as usize + 1..r[1] as usize + 1] {
                    *c += 1;
                }
            }
            for tx in 0..grid_x {
                counts[tx + 1] += counts[tx];
            }
            let mut cursor = counts.clone();
            let mut ids = vec![0u32; counts[grid_x] as usize];
            for &(g, r) in &members {
                for c in &mut cursor[r[0] as usize..r[1] as usize] {
                    ids[*c as usize] = g;
                    *c += 1;
                }
            }
            Band {
                offsets: counts,
                ids,
            }
        })
        .collect();
    let pairs = bands.iter().map(|b| b.ids.len()).sum();
    Bins { bands, pairs }
}

#[cfg(test)]
mod tests {
    use super::radix_sort;
    use crate::rng::Rng;

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
        let sorted = radix_sort(keys.clone());
        // The standard library's stable sort by key alone is the reference.
        keys.sort_by_key(|e| e.0);
        assert_eq!(sorted, keys);
        assert!(radix_sort(Vec::new()).is_empty());
    }
}
