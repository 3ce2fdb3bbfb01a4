//! The portable, AVX2 and AVX-512 versions of our own loops (tile transforms, sums) give the
//! same results: the forward checks of tests/conv.rs at every level this CPU has. A separate
//! binary, since the level is process-wide.

mod common;

use common::*;
use gagavatar_ops::conv::{active_simd_level, limit_simd};

#[test]
fn every_simd_level_matches_candle() {
    let mut covered = Vec::new();
    for level in [0u8, 1, 2] {
        limit_simd(level);
        // A level the CPU lacks falls back to a lower one, which would only repeat a check.
        let available = active_simd_level() == level;
        // One switch for both SIMD levels: a CPU with AVX-512 also has AVX2+FMA, so a run that
        // requires AVX-512 covers every level.
        if !gagavatar_testkit::optional_path(
            &format!("every_simd_level_matches_candle, level {level}"),
            available,
            &format!("this CPU runs level {} at most", active_simd_level()),
            gagavatar_testkit::REQUIRE_AVX512,
        ) {
            continue;
        }
        covered.push(level);
        let mut worst = 0.0f64;
        for (ci, c) in CASES.iter().enumerate() {
            worst = worst.max(check_forward(ci, c));
        }
        println!("SIMD level {level}: max error {worst:.2e}");
    }
    limit_simd(u8::MAX);
    println!("SIMD levels covered: {covered:?}");
}
