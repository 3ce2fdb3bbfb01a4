//! Head boxes and crops against the reference's float32 PyTorch arithmetic and
//! `F.interpolate(antialias=True)`.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::*;
use gagavatar_train::head_box::{crop_resize, head_box, head_boxes, HeadBox};

/// f32 crop-resize against the f64 reference (values in [0, 1]).
const TOL_CROP: f64 = 1e-5;

#[test]
fn golden_integer_boxes() {
    let io = load("head_box.safetensors");
    let bbox: Vec<Vec<f32>> = get(&io, "bbox").to_vec2().unwrap();
    for n in [512usize, 64] {
        let want: Vec<Vec<i64>> = get(&io, &format!("boxes_{n}")).to_vec2().unwrap();
        let valid: Vec<i64> = get(&io, &format!("valid_{n}")).to_vec1().unwrap();
        let (mut ok, mut err) = (0, 0);
        for (i, b) in bbox.iter().enumerate() {
            let got = head_box([b[0], b[1], b[2], b[3]], n, n);
            if valid[i] == 1 {
                let w = &want[i];
                let expected = HeadBox {
                    x0: w[0] as usize,
                    y0: w[1] as usize,
                    x1: w[2] as usize,
                    y1: w[3] as usize,
                };
                let got = got.unwrap_or_else(|e| panic!("bbox {i} {b:?} at {n}: {e}"));
                assert_eq!(got, expected, "bbox {i} {b:?} at {n}");
                // Inside the image, and square up to the truncation of each corner.
                assert!(got.x1 <= n && got.y1 <= n);
                assert!(got.width().abs_diff(got.height()) <= 1, "bbox {i}: {got:?}");
                ok += 1;
            } else {
                assert!(
                    got.is_err(),
                    "bbox {i} {b:?} at {n}: expected an error, got {got:?}"
                );
                err += 1;
            }
        }
        eprintln!("{n}: {ok} boxes equal, {err} errors as expected");
        assert!(
            ok > 300 && err > 20,
            "the fixture should exercise both outcomes"
        );
    }
}

#[test]
fn golden_crop_resize() {
    let io = load("head_box.safetensors");
    let img = get(&io, "crop_image");
    let boxes = head_boxes(get(&io, "crop_bbox"), 64, 64).unwrap();
    for size in [24usize, 48] {
        let got = crop_resize(img, &boxes, size).unwrap();
        assert_close(
            &format!("crop {size}"),
            &got,
            get(&io, &format!("crop_{size}")),
            TOL_CROP,
        );
    }
}

#[test]
fn borders_shrink_the_box() {
    // A bbox touching the left border: the side shrinks to 2 cx, so the box starts at 0.
    let b = head_box([0.0, 0.2, 0.3, 0.6], 512, 512).unwrap();
    assert_eq!(b.x0, 0);
    assert_eq!(
        b.width(),
        153,
        "side 2 * 0.15 * 512 = 153.6, truncated: {b:?}"
    );
    // The whole image stays the whole image.
    let full = head_box([0.0, 0.0, 1.0, 1.0], 512, 512).unwrap();
    assert_eq!(
        full,
        HeadBox {
            x0: 0,
            y0: 0,
            x1: 512,
            y1: 512
        }
    );
    // A bottom-right corner bbox stays inside.
    let c = head_box([0.7, 0.7, 1.0, 1.0], 512, 512).unwrap();
    assert!(c.x1 <= 512 && c.y1 <= 512 && c.x0 > 0, "{c:?}");
    // A centred bbox grows by 1.1: side 0.55 * 512 = 281.6.
    let m = head_box([0.25, 0.25, 0.75, 0.75], 512, 512).unwrap();
    assert_eq!((m.x0, m.x1), (115, 396), "{m:?}");
}

#[test]
fn tiny_and_degenerate_boxes() {
    // Tiny but non-empty at 512: a one-pixel crop (1.1 * 0.0005 * 512 = 0.28 px around a centre
    // that sits between pixels 256 and 257).
    let t = head_box([0.5, 0.5, 0.5005, 0.5005], 512, 512).unwrap();
    assert_eq!((t.width(), t.height()), (1, 1), "{t:?}");
    // Both corners inside one pixel: nothing left after truncation.
    for n in [64, 512] {
        let e = head_box([0.51, 0.51, 0.5105, 0.5105], n, n)
            .unwrap_err()
            .to_string();
        assert!(e.contains("empty head box"), "{n}: {e}");
    }
    for (bad, what) in [
        ([f32::NAN, 0.1, 0.5, 0.5], "non-finite"),
        ([0.1, 0.1, f32::INFINITY, 0.5], "non-finite"),
        ([0.5, 0.1, 0.4, 0.5], "no area"),
        ([0.1, 0.3, 0.5, 0.3], "no area"),
        ([1.2, 1.2, 1.4, 1.4], "empty head box"),
        ([-0.5, -0.5, -0.1, -0.1], "empty head box"),
    ] {
        let e = head_box(bad, 512, 512).unwrap_err().to_string();
        assert!(e.contains(what), "{bad:?}: expected `{what}`, got `{e}`");
    }
    // Batch form names the sample.
    let t = Tensor::new(
        &[[0.1f32, 0.1, 0.5, 0.5], [0.3, 0.3, f32::NAN, 0.4]],
        &Device::Cpu,
    )
    .unwrap();
    let e = head_boxes(&t, 512, 512).unwrap_err().to_string();
    assert!(e.contains("bbox[1]"), "{e}");
    let wrong = Tensor::zeros((2, 3), DType::F32, &Device::Cpu).unwrap();
    assert!(head_boxes(&wrong, 512, 512).is_err());
}

#[test]
fn crop_errors_and_gradient() {
    let img =
        Var::from_tensor(&Tensor::rand(0f32, 1.0, (2, 3, 32, 32), &Device::Cpu).unwrap()).unwrap();
    let b0 = HeadBox {
        x0: 4,
        y0: 6,
        x1: 20,
        y1: 21,
    };
    let b1 = HeadBox {
        x0: 0,
        y0: 0,
        x1: 32,
        y1: 32,
    };
    // Wrong count, empty box, box past the image, zero output.
    assert!(crop_resize(&img, &[b0], 16).is_err());
    assert!(crop_resize(
        &img,
        &[
            b0,
            HeadBox {
                x0: 5,
                y0: 5,
                x1: 5,
                y1: 9
            }
        ],
        16
    )
    .is_err());
    assert!(crop_resize(
        &img,
        &[
            b0,
            HeadBox {
                x0: 0,
                y0: 0,
                x1: 33,
                y1: 8
            }
        ],
        16
    )
    .is_err());
    assert!(crop_resize(&img, &[b0, b1], 0).is_err());
    // The gradient of a crop reaches exactly the cropped pixels of its own sample.
    let crops = crop_resize(&img, &[b0, b1], 16).unwrap();
    assert_eq!(crops.dims(), &[2, 3, 16, 16]);
    let loss = crops.narrow(0, 0, 1).unwrap().sum_all().unwrap();
    let g = loss.backward().unwrap();
    let gi = g.get(img.as_tensor()).expect("gradient of the image");
    let flat = gi.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for (i, &gv) in flat.iter().enumerate() {
        let (b, c, y, x) = (i / (3 * 1024), (i / 1024) % 3, (i / 32) % 32, i % 32);
        let inside = b == 0 && (4..20).contains(&x) && (6..21).contains(&y);
        assert!(
            inside == (gv != 0.0),
            "sample {b} channel {c} pixel ({y}, {x}): gradient {gv}, inside the box: {inside}"
        );
    }
    // Resampling preserves the mean: each crop's weights sum to out^2 over the crop.
    let total: f32 = flat[..1024].iter().sum();
    assert!(
        (total - 256.0).abs() < 1e-3,
        "gradient mass {total}, expected 16 * 16"
    );
}
