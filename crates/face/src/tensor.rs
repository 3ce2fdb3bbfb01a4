//! The feature maps the networks pass between layers: one image, NHWC (TFLite's layout), f32.
//!
//! Buffers are recycled: a dropped map's storage goes to a small per-thread pool that the next
//! map of a similar size takes, already initialised, so a forward pass neither page-faults
//! fresh memory nor zero-fills outputs that its kernel overwrites anyway.

use std::cell::RefCell;

/// A `h x w x c` feature map, channels fastest (`data[(y * w + x) * c + ch]`).
#[derive(Debug, PartialEq)]
pub struct Nhwc {
    pub h: usize,
    pub w: usize,
    pub c: usize,
    pub data: Vec<f32>,
}

/// Buffers kept per thread, and the most bytes they may hold.
const POOL_BUFFERS: usize = 48;
const POOL_BYTES: usize = 48 << 20;

thread_local! {
    static POOL: RefCell<Vec<Vec<f32>>> = const { RefCell::new(Vec::new()) };
}

/// A buffer of `n` values with unspecified (initialised) contents: for outputs a kernel
/// overwrites entirely.
pub fn take(n: usize) -> Vec<f32> {
    let reused = POOL.with(|p| {
        let mut p = p.borrow_mut();
        // The smallest buffer that fits.
        let best = p
            .iter()
            .enumerate()
            .filter(|(_, v)| v.capacity() >= n)
            .min_by_key(|(_, v)| v.capacity())
            .map(|(i, _)| i);
        best.map(|i| p.swap_remove(i))
    });
    match reused {
        Some(mut v) => {
            if v.len() >= n {
                v.truncate(n);
            } else {
                v.resize(n, 0.0);
            }
            v
        }
        None => vec![0.0; n],
    }
}

/// Returns a buffer to this thread's pool (dropped instead when the pool is full).
fn give(v: Vec<f32>) {
    if v.capacity() < 1024 {
        return;
    }
    POOL.with(|p| {
        let mut p = p.borrow_mut();
        let bytes: usize = p.iter().map(|b| b.capacity() * 4).sum();
        if p.len() < POOL_BUFFERS && bytes + v.capacity() * 4 <= POOL_BYTES {
            p.push(v);
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
        assert_eq!(b.data.as_ptr(), ptr);
        drop(b);
        let c = Nhwc::zeros(40, 41, 8);
        assert_eq!(c.data.len(), 40 * 41 * 8);
        assert!(c.data.iter().all(|&v| v == 0.0));
    }
}
