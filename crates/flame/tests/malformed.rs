//! Broken assets and records must give typed errors naming the key or field, never a panic.

mod common;

use std::path::{Path, PathBuf};

use candle_core::{DType, Device};
use common::golden_dir;
use gagavatar_flame::asset::{read_tensor_file, write_safetensors, RawData, RawTensor, TensorMap};
use gagavatar_flame::{
    BasisLayout, FlameAsset, FlameConfig, FlameError, FlameModel, LoadOptions, TrackedFrame,
};
use gagavatar_formats::FormatError;

fn tiny_options() -> LoadOptions {
    LoadOptions {
        layout: Some(BasisLayout {
            shape: 6,
            expression: 4,
        }),
    }
}

fn tiny_map() -> TensorMap {
    read_tensor_file(&golden_dir().join("tiny_flame.pt")).unwrap()
}

struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Self {
        let p = std::env::temp_dir().join(format!("gagavatar-flame-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&p).unwrap();
        Self(p)
    }
    fn file(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let p = self.0.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn load_modified(
    dir: &TempDir,
    name: &str,
    edit: impl FnOnce(&mut TensorMap),
) -> Result<FlameAsset, FlameError> {
    let mut m = tiny_map();
    edit(&mut m);
    let path = dir.file(name, &write_safetensors(&m).unwrap());
    FlameAsset::load(&path, &tiny_options())
}

#[test]
fn tiny_pt_and_its_safetensors_copy_load_identically() {
    let dir = TempDir::new("copy");
    let from_pt = FlameAsset::load(&golden_dir().join("tiny_flame.pt"), &tiny_options()).unwrap();
    let from_st = load_modified(&dir, "copy.safetensors", |_| {}).unwrap();
    assert!(from_pt == from_st);
}

#[test]
fn missing_key_is_named() {
    let dir = TempDir::new("missing");
    for key in [
        "flame_model.posedirs",
        "lmk_embeddings.dynamic_lmk_bary_coords",
        "flame_model.f",
        // The 70-point set; the plain `full_lmk_*` pair beside it is not a substitute.
        "lmk_embeddings.full_lmk_faces_idx_with_eye",
        "lmk_embeddings.full_lmk_bary_coords_with_eye",
    ] {
        let err = load_modified(&dir, "m.safetensors", |m| {
            m.remove(key);
        })
        .unwrap_err();
        assert!(
            matches!(&err, FlameError::MissingKey { key: k } if k == key),
            "{err}"
        );
        assert!(err.to_string().contains(key));
    }
}

#[test]
fn wrong_shape_is_named() {
    let dir = TempDir::new("shape");
    let err = load_modified(&dir, "s.safetensors", |m| {
        m.insert(
            "flame_model.weights".into(),
            RawTensor::float(vec![40, 4], vec![0.25; 160]),
        );
    })
    .unwrap_err();
    assert!(
        matches!(&err, FlameError::Shape { key, .. } if key == "flame_model.weights"),
        "{err}"
    );
    let err = load_modified(&dir, "s2.safetensors", |m| {
        m.insert(
            "lmk_embeddings.dynamic_lmk_faces_idx".into(),
            RawTensor::int(vec![78, 3], vec![0; 234]),
        );
    })
    .unwrap_err();
    assert!(err.to_string().contains("dynamic_lmk_faces_idx"), "{err}");
}

#[test]
fn wrong_dtype_is_named() {
    let dir = TempDir::new("dtype");
    let err = load_modified(&dir, "d.safetensors", |m| {
        let f = m.get_mut("flame_model.f").unwrap();
        let RawData::Int(v) = &f.data else { panic!() };
        f.data = RawData::Float(v.iter().map(|&x| x as f32).collect());
    })
    .unwrap_err();
    assert!(
        matches!(&err, FlameError::DType { key, .. } if key == "flame_model.f"),
        "{err}"
    );
    let err = load_modified(&dir, "d2.safetensors", |m| {
        m.insert(
            "flame_model.v_template".into(),
            RawTensor::int(vec![40, 3], vec![0; 120]),
        );
    })
    .unwrap_err();
    assert!(
        matches!(&err, FlameError::DType { key, .. } if key == "flame_model.v_template"),
        "{err}"
    );
}

#[test]
fn bad_values_are_named() {
    let dir = TempDir::new("values");
    let err = load_modified(&dir, "n.safetensors", |m| {
        let t = m.get_mut("flame_model.shapedirs").unwrap();
        if let RawData::Float(v) = &mut t.data {
            v[17] = f32::NAN;
        }
    })
    .unwrap_err();
    assert!(
        matches!(&err, FlameError::Invalid { key, .. } if key == "flame_model.shapedirs"),
        "{err}"
    );
    let err = load_modified(&dir, "i.safetensors", |m| {
        let t = m.get_mut("flame_model.f").unwrap();
        if let RawData::Int(v) = &mut t.data {
            v[5] = 40;
        }
    })
    .unwrap_err();
    assert!(
        matches!(&err, FlameError::Invalid { key, .. } if key == "flame_model.f"),
        "{err}"
    );
    let err = load_modified(&dir, "l.safetensors", |m| {
        let t = m.get_mut("lmk_embeddings.static_lmk_faces_idx").unwrap();
        if let RawData::Int(v) = &mut t.data {
            v[0] = -1;
        }
    })
    .unwrap_err();
    assert!(err.to_string().contains("static_lmk_faces_idx"), "{err}");
    let err = load_modified(&dir, "k.safetensors", |m| {
        m.insert(
            "flame_model.kintree_table".into(),
            RawTensor::int(vec![2, 5], vec![-1, 0, 3, 1, 1, 0, 1, 2, 3, 4]),
        );
    })
    .unwrap_err();
    assert!(
        matches!(&err, FlameError::Invalid { key, .. } if key == "flame_model.kintree_table"),
        "{err}"
    );
}

fn assert_load_fails(path: &Path) -> FlameError {
    match FlameAsset::load(path, &tiny_options()) {
        Ok(_) => panic!("{} loaded", path.display()),
        Err(e) => e,
    }
}

#[test]
fn truncated_and_garbage_files_fail_cleanly() {
    let dir = TempDir::new("trunc");
    let pt = std::fs::read(golden_dir().join("tiny_flame.pt")).unwrap();
    for cut in [10, pt.len() / 3, pt.len() / 2, pt.len() - 30] {
        let e = assert_load_fails(&dir.file("t.pt", &pt[..cut]));
        assert!(
            matches!(
                e,
                FlameError::Format(
                    FormatError::TorchZip { .. }
                        | FormatError::Pickle { .. }
                        | FormatError::Safetensors { .. }
                )
            ),
            "cut {cut}: {e}"
        );
    }
    let st = write_safetensors(&tiny_map()).unwrap();
    for cut in [0, 4, 100, st.len() - 1] {
        let e = assert_load_fails(&dir.file("t.safetensors", &st[..cut]));
        assert!(
            matches!(e, FlameError::Format(FormatError::Safetensors { .. })),
            "cut {cut}: {e}"
        );
    }
    let e = assert_load_fails(&dir.file("g.bin", b"this is not a model"));
    assert!(
        matches!(e, FlameError::Format(FormatError::Safetensors { .. })),
        "{e}"
    );
    let e = assert_load_fails(&dir.0.join("does-not-exist.pt"));
    assert_eq!(
        match &e {
            FlameError::Format(f) => f.io_kind(),
            _ => None,
        },
        Some(std::io::ErrorKind::NotFound),
        "{e}"
    );
    // Flipping bytes inside the pickle region must not panic either.
    for pos in (0..pt.len()).step_by(97) {
        let mut bad = pt.clone();
        bad[pos] ^= 0x5a;
        let _ = FlameAsset::load(&dir.file("f.pt", &bad), &tiny_options());
    }
}

#[test]
fn records_are_validated() {
    let asset = FlameAsset::load(&golden_dir().join("tiny_flame.pt"), &tiny_options()).unwrap();
    let config = FlameConfig {
        n_shape: 6,
        n_exp: 4,
        ..FlameConfig::default()
    };
    let model = FlameModel::new(&asset, config, &Device::Cpu, DType::F32).unwrap();
    // Shorter codes are zero-padded.
    let r = TrackedFrame::from_json_str(
        r#"{"shapecode":[0.1],"expcode":[],"posecode":[0,0,0,0.2],"eyecode":[0]}"#,
    )
    .unwrap();
    let p = r.params(&model).unwrap();
    assert_eq!(p.shape.dims(), [1, 6]);
    assert_eq!(
        p.pose.to_vec2::<f32>().unwrap()[0],
        vec![0.0, 0.0, 0.0, 0.2, 0.0, 0.0]
    );
    // Longer codes are refused, naming the field.
    let r = TrackedFrame::from_json_str(
        r#"{"shapecode":[0,0,0,0,0,0,0],"expcode":[],"posecode":[],"eyecode":[]}"#,
    )
    .unwrap();
    let e = r.params(&model).unwrap_err();
    assert!(
        matches!(&e, FlameError::Record { field, .. } if field == "shapecode"),
        "{e}"
    );
    let r = TrackedFrame::from_json_str(
        r#"{"shapecode":[],"expcode":[],"posecode":[0,0,0,0,0,0,0],"eyecode":[]}"#,
    )
    .unwrap();
    assert!(
        matches!(r.params(&model), Err(FlameError::Record { field, .. }) if field == "posecode")
    );
    // NaN / Infinity are not JSON; huge numbers overflow; both are typed record errors.
    for bad in [
        r#"{"shapecode":[NaN],"expcode":[],"posecode":[],"eyecode":[]}"#,
        r#"{"shapecode":[],"expcode":[Infinity],"posecode":[],"eyecode":[]}"#,
        r#"{"shapecode":[],"expcode":[],"posecode":[1e400],"eyecode":[]}"#,
        r#"{"shapecode":[],"expcode":[],"posecode":[],"eyecode":[null]}"#,
        r#"{"shapecode":[],"expcode":[],"posecode":[],"eyecode":[], "transform_matrix": [[1,0,0],[0,1,0],[0,0,1]]}"#,
        r#"{"shapecode":[],"expcode":[],"posecode":[],"eyecode":[], "bbox": [0, 1]}"#,
        r#"[1, 2]"#,
        r#"{"shapecode":[],"expcode":"#,
    ] {
        let e = TrackedFrame::from_json_str(bad).unwrap_err();
        assert!(matches!(e, FlameError::Record { .. }), "{bad}: {e}");
    }
}
