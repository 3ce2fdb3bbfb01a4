//! Huge photos are downscaled while they are decoded: peak memory stays near the output size,
//! not the photo's (a 10000x10000 photo peaked at 1.8 GB when decoded whole). A counting
//! allocator measures the decode alone; the inputs are made before it starts counting, and the
//! tests run one at a time.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use gagavatar_formats::image::{decode_image, DecodeOptions};

struct Counting;
static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator, only counting sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let now = LIVE.fetch_add(l.size(), Ordering::Relaxed) + l.size();
        PEAK.fetch_max(now, Ordering::Relaxed);
        System.alloc(l)
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        LIVE.fetch_sub(l.size(), Ordering::Relaxed);
        System.dealloc(p, l)
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, n: usize) -> *mut u8 {
        if n > l.size() {
            let now = LIVE.fetch_add(n - l.size(), Ordering::Relaxed) + n - l.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        } else {
            LIVE.fetch_sub(l.size() - n, Ordering::Relaxed);
        }
        System.realloc(p, l, n)
    }
}

#[global_allocator]
static A: Counting = Counting;

/// The tests measure one at a time (the counter is process-wide).
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// Held by each test from before it makes its input: the counters are process-wide, so another
/// test's allocations must not fall inside a measurement.
fn lock() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

/// Bytes allocated at the peak of `f` above what was live before it.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let before = LIVE.load(Ordering::Relaxed);
    PEAK.store(before, Ordering::Relaxed);
    let out = f();
    (out, PEAK.load(Ordering::Relaxed) - before)
}

const W: u32 = 6000;
const H: u32 = 4000;
/// The photo as RGB would be 72 MB; decoding it to fit 1024 must stay far below that.
const PEAK_LIMIT: usize = 32 << 20;

fn pixel(x: u32, y: u32) -> [u8; 3] {
    [(x / 24) as u8, (y / 16) as u8, ((x + y) / 40) as u8]
}

/// A `w`x`h` RGB PNG of [`pixel`], encoded row by row (the photo never exists whole here either).
fn big_png_sized(w: u32, h: u32) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_compression(png::Compression::Fastest);
        let mut writer = enc.write_header().unwrap();
        let mut s = writer.stream_writer().unwrap();
        let mut row = vec![0u8; w as usize * 3];
        for y in 0..h {
            for x in 0..w {
                row[x as usize * 3..x as usize * 3 + 3].copy_from_slice(&pixel(x, y));
            }
            std::io::Write::write_all(&mut s, &row).unwrap();
        }
        s.finish().unwrap();
    }
    out
}

fn big_png() -> Vec<u8> {
    big_png_sized(W, H)
}

fn big_jpeg() -> Vec<u8> {
    let img = image::RgbImage::from_fn(W, H, |x, y| image::Rgb(pixel(x, y)));
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90)
        .encode_image(&img)
        .unwrap();
    out
}

/// Call with [`lock`] held.
fn check(name: &str, bytes: &[u8], tolerance: i32) {
    let opts = DecodeOptions {
        min_side: 1,
        fit_within: Some(1024),
    };
    let (d, peak) = peak_of(|| decode_image(bytes, name, &opts).unwrap());
    assert_eq!(d.rgb.dimensions(), (1024, 683), "{name}");
    assert_eq!((d.original_width, d.original_height), (W, H), "{name}");
    assert!(
        peak < PEAK_LIMIT,
        "{name}: decoding allocated {} MB at its peak (limit {} MB; the photo is {} MB as RGB)",
        peak >> 20,
        PEAK_LIMIT >> 20,
        (W * H * 3) >> 20
    );
    // The pixels are the area average of the photo: compare a few with the formula.
    let s = W as f64 / 1024.0;
    for (ox, oy) in [(10u32, 10u32), (500, 300), (1000, 650)] {
        let (x0, y0) = (
            (ox as f64 * s) as u32,
            (oy as f64 * s * 683.0 / 682.7) as u32,
        );
        let want = pixel(x0 + 3, y0 + 3);
        let got = d.rgb.get_pixel(ox, oy).0;
        for c in 0..3 {
            assert!(
                (got[c] as i32 - want[c] as i32).abs() <= tolerance,
                "{name}: ({ox}, {oy})[{c}]: expected {want:?}, actual {got:?}"
            );
        }
    }
    eprintln!("{name}: peak {:.1} MB", peak as f64 / 1e6);
}

/// PNG rows are area-averaged as they are decoded.
#[test]
fn a_huge_png_is_downscaled_row_by_row() {
    // The gradient changes by at most one level across an output pixel's area.
    let _guard = lock();
    check("huge.png", &big_png(), 2);
}

/// A baseline JPEG is decoded at a quarter of its size by the IDCT, then averaged.
#[test]
fn a_huge_jpeg_is_decoded_at_reduced_size() {
    // JPEG quantisation and the reduced IDCT add a few levels.
    let _guard = lock();
    check("huge.jpg", &big_jpeg(), 6);
}

/// The photo from the issue: 10000x10000 (300 MB as RGB, 1.8 GB peak when it was decoded
/// whole) fits 1024 with a peak of a few megabytes.
#[test]
fn a_10000_px_square_png_stays_small() {
    const SIDE: u32 = 10_000;
    let _guard = lock();
    let bytes = big_png_sized(SIDE, SIDE);
    let opts = DecodeOptions {
        min_side: 1,
        fit_within: Some(1024),
    };
    let (d, peak) = peak_of(|| decode_image(&bytes, "square.png", &opts).unwrap());
    assert_eq!(d.rgb.dimensions(), (1024, 1024));
    assert_eq!((d.original_width, d.original_height), (SIDE, SIDE));
    assert!(
        peak < PEAK_LIMIT,
        "decoding allocated {} MB at its peak (limit {} MB; the photo is 300 MB as RGB)",
        peak >> 20,
        PEAK_LIMIT >> 20
    );
    eprintln!("square.png: peak {:.1} MB", peak as f64 / 1e6);
}

/// A PNG whose header promises a large image (within the caps) but whose data stops after a
/// few rows: decoded at full size, the output grows with the rows that arrive, so the refusal
/// costs kilobytes, not the 405 MB the header asks for.
#[test]
fn a_png_header_without_its_data_allocates_little() {
    let (w, h) = (15_000u32, 9_000u32);
    let _guard = lock();
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, w, h);
        enc.set_color(png::ColorType::Rgb);
        let mut wr = enc.write_header().unwrap();
        let mut s = wr.stream_writer().unwrap();
        let row = vec![7u8; w as usize * 3];
        for _ in 0..4 {
            std::io::Write::write_all(&mut s, &row).unwrap();
        }
        // Flushes the rows written so far without finishing the image.
        std::io::Write::flush(&mut s).unwrap();
        std::mem::forget(s);
    }
    let (r, peak) = peak_of(|| decode_image(&bytes, "cut.png", &DecodeOptions::default()));
    let e = r.expect_err("a truncated PNG must be refused").to_string();
    assert!(e.starts_with("cut.png: "), "{e}");
    assert!(
        peak < PEAK_LIMIT,
        "refusing the truncated PNG allocated {} MB (limit {} MB)",
        peak >> 20,
        PEAK_LIMIT >> 20
    );
}
