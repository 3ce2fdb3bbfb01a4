//! Which pairs are scored (the README's "Evaluation protocol"):
//! - self reenactment: in each video (frames in natural order), the first frame is the source
//!   and every other frame is both the driver and the ground-truth target;
//! - cross reenactment: the source is the first frame of video `i`, the driver a frame of
//!   another video `j`; there is no ground truth. Pair `k` draws `i`, `j != i` and the driver
//!   frame uniformly from a SplitMix64 stream seeded by `(seed, k)`, so the list is a pure
//!   function of the videos, the count and the seed (and is written beside the scores). A
//!   pair drawn twice is skipped, so the pairs are distinct.
//!
//! `limit` for self reenactment keeps a seeded uniform subset, in list order.

use serde::{Deserialize, Serialize};

use crate::error::{input_err, Result};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    #[serde(rename = "self")]
    SelfReenactment,
    Cross,
}

impl Mode {
    pub fn name(self) -> &'static str {
        match self {
            Mode::SelfReenactment => "self",
            Mode::Cross => "cross",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "self" => Some(Mode::SelfReenactment),
            "cross" => Some(Mode::Cross),
            _ => None,
        }
    }
}

/// One scored pair: the source photo, and the driving frame (the target too in self
/// reenactment).
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct EvalPair {
    pub mode: Mode,
    pub source: String,
    pub driver: String,
}

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A SplitMix64 stream.
struct Stream(u64);

impl Stream {
    fn new(seed: u64, salt: u64, k: u64) -> Self {
        Stream(splitmix(splitmix(seed ^ salt).wrapping_add(k)))
    }
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        splitmix(self.0)
    }
    /// Uniform in `0..n` (`n > 0`); the modulo bias is below 2^-40 for any realistic `n`.
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

const SALT_SELF: u64 = 0x5E1F_0000;
const SALT_CROSS: u64 = 0xC205_5000;

/// Self-reenactment pairs of `videos` (each a list of frame names in natural order; videos
/// with fewer than two frames give none).
pub fn self_pairs(videos: &[Vec<String>], limit: Option<usize>, seed: u64) -> Vec<EvalPair> {
    let all: Vec<EvalPair> = videos
        .iter()
        .filter(|v| v.len() >= 2)
        .flat_map(|v| {
            v[1..].iter().map(|d| EvalPair {
                mode: Mode::SelfReenactment,
                source: v[0].clone(),
                driver: d.clone(),
            })
        })
        .collect();
    match limit {
        Some(n) if n < all.len() => {
            // Partial Fisher-Yates over indices, then back to list order.
            let mut idx: Vec<usize> = (0..all.len()).collect();
            let mut rng = Stream::new(seed, SALT_SELF, 0);
            for i in 0..n {
                let j = i + rng.below(all.len() - i);
                idx.swap(i, j);
            }
            let mut keep = idx[..n].to_vec();
            keep.sort_unstable();
            keep.into_iter().map(|i| all[i].clone()).collect()
        }
        _ => all,
    }
}

/// `n` distinct cross-reenactment pairs (fewer when the split has fewer); needs two or more
/// non-empty videos.
pub fn cross_pairs(videos: &[Vec<String>], n: usize, seed: u64) -> Result<Vec<EvalPair>> {
    let v: Vec<&Vec<String>> = videos.iter().filter(|v| !v.is_empty()).collect();
    if v.len() < 2 {
        return Err(input_err(
            "videos",
            format!(
                "cross reenactment needs two or more videos, the split has {}",
                v.len()
            ),
        ));
    }
    let frames: usize = v.iter().map(|x| x.len()).sum();
    let possible: usize = v.iter().map(|x| frames - x.len()).sum();
    let n = n.min(possible);
    let mut seen = std::collections::HashSet::new();
    let mut out = Vec::with_capacity(n);
    // Draw k = 0, 1, ... until n distinct pairs; a repeat is skipped (the next k draws anew).
    let mut k = 0u64;
    while out.len() < n {
        let mut rng = Stream::new(seed, SALT_CROSS, k);
        k += 1;
        let i = rng.below(v.len());
        let j = (i + 1 + rng.below(v.len() - 1)) % v.len();
        let d = rng.below(v[j].len());
        let p = EvalPair {
            mode: Mode::Cross,
            source: v[i][0].clone(),
            driver: v[j][d].clone(),
        };
        if seen.insert(p.clone()) {
            out.push(p);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn videos() -> Vec<Vec<String>> {
        (0..4)
            .map(|v| (0..5).map(|f| format!("v{v}_{f}")).collect())
            .chain(std::iter::once(vec!["lonely_0".to_string()]))
            .collect()
    }

    #[test]
    fn self_pairs_use_the_first_frame_as_source() {
        let p = self_pairs(&videos(), None, 0);
        assert_eq!(p.len(), 16);
        assert!(p
            .iter()
            .all(|p| p.source.ends_with("_0") && !p.driver.ends_with("_0")));
        assert_eq!(p[0].driver, "v0_1");
        let sub = self_pairs(&videos(), Some(5), 3);
        assert_eq!(sub.len(), 5);
        assert_eq!(sub, self_pairs(&videos(), Some(5), 3), "seeded");
        assert_ne!(sub, self_pairs(&videos(), Some(5), 4));
        assert!(sub.windows(2).all(|w| w[0] < w[1]), "list order kept");
    }

    #[test]
    fn cross_pairs_mix_videos_and_are_seeded() {
        let p = cross_pairs(&videos(), 200, 9).unwrap();
        assert_eq!(p, cross_pairs(&videos(), 200, 9).unwrap());
        assert_ne!(p, cross_pairs(&videos(), 200, 10).unwrap());
        let video = |s: &str| s.split('_').next().unwrap().to_string();
        for q in &p {
            assert!(q.source.ends_with("_0"), "{q:?}");
            assert_ne!(video(&q.source), video(&q.driver), "{q:?}");
        }
        // Every video serves as source and as driver somewhere.
        for v in ["v0", "v1", "v2", "v3", "lonely"] {
            assert!(
                p.iter().any(|q| video(&q.source) == v),
                "{v} never a source"
            );
            assert!(p.iter().any(|q| video(&q.driver) == v), "{v} never drives");
        }
        let distinct: std::collections::HashSet<_> = p.iter().collect();
        assert_eq!(distinct.len(), p.len(), "pairs repeat");
        // 5 sources x the frames of the other videos: 4 * 16 + 20 = 84 distinct pairs at most.
        assert_eq!(cross_pairs(&videos(), 1000, 1).unwrap().len(), 84);
        assert!(cross_pairs(&videos()[..1], 3, 0).is_err());
        assert!(cross_pairs(&[], 3, 0).is_err());
    }
}
