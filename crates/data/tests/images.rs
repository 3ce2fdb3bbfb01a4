//! Image values: PNG / JPEG bytes and torch-saved tensors decode to the pixels Python wrote.

// The same fixtures as the formats crate's tests (temporary folders, pickles, LMDBs).
#[path = "../../formats/tests/common/mod.rs"]
mod common;

use common::{data, hex};
use gagavatar_data::images::{decode_image, encode_png, read_image_file};

/// JPEG decoders may differ by an IDCT rounding or two: PIL (libjpeg-turbo) and the `image`
/// crate (zune-jpeg) on a quality-95, 4:4:4 smooth gradient.
const JPEG_DECODER_TOLERANCE: i32 = 2;

#[test]
fn images_decode_to_the_expected_pixels() {
    let exp = common::read_json("images_expected.json");
    for (name, e) in exp.as_object().unwrap() {
        let img = read_image_file(&data(name)).unwrap_or_else(|err| panic!("{err}"));
        assert_eq!(
            img.width() as u64,
            e["width"].as_u64().unwrap(),
            "{name}: width"
        );
        assert_eq!(
            img.height() as u64,
            e["height"].as_u64().unwrap(),
            "{name}: height"
        );
        let want = hex(e["rgb_hex"].as_str().unwrap());
        let tol = if name.ends_with(".jpg") {
            JPEG_DECODER_TOLERANCE
        } else {
            0
        };
        for (i, (g, w)) in img.as_raw().iter().zip(&want).enumerate() {
            let d = (i32::from(*g) - i32::from(*w)).abs();
            assert!(
                d <= tol,
                "{name}: byte {i} (pixel {}, channel {}): expected {w}, actual {g}",
                i / 3,
                i % 3
            );
        }
        assert_eq!(img.as_raw().len(), want.len(), "{name}");
    }
}

#[test]
fn png_round_trip() {
    let img = read_image_file(&data("img_rgb.png")).unwrap();
    let bytes = encode_png(&img).unwrap();
    let back = decode_image(&bytes, std::path::Path::new("mem"), "x").unwrap();
    assert_eq!(back, img);
}

#[test]
fn corrupt_values_are_errors_never_panics() {
    let p = std::path::Path::new("img_lmdb");
    for name in ["img_rgb.png", "img_rgb.jpg", "img_u8_chw.pt"] {
        let bytes = std::fs::read(data(name)).unwrap();
        let step = if name.ends_with(".pt") { 7 } else { 1 };
        for cut in (0..bytes.len()).step_by(step) {
            // JPEG decoders may fill a cut-off tail, and a PNG cut inside its final 12-byte
            // IEND chunk still holds every pixel: a result or an error is fine there, a panic
            // never.
            let r = decode_image(&bytes[..cut], p, "frame_0");
            let must_fail = match name {
                n if n.ends_with(".jpg") => false,
                n if n.ends_with(".png") => cut < bytes.len() - 12,
                _ => true,
            };
            assert!(
                !must_fail || r.is_err(),
                "{name}: a {cut}-byte prefix decoded"
            );
        }
    }
    let e = decode_image(b"GIF89a....", p, "frame_3")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("img_lmdb") && e.contains("frame_3") && e.contains("not an image"),
        "{e}"
    );
    let e = decode_image(&std::fs::read(data("img_rgb.png")).unwrap()[..40], p, "f")
        .unwrap_err()
        .to_string();
    assert!(e.contains("PNG data"), "{e}");
}
