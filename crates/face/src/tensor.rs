//! The feature maps the networks pass between layers: one image, NHWC (TFLite's layout), f32.
//!
//! Buffers are recycled: a dropped map's storage goes to a small per-thread pool that the next
//! map of a similar size takes, already initialised, so a forward pass neither page-faults
//! fresh memory nor zero-fills outputs that its kernel overwrites anyway.

use std::cell::RefCell;
use std::collections::HashMap;

/// A `h x w x c` feature map, channels fastest (`data[(y * w + x) * c + ch]`).
#[derive(Debug, PartialEq)]
pub struct Nhwc {
    pub h: usize,
    pub w: usize,
    pub c: usize,
    pub data: Vec<f32>,
}

/// The most bytes the buffers kept per thread may hold.
const POOL_BYTES: usize = 64 << 20;

/// Dropped buffers by length: a forward pass asks for the same sizes frame after frame, so an
/// exact-length match is the common case and needs no fill.
#[derive(Default)]
struct Pool {
    by_len: HashMap<usize, Vec<Vec<f32>>>,
    bytes: usize,
}

thread_local! {
    static POOL: RefCell<Pool> = RefCell::new(Pool::default());
}

/// A buffer of `n` values with unspecified (initialised) contents: for outputs a kernel
/// overwrites entirely.
pub fn take(n: usize) -> Vec<f32> {
    let reused = POOL.with(|p| {
        let mut p = p.borrow_mut();
        let v = p.by_len.get_mut(&n).and_then(Vec::pop);
        if let Some(v) = &v {
            p.bytes -= v.capacity() * 4;
        }
        v
    });
    reused.unwrap_or_else(|| vec![0.0; n])
}

/// Returns a buffer to this thread's pool (dropped instead when the pool is full, or when it
/// is too small to be worth keeping).
pub fn give(v: Vec<f32>) {
    if v.capacity() < 1024 || v.len() != v.capacity() {
        return;
    }
    POOL.with(|p| {
        let mut p = p.borrow_mut();
        let bytes = v.capacity() * 4;
        if p.bytes + bytes <= POOL_BYTES {
            p.bytes += bytes;
            p.by_len.entry(v.len()).or_default().push(v);
        }
    });
}

impl Drop for Nhwc {
    fn drop(&mut self) {
        give(std::mem::take(&mut self.data));
    }
}

impl Clone for Nhwc {
    fn clone(&self) -> Self {
        let mut data = take(self.data.len());
        data.copy_from_slice(&self.data);
        Nhwc::from_vec(self.h, self.w, self.c, data)
    }
}

impl Nhwc {
    /// A map of zeros.
    pub fn zeros(h: usize, w: usize, c: usize) -> Self {
        let mut data = take(h * w * c);
        data.fill(0.0);
        Nhwc { h, w, c, data }
    }

    /// A map whose values the caller overwrites entirely.
    pub fn uninit(h: usize, w: usize, c: usize) -> Self {
        Nhwc {
            h,
            w,
            c,
            data: take(h * w * c),
        }
    }

    /// Wraps `data`, which must hold exactly `h * w * c` values.
    pub fn from_vec(h: usize, w: usize, c: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), h * w * c, "feature map size");
        Nhwc { h, w, c, data }
    }

    /// The values, moved out.
    pub fn into_vec(mut self) -> Vec<f32> {
        std::mem::take(&mut self.data)
    }

    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.h * self.w
    }

    /// The `c` values of pixel `(y, x)`.
    pub fn at(&self, y: usize, x: usize) -> &[f32] {
        let o = (y * self.w + x) * self.c;
        &self.data[o..o + self.c]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recycled_buffers_have_the_asked_size() {
        let a = Nhwc::zeros(40, 40, 8);
        let ptr = a.data.as_ptr();
        drop(a);
        let b = Nhwc::uninit(20, 20, 8);
        assert_eq!(b.data.len(), 3200);
        drop(b);
        let c = Nhwc::uninit(40, 40, 8);
        assert_eq!(c.data.as_ptr(), ptr, "the same size is reused");
        drop(c);
        let d = Nhwc::zeros(40, 41, 8);
        assert_eq!(d.data.len(), 40 * 41 * 8);
        assert!(d.data.iter().all(|&v| v == 0.0));
    }
}
