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
    // values; the index makes every key unique, so an unstable sort gives the stable order.
    let mut keys: Vec<(u64, u32)> = proj
        .radius
        .iter()
        .enumerate()
        .filter(|(_, &r)| r > 0)
        .map(|(i, _)| (proj.g[i].depth.as_f64().to_bits(), i as u32))
        .collect();
    keys.par_sort_unstable();
    keys.into_iter()
        .map(|(_, i)| (i, proj.rect[i as usize]))
        .collect()
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
