//! The portable, AVX2 and AVX-512 versions of our own loops (tile transforms, sums) give the
//! same results: the forward checks of tests/conv.rs at every level this CPU has. A separate
//! binary, since the level is process-wide.

mod common;

use common::*;
use gagavatar_ops::conv::limit_simd;

#[test]
fn every_simd_level_matches_candle() {
    for level in [0u8, 1, 2] {
        limit_simd(level);
        let mut worst = 0.0f64;
        for (ci, c) in CASES.iter().enumerate() {
            worst = worst.max(check_forward(ci, c));
        }
        println!("SIMD level {level}: max error {worst:.2e}");
    }
    limit_simd(u8::MAX);
}
