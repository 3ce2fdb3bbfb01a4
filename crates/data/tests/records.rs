//! Tracked-frame pickles (`optim.pkl`): the release's numpy pickles read exactly, our writer's
//! output read back identically and equal to a byte-level golden (which CPython + numpy read:
//! `tools/reference/writer_goldens_check.py`), and every broken field named.

// The same fixtures as the formats crate's tests (temporary folders, pickles, LMDBs).
#[path = "../../formats/tests/common/mod.rs"]
mod common;
#[path = "../../formats/tests/common/golden.rs"]
mod golden;

use std::collections::BTreeMap;
use std::path::Path;

use common::{data, f32s, TempDir};
use gagavatar_data::records::{
    read_records, records_from_value, records_to_pickle, write_records, EXPRESSION_COMPONENTS,
    EYE_COMPONENTS, POSE_COMPONENTS, SHAPE_COMPONENTS,
};
use gagavatar_data::{DataError, TrackedFrame};
use gagavatar_formats::numpy::{ArrayData, NdArray};
use gagavatar_formats::pickle::{parse_pickle, to_pickle, DictKey, PyValue};

const FIELDS: [&str; 6] = [
    "bbox",
    "shapecode",
    "expcode",
    "posecode",
    "eyecode",
    "transform_matrix",
];

fn field_values(r: &TrackedFrame, field: &str) -> Vec<f64> {
    match field {
        "bbox" => r.bbox.expect("bbox").to_vec(),
        "shapecode" => r.shapecode.clone(),
        "expcode" => r.expcode.clone(),
        "posecode" => r.posecode.clone(),
        "eyecode" => r.eyecode.clone(),
        "transform_matrix" => r
            .transform_matrix
            .expect("tm")
            .iter()
            .flatten()
            .copied()
            .collect(),
        _ => unreachable!(),
    }
}

/// Every value equals the float32 the fixture holds, bit for bit.
fn assert_matches_expected(
    records: &BTreeMap<String, TrackedFrame>,
    expected: &serde_json::Value,
    what: &str,
) {
    let exp = expected.as_object().unwrap();
    assert_eq!(records.len(), exp.len(), "{what}: frame count");
    for (name, fields) in exp {
        let r = records
            .get(name)
            .unwrap_or_else(|| panic!("{what}: frame {name} missing"));
        for field in FIELDS {
            let want = f32s(fields[field]["hex"].as_str().unwrap());
            let got = field_values(r, field);
            assert_eq!(got.len(), want.len(), "{what}: {name}.{field} length");
            for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                assert!(
                    *g == f64::from(*w),
                    "{what}: {name}.{field}[{i}]: expected {w}, actual {g}"
                );
            }
        }
    }
}

#[test]
fn release_pickles_read_exactly() {
    let expected = common::read_json("records_expected.json");
    for name in [
        "records_p2.pkl",
        "records_p4.pkl",
        "records_p2_numpy1.pkl",
        "records_p4_numpy1.pkl",
        "records_shape_1x300.pkl",
    ] {
        let recs = read_records(&data(name)).unwrap_or_else(|e| panic!("{e}"));
        assert_matches_expected(&recs, &expected, name);
    }
}

fn sample_records() -> BTreeMap<String, TrackedFrame> {
    let mut out = BTreeMap::new();
    for (k, name) in ["clip_b_10", "clip_b_2", "clip_a_0"].iter().enumerate() {
        let f = |n: usize, scale: f64| -> Vec<f64> {
            (0..n)
                .map(|i| {
                    (f64::from(f32::from_bits(0x3f80_0000 + (i * 7919 + k) as u32)) - 1.5) * scale
                })
                .collect()
        };
        out.insert(
            name.to_string(),
            TrackedFrame {
                shapecode: f(300, 2.0),
                expcode: f(100, 1.0),
                posecode: f(6, 0.1),
                eyecode: f(6, 0.05),
                transform_matrix: Some([
                    [1.0, 0.0, 0.0, 0.01],
                    [0.0, 1.0, 0.0, -0.02],
                    [0.0, 0.0, 1.0, 9.5 + k as f64],
                ]),
                bbox: Some([0.1, 0.2, 0.8, 0.9]),
            },
        );
    }
    out
}

/// f64 values the writer can hold exactly (float32 values).
fn as_f32_exact(mut r: TrackedFrame) -> TrackedFrame {
    let round = |v: &mut Vec<f64>| v.iter_mut().for_each(|x| *x = f64::from(*x as f32));
    round(&mut r.shapecode);
    round(&mut r.expcode);
    round(&mut r.posecode);
    round(&mut r.eyecode);
    if let Some(m) = r.transform_matrix.as_mut() {
        m.iter_mut()
            .flatten()
            .for_each(|x| *x = f64::from(*x as f32));
    }
    if let Some(b) = r.bbox.as_mut() {
        b.iter_mut().for_each(|x| *x = f64::from(*x as f32));
    }
    r
}

#[test]
fn written_records_read_back_identically() {
    let recs: BTreeMap<String, TrackedFrame> = sample_records()
        .into_iter()
        .map(|(k, v)| (k, as_f32_exact(v)))
        .collect();
    let dir = TempDir::new("records");
    let path = dir.path().join("optim.pkl");
    write_records(&path, &recs).unwrap();
    let back = read_records(&path).unwrap();
    assert_eq!(back, recs);
    // Natural order inside the file: clip_a_0, clip_b_2, clip_b_10.
    let PyValue::Dict(entries) = parse_pickle(&std::fs::read(&path).unwrap()).unwrap() else {
        panic!()
    };
    let keys: Vec<String> = entries.iter().map(|(k, _)| k.to_string()).collect();
    assert_eq!(keys, ["\"clip_a_0\"", "\"clip_b_2\"", "\"clip_b_10\""]);
    // No temp file left behind.
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(leftovers, [std::ffi::OsString::from("optim.pkl")]);

    // For the Python check by hand (see tools/reference/README.md): our pickle and the values
    // it must hold.
    if let Ok(out) = std::env::var("GAGAVATAR_RECORDS_OUT") {
        let out = Path::new(&out);
        std::fs::create_dir_all(out).unwrap();
        std::fs::copy(&path, out.join("optim.pkl")).unwrap();
        let doc = release_json(&recs);
        std::fs::write(
            out.join("expected.json"),
            serde_json::to_string(&doc).unwrap(),
        )
        .unwrap();
    }
}

/// The values a written `optim.pkl` must hold, in the form
/// `tracked_data_fixtures.py --check-records` reads: `{"order": [frame names in file order],
/// "frames": {frame: {field: nested list}}}`, codes zero-padded to the release's lengths and
/// every number rounded to float32 (here, independently of the writer).
fn release_json(recs: &BTreeMap<String, TrackedFrame>) -> serde_json::Value {
    let rounded = |v: &[f64], n: usize| -> Vec<f64> {
        let mut v: Vec<f64> = v.iter().map(|&x| f64::from(x as f32)).collect();
        v.resize(n, 0.0);
        v
    };
    let mut names: Vec<&String> = recs.keys().collect();
    gagavatar_data::sort_frame_names(&mut names);
    let mut frames = serde_json::Map::new();
    for &name in &names {
        let r = &recs[name];
        let tm: Vec<Vec<f64>> = r
            .transform_matrix
            .expect("transform_matrix")
            .iter()
            .map(|row| rounded(row, row.len()))
            .collect();
        frames.insert(
            name.clone(),
            serde_json::json!({
                "bbox": rounded(&r.bbox.expect("bbox"), 4),
                "shapecode": rounded(&r.shapecode, SHAPE_COMPONENTS),
                "expcode": rounded(&r.expcode, EXPRESSION_COMPONENTS),
                "posecode": rounded(&r.posecode, POSE_COMPONENTS),
                "eyecode": rounded(&r.eyecode, EYE_COMPONENTS),
                "transform_matrix": tm,
            }),
        );
    }
    serde_json::json!({ "order": names, "frames": frames })
}

/// The golden `optim.pkl` and its expected values (also read by
/// `tools/reference/writer_goldens_check.py`).
const RECORDS_GOLDEN: &str = "written/optim.pkl";
const RECORDS_GOLDEN_JSON: &str = "written/optim_expected.json";
const RECORDS_BLESS: &str = "GAGAVATAR_BLESS=1 cargo test -p gagavatar-data --test records \
                             written_records_match_golden";

/// The `expcode` length of the golden's second frame (the writer pads it).
const SHORT_EXPCODE: usize = 50;
/// Bits of 2^-7: full-mantissa eye codes are made by adding to them.
const EYE_BASE_BITS: u32 = 0x3c00_0000;

/// Three frames of two videos, given out of the file's natural order: codes of eighths (short
/// in JSON, exact in float32), one short `expcode` the writer pads, and boxes, poses and
/// cameras with values float32 cannot hold (the writer rounds them) or holds only with a full
/// mantissa.
fn golden_records() -> BTreeMap<String, TrackedFrame> {
    let eighths = |n: usize, k: usize| -> Vec<f64> {
        (0..n)
            .map(|i| ((i * (k + 5)) % 33) as f64 / 8.0 - 2.0)
            .collect()
    };
    let mut out = BTreeMap::new();
    for (k, name) in ["spk_a_10", "spk_b_x_0", "spk_a_2"].iter().enumerate() {
        let t = k as f64;
        out.insert(
            name.to_string(),
            TrackedFrame {
                shapecode: eighths(SHAPE_COMPONENTS, 0),
                expcode: eighths(
                    if k == 1 {
                        SHORT_EXPCODE
                    } else {
                        EXPRESSION_COMPONENTS
                    },
                    k + 1,
                ),
                posecode: vec![0.1 * t, -0.2, 0.3, 0.01, -0.02 * t, 0.0],
                eyecode: (0..6)
                    .map(|i| f64::from(f32::from_bits(EYE_BASE_BITS + i * 7919 + k as u32)))
                    .collect(),
                transform_matrix: Some([
                    [0.9, -0.1, 0.0, 0.01 * t],
                    [0.1, 0.9, 0.0, -0.02],
                    [0.0, 0.0, 1.0, 9.5 + t],
                ]),
                bbox: Some([12.5 + t, 20.25, 480.1, 501.7]),
            },
        );
    }
    out
}

#[test]
fn written_records_match_golden() {
    let recs = golden_records();
    let dir = TempDir::new("records-golden");
    let path = dir.path().join("optim.pkl");
    write_records(&path, &recs).unwrap();
    let expected = release_json(&recs);
    // Our reader sees the padded, rounded values the expected JSON lists.
    let back = read_records(&path).unwrap();
    for (name, fields) in expected["frames"].as_object().unwrap() {
        for field in FIELDS {
            let want: Vec<f64> = match &fields[field] {
                serde_json::Value::Array(rows) if rows[0].is_array() => rows
                    .iter()
                    .flat_map(|r| r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
                    .collect(),
                v => v
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|x| x.as_f64().unwrap())
                    .collect(),
            };
            assert_eq!(field_values(&back[name], field), want, "{name}.{field}");
        }
    }
    golden::check_bytes(
        &data(RECORDS_GOLDEN),
        &std::fs::read(&path).unwrap(),
        RECORDS_BLESS,
    );
    golden::check_json(&data(RECORDS_GOLDEN_JSON), &expected, RECORDS_BLESS);
}

#[test]
fn writer_pads_short_codes_and_refuses_what_the_release_cannot_load() {
    let mut recs = sample_records();
    let dir = TempDir::new("records-bad");
    let path = dir.path().join("optim.pkl");
    recs.get_mut("clip_a_0").unwrap().expcode.truncate(50);
    write_records(&path, &recs).unwrap();
    let back = read_records(&path).unwrap();
    assert_eq!(back["clip_a_0"].expcode.len(), 100);
    assert!(back["clip_a_0"].expcode[50..].iter().all(|&x| x == 0.0));

    type Edit = Box<dyn Fn(&mut TrackedFrame)>;
    let cases: Vec<(Edit, &str, &str)> = vec![
        (
            Box::new(|r| r.shapecode.push(0.0)),
            "shapecode",
            "has 301 values",
        ),
        (Box::new(|r| r.bbox = None), "bbox", "is missing"),
        (
            Box::new(|r| r.transform_matrix = None),
            "transform_matrix",
            "is missing",
        ),
        (
            Box::new(|r| r.eyecode[2] = f64::NAN),
            "eyecode",
            "element 2",
        ),
        (
            Box::new(|r| r.posecode[1] = 1e300),
            "posecode",
            "not a finite float32",
        ),
    ];
    for (edit, field, needle) in cases {
        let mut recs = sample_records();
        edit(recs.get_mut("clip_b_2").unwrap());
        let e = records_to_pickle(&path, &recs).unwrap_err();
        match &e {
            DataError::Record {
                frame,
                field: f,
                reason,
                ..
            } => {
                assert_eq!(frame, "`clip_b_2`", "{e}");
                assert_eq!(f, field, "{e}");
                assert!(reason.contains(needle), "{e}");
            }
            other => panic!("{other}"),
        }
    }
}

fn arr(shape: Vec<usize>, n: usize) -> PyValue {
    PyValue::Array(NdArray {
        shape,
        data: ArrayData::F32((0..n).map(|i| i as f32 * 0.01).collect()),
    })
}

fn frame_value(edit: impl FnOnce(&mut Vec<(DictKey, PyValue)>)) -> PyValue {
    let mut fields = vec![
        (DictKey::Str("bbox".into()), arr(vec![4], 4)),
        (DictKey::Str("shapecode".into()), arr(vec![300], 300)),
        (DictKey::Str("expcode".into()), arr(vec![100], 100)),
        (DictKey::Str("posecode".into()), arr(vec![6], 6)),
        (DictKey::Str("eyecode".into()), arr(vec![6], 6)),
        (DictKey::Str("transform_matrix".into()), arr(vec![3, 4], 12)),
        (DictKey::Str("extra".into()), PyValue::Str("ignored".into())),
    ];
    edit(&mut fields);
    PyValue::Dict(vec![(DictKey::Str("vid_7".into()), PyValue::Dict(fields))])
}

fn set(fields: &mut [(DictKey, PyValue)], name: &str, v: PyValue) {
    let slot = fields
        .iter_mut()
        .find(|(k, _)| *k == DictKey::Str(name.into()))
        .unwrap();
    slot.1 = v;
}

#[test]
fn broken_fields_are_named() {
    let p = Path::new("optim.pkl");
    // The valid frame, through real pickle bytes.
    let good = parse_pickle(&to_pickle(&frame_value(|_| {})).unwrap()).unwrap();
    let recs = records_from_value(p, &good).unwrap();
    assert_eq!(recs["vid_7"].expcode[3], f64::from(0.03f32));
    assert!(recs["vid_7"].bbox.is_some());
    // A missing bbox is allowed when reading (driving needs none).
    let no_box = frame_value(|f| f.retain(|(k, _)| *k != DictKey::Str("bbox".into())));
    assert!(records_from_value(p, &no_box).unwrap()["vid_7"]
        .bbox
        .is_none());

    type Edit = Box<dyn Fn(&mut Vec<(DictKey, PyValue)>)>;
    let cases: Vec<(Edit, &str, &str)> = vec![
        (
            Box::new(|f| f.retain(|(k, _)| *k != DictKey::Str("expcode".into()))),
            "expcode",
            "is missing",
        ),
        (
            Box::new(|f| set(f, "shapecode", arr(vec![299], 299))),
            "shapecode",
            "has shape [299], expected [300] or [1, 300]",
        ),
        (
            Box::new(|f| set(f, "transform_matrix", arr(vec![4, 3], 12))),
            "transform_matrix",
            "has shape [4, 3]",
        ),
        (
            Box::new(|f| set(f, "bbox", arr(vec![2, 2], 4))),
            "bbox",
            "has shape [2, 2]",
        ),
        (
            Box::new(|f| set(f, "posecode", PyValue::Str("x".into()))),
            "posecode",
            "is a str",
        ),
        (
            Box::new(|f| {
                set(
                    f,
                    "eyecode",
                    PyValue::Array(NdArray {
                        shape: vec![6],
                        data: ArrayData::F32(vec![0.0, 0.0, f32::INFINITY, 0.0, 0.0, 0.0]),
                    }),
                )
            }),
            "eyecode",
            "element 2 is not finite",
        ),
        (
            Box::new(|f| {
                set(
                    f,
                    "eyecode",
                    PyValue::Array(NdArray {
                        shape: vec![6],
                        data: ArrayData::Bool(vec![true; 6]),
                    }),
                )
            }),
            "eyecode",
            "bool array",
        ),
    ];
    for (edit, field, needle) in cases {
        let v = frame_value(edit);
        // Through pickle bytes, so the file path reaches the message.
        let dir = TempDir::new("broken");
        let path = dir.path().join("optim.pkl");
        std::fs::write(&path, to_pickle(&v).unwrap()).unwrap();
        let e = read_records(&path).unwrap_err();
        let text = e.to_string();
        match &e {
            DataError::Record {
                frame,
                field: f,
                reason,
                ..
            } => {
                assert_eq!(frame, "`vid_7`", "{text}");
                assert_eq!(f, field, "{text}");
                assert!(reason.contains(needle), "{text}");
            }
            other => panic!("expected a record error for {field}: {other}"),
        }
        assert!(
            text.contains("optim.pkl") && text.contains("vid_7") && text.contains(field),
            "{text}"
        );
    }
    // Wrong top-level shapes.
    let e = records_from_value(p, &PyValue::List(vec![]))
        .unwrap_err()
        .to_string();
    assert!(e.contains("top level is a list"), "{e}");
    let e = records_from_value(p, &PyValue::Dict(vec![(DictKey::Int(3), PyValue::None)]))
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame key 3 is not a string"), "{e}");
    let e = records_from_value(
        p,
        &PyValue::Dict(vec![(DictKey::Str("f_1".into()), PyValue::Int(1))]),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("frame `f_1` is an int"), "{e}");
}
