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

/// Visible Gaussian indices sorted front to back (ties by index).
pub fn depth_order<T: Real>(proj: &Projected<T>) -> Vec<u32> {
    let mut order: Vec<u32> = (0..proj.radius.len() as u32)
        .filter(|&i| proj.radius[i as usize] > 0)
        .collect();
    // Keys are unique (index breaks ties), so an unstable sort gives the stable order.
    order.par_sort_unstable_by(|&a, &b| {
        proj.depth[a as usize]
            .total_cmp(&proj.depth[b as usize])
            .then(a.cmp(&b))
    });
    order
}

pub fn bin<T: Real>(proj: &Projected<T>, grid_x: usize, grid_y: usize) -> Bins {
    let order = depth_order(proj);
    let bands: Vec<Band> = (0..grid_y)
        .into_par_iter()
        .map(|ty| {
            let ty = ty as u16;
            let mut counts = vec![0u32; grid_x + 1];
            let mut members = Vec::new();
            for &g in &order {
                let [x0, x1, y0, y1] = proj.rect[g as usize];
                if y0 <= ty && ty < y1 {
                    members.push(g);
                    for c in &mut counts[x0 as usize + 1..x1 as usize + 1] {
                        *c += 1;
                    }
                }
            }
            for tx in 0..grid_x {
                counts[tx + 1] += counts[tx];
            }
            let mut cursor = counts.clone();
            let mut ids = vec![0u32; counts[grid_x] as usize];
            for &g in &members {
                let [x0, x1, _, _] = proj.rect[g as usize];
                for c in &mut cursor[x0 as usize..x1 as usize] {
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
