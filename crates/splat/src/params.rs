//! The release rasterizer's thresholds and the layout of the screen-space gradients, shared by
//! the projection (which culls with them) and the rasterizer.

/// Alpha is clamped to this value so a single Gaussian never makes a pixel fully opaque.
pub const MAX_ALPHA: f64 = 0.99;
/// Contributions with alpha below 1/255 are skipped.
pub const MIN_ALPHA: f64 = 1.0 / 255.0;
/// A pixel stops before a Gaussian would take its transmittance below this.
pub const MIN_TRANSMITTANCE: f64 = 1e-4;
/// Screen-space gradient entries per Gaussian: mean x, mean y, conic A, B, C, opacity.
pub const SCREEN: usize = 6;
