//! Writes the seed corpus `fuzz/corpus/<target>/`: small real files, either copied from the
//! repository's fixtures (written by Python, torch, numpy, liblmdb) or written by our own
//! writers (mp4, LMDB, torch zip, safetensors, PLY, pickles) and the `image` crate's encoders.
//!
//! Regenerate (from the repository root):  cargo run -p gagavatar-fuzz --example make_seeds

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use gagavatar_formats::numpy::{ArrayData, NdArray};
use gagavatar_formats::pickle::{to_pickle, DictKey, PyValue};
use gagavatar_formats::safetensors::{to_safetensors_bytes, TensorOut};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn out(target: &str, name: &str, bytes: &[u8]) {
    let dir = root().join("fuzz/corpus").join(target);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join(name), bytes).unwrap();
}

fn copy(target: &str, name: &str, from: &str) {
    let bytes = std::fs::read(root().join(from)).unwrap_or_else(|e| panic!("{from}: {e}"));
    out(target, name, &bytes);
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("gagavatar-make-seeds-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn pickles() {
    for p in 0..6 {
        copy(
            "pickle",
            &format!("plain_p{p}.pkl"),
            &format!("crates/formats/tests/golden/pickle_plain_p{p}.pkl"),
        );
    }
    // The pickle inside a torch checkpoint (persistent ids, rebuild calls, config objects).
    let pt = std::fs::read(root().join("crates/formats/tests/golden/pickle_p2.pt")).unwrap();
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(pt)).unwrap();
    let name = zip
        .file_names()
        .map(|n| n.unwrap().into_owned())
        .find(|n| n.ends_with("data.pkl"))
        .unwrap();
    let mut data = Vec::new();
    std::io::Read::read_to_end(&mut zip.by_name(&name).unwrap(), &mut data).unwrap();
    out("pickle", "torch_data_p2.pkl", &data);
    copy(
        "pickle",
        "evil_os_system.pkl",
        "crates/formats/tests/data/evil_os_system.pkl",
    );

    for n in [
        "numpy_misc_p2.pkl",
        "numpy_misc_p4.pkl",
        "numpy_misc_p5.pkl",
        "numpy_complex.pkl",
    ] {
        copy("numpy", n, &format!("crates/formats/tests/data/{n}"));
    }
    copy(
        "numpy",
        "records_p2.pkl",
        "crates/data/tests/data/records_p2.pkl",
    );
    // An optim.pkl of two frames as our writer writes it.
    let arr = |shape: Vec<usize>, v: Vec<f32>| {
        PyValue::Array(NdArray {
            shape,
            data: ArrayData::F32(v),
        })
    };
    let frame = |k: f32| {
        PyValue::Dict(vec![
            (
                DictKey::Str("shapecode".into()),
                arr(vec![4], vec![k, 0.1, -0.2, 0.0]),
            ),
            (DictKey::Str("expcode".into()), arr(vec![2], vec![0.3, k])),
            (DictKey::Str("posecode".into()), arr(vec![6], vec![0.0; 6])),
            (DictKey::Str("eyecode".into()), arr(vec![6], vec![0.0; 6])),
            (
                DictKey::Str("transform_matrix".into()),
                arr(
                    vec![3, 4],
                    vec![1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 10.],
                ),
            ),
            (
                DictKey::Str("bbox".into()),
                arr(vec![4], vec![0.1, 0.1, 0.9, 0.9]),
            ),
        ])
    };
    let v = PyValue::Dict(vec![
        (DictKey::Str("video_0".into()), frame(0.5)),
        (DictKey::Str("video_1".into()), frame(-0.5)),
    ]);
    out("numpy", "records_ours.pkl", &to_pickle(&v).unwrap());
}

fn torch_zips() {
    copy(
        "torch_zip",
        "pickle_p1.pt",
        "crates/formats/tests/golden/pickle_p1.pt",
    );
    copy(
        "torch_zip",
        "pickle_p4.pt",
        "crates/formats/tests/golden/pickle_p4.pt",
    );
    copy(
        "torch_zip",
        "img_u8_chw.pt",
        "crates/data/tests/data/img_u8_chw.pt",
    );
    let path = tmp("w.pt");
    let shapes: [(&str, &[usize]); 2] = [("enc.w", &[2, 3]), ("enc.b", &[3])];
    let cfg = PyValue::Dict(vec![(
        DictKey::Str("name".into()),
        PyValue::Str("tiny".into()),
    )]);
    gagavatar_formats::torch_zip::write_torch_zip(&path, &shapes, Some(&cfg), |i| {
        Ok((0..[6, 3][i]).map(|x| x as f32 * 0.25).collect())
    })
    .unwrap();
    out("torch_zip", "ours.pt", &std::fs::read(&path).unwrap());
}

fn safetensors() {
    let md = BTreeMap::from([("format".to_string(), "pt".to_string())]);
    let bytes = to_safetensors_bytes(
        &[
            TensorOut::f32("means", vec![2, 3], vec![0.0, 0.1, 0.2, 0.3, 0.4, 0.5]),
            TensorOut::i64("flame_model.f", vec![1, 3], vec![0, 1, 2]),
        ],
        &md,
    )
    .unwrap();
    out("safetensors", "small.safetensors", &bytes);
    copy(
        "safetensors",
        "pickle_expected.safetensors",
        "crates/formats/tests/golden/pickle_expected.safetensors",
    );
}

fn lmdbs() {
    copy(
        "lmdb",
        "python_small.mdb",
        "crates/formats/tests/data/lmdb_small/data.mdb",
    );
    let dir = tmp("env");
    let mut entries: Vec<(Vec<u8>, Vec<u8>)> = (0..12)
        .map(|i| (format!("frame_{i}").into_bytes(), vec![i as u8; 10 + i * 7]))
        .collect();
    // One value on overflow pages.
    entries.push((b"big".to_vec(), (0..5000).map(|i| i as u8).collect()));
    gagavatar_formats::lmdb::write_lmdb(&dir, entries).unwrap();
    out(
        "lmdb",
        "ours.mdb",
        &std::fs::read(dir.join("data.mdb")).unwrap(),
    );
}

fn mp4() {
    use gagavatar_video::{VideoOptions, VideoWriter};
    let path = tmp("v.mp4");
    let (w, h) = (16, 16);
    let mut v = VideoWriter::create(
        &path,
        w,
        h,
        VideoOptions {
            fps: 25.0,
            watermark: false,
        },
    )
    .unwrap();
    for f in 0..3u8 {
        let frame: Vec<u8> = (0..w * h * 3)
            .map(|i| (i as u8).wrapping_mul(f + 1))
            .collect();
        v.push_rgb(&frame).unwrap();
    }
    v.finish().unwrap();
    out("mp4", "ours_16x16_3f.mp4", &std::fs::read(&path).unwrap());
}

fn plys() {
    let names = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0",
        "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "feat_0", "feat_1",
    ];
    let values: Vec<f32> = (0..names.len() * 3)
        .map(|i| (i as f32 * 0.37).sin())
        .collect();
    let bytes = gagavatar_formats::ply::ply_bytes(&["gagavatar"], &names, &values).unwrap();
    out("ply", "ours_3dgs.ply", &bytes);
    out(
        "ply",
        "ascii.ply",
        b"ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 2\nproperty float x\n\
property uchar red\nproperty double y\nelement face 1\nproperty list uchar int vertex_indices\n\
end_header\n0.5 255 -1e3\n1 0 2\n3 0 1 1\n",
    );
}

fn records() {
    copy(
        "records_json",
        "demo_source.json",
        "assets/demo/source.json",
    );
    out(
        "records_json",
        "nested.json",
        br#"{"shapecode": [[0.1, 0.2]], "expcode": [1], "posecode": [0,0,0,0.1,0,0],
"eyecode": [], "bbox": [0.1, 0.2, 0.8, 0.9],
"transform_matrix": [[[1,0,0,0],[0,1,0,0],[0,0,1,10]]]}"#,
    );
    out(
        "records_json",
        "records.json",
        br#"{"v_0": {"shapecode": [0.1], "expcode": [0.2], "posecode": [0,0,0,0,0,0],
"eyecode": [0,0,0,0,0,0], "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,10]]},
"v_1": {"shapecode": [], "expcode": [], "posecode": [], "eyecode": []}}"#,
    );
    let text = std::fs::read_to_string(root().join("assets/demo/driver.json")).unwrap();
    let v: serde_json_lite::Value = serde_json_lite::parse(&text);
    out(
        "driving_json",
        "demo_driver_2f.json",
        v.first_frames(2).as_bytes(),
    );
    out(
        "driving_json",
        "with_images.json",
        br#"{"fps": 30, "frames": [
{"name": "a", "image": "a.png", "shapecode": [], "expcode": [0.5], "posecode": [0,0,0,0.2,0,0],
 "eyecode": [], "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,10]]},
{"name": "b", "image": "b.png", "shapecode": [], "expcode": [], "posecode": [], "eyecode": [],
 "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,10]]}]}"#,
    );
}

/// Just enough JSON handling to cut the demo driver down to a few frames without a JSON
/// dependency in this example: the file is `{"fps": F, "frames": [ {...}, {...}, ... ]}`.
mod serde_json_lite {
    pub struct Value(String);

    pub fn parse(text: &str) -> Value {
        Value(text.to_string())
    }

    impl Value {
        pub fn first_frames(&self, n: usize) -> String {
            let s = &self.0;
            let start = s.find('[').expect("frames list");
            let mut depth = 0;
            let mut count = 0;
            for (i, c) in s[start..].char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => {
                        depth -= 1;
                        if depth == 0 {
                            count += 1;
                            if count == n {
                                return format!("{}]}}\n", &s[..start + i + 1]);
                            }
                        }
                    }
                    _ => {}
                }
            }
            s.clone()
        }
    }
}

fn configs() {
    copy("toml_config", "tiny.toml", "crates/train/configs/tiny.toml");
    copy(
        "toml_config",
        "release.toml",
        "crates/train/configs/release.toml",
    );
    copy("toml_config", "demo.toml", "assets/demo/train_config.toml");
}

/// A JPEG with an EXIF APP1 segment holding `orientation`, inserted after SOI.
fn with_exif_orientation(jpeg: &[u8], orientation: u16) -> Vec<u8> {
    let mut tiff = Vec::new();
    tiff.extend(b"II*\0");
    tiff.extend(8u32.to_le_bytes());
    tiff.extend(1u16.to_le_bytes()); // one entry
    tiff.extend(0x0112u16.to_le_bytes()); // Orientation
    tiff.extend(3u16.to_le_bytes()); // SHORT
    tiff.extend(1u32.to_le_bytes());
    tiff.extend(orientation.to_le_bytes());
    tiff.extend([0, 0]);
    tiff.extend(0u32.to_le_bytes()); // no next IFD
    let mut app1 = b"Exif\0\0".to_vec();
    app1.extend(tiff);
    let mut out = jpeg[..2].to_vec();
    out.extend([0xff, 0xe1]);
    out.extend(((app1.len() + 2) as u16).to_be_bytes());
    out.extend(app1);
    out.extend(&jpeg[2..]);
    out
}

fn images() {
    let (w, h) = (24u32, 16u32);
    let rgb = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([(x * 10) as u8, (y * 15) as u8, ((x + y) * 5) as u8])
    });
    let enc = |img: &image::DynamicImage, f: image::ImageFormat| {
        let mut c = std::io::Cursor::new(Vec::new());
        img.write_to(&mut c, f).unwrap();
        c.into_inner()
    };
    let dynimg = image::DynamicImage::ImageRgb8(rgb.clone());
    let png = enc(&dynimg, image::ImageFormat::Png);
    out("image", "rgb.png", &png);
    // PNG data named .jpg, as phones and chat apps produce.
    out("image", "png_named.jpg", &png);
    let jpeg = enc(&dynimg, image::ImageFormat::Jpeg);
    out("image", "rgb.jpg", &jpeg);
    out(
        "image",
        "exif_rotate90.jpg",
        &with_exif_orientation(&jpeg, 6),
    );
    out("image", "rgb.bmp", &enc(&dynimg, image::ImageFormat::Bmp));
    let rgba = image::DynamicImage::ImageRgba8(image::RgbaImage::from_fn(w, h, |x, y| {
        image::Rgba([x as u8 * 9, y as u8 * 9, 200, (x * y) as u8])
    }));
    out("image", "rgba.png", &enc(&rgba, image::ImageFormat::Png));
    out(
        "image",
        "rgba_lossless.webp",
        &enc(&rgba, image::ImageFormat::WebP),
    );
    let grey = image::DynamicImage::ImageLuma16(image::ImageBuffer::from_fn(w, h, |x, y| {
        image::Luma([(x * 2000 + y * 100) as u16])
    }));
    out("image", "grey16.png", &enc(&grey, image::ImageFormat::Png));
    copy("image", "img_rgb.jpg", "crates/data/tests/data/img_rgb.jpg");
    copy("image", "demo_source.png", "assets/demo/source.png");
}

fn main() {
    pickles();
    torch_zips();
    safetensors();
    lmdbs();
    mp4();
    plys();
    records();
    configs();
    images();
    let _ = std::fs::remove_dir_all(tmp("x").parent().unwrap());
    eprintln!("wrote {}", root().join("fuzz/corpus").display());
}
