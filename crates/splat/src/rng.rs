//! The project's one seeded generator: SplitMix64 (no randomness crate), tiny and fully
//! specified, so a seed means the same data on every machine. Used for test scenes, seeded
//! weights, synthetic datasets and training-pair sampling.

/// SplitMix64.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    /// A generator for `seed` (mixed with a constant, so seed 0 is not the all-zero state).
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }
    /// A generator whose internal state is exactly `state`.
    pub fn from_state(state: u64) -> Self {
        Self(state)
    }
    /// A stream for a seed and a path of stream ids (e.g. `[tag, identity, frame]`); distinct
    /// paths give independent streams.
    pub fn stream(seed: u64, ids: &[u64]) -> Self {
        let mut r = Self(seed ^ 0x6A09_E667_F3BC_C908);
        for &id in ids {
            let mixed = r.next_u64() ^ id.wrapping_mul(0xD1B5_4A32_D192_ED03);
            r = Self(mixed);
            r.next_u64();
        }
        r
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
    /// Uniform in `0..n` (`n > 0`), by 128-bit multiply (bias below 2^-32 for n < 2^32).
    pub fn below(&mut self, n: usize) -> usize {
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }
    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}
