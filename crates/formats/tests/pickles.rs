//! numpy / plain-data pickles against CPython's view of them (fixtures from
//! `tools/reference/tracked_data_fixtures.py`), refused content, and hostile bytes.

mod common;

use common::{data, first_difference};
use gagavatar_formats::numpy::ArrayData;
use gagavatar_formats::pickle::{parse_pickle, read_pickle, DictKey, PyValue};
use serde_json::{json, Value as Json};

/// The canonical JSON of `tracked_data_fixtures.py::canon`.
fn canon(v: &PyValue) -> Json {
    match v {
        PyValue::None => Json::Null,
        PyValue::Bool(b) => json!(b),
        PyValue::Int(i) => json!({ "int": i.to_string() }),
        PyValue::Float(f) => json!({ "float": format!("{:016x}", f.to_bits()) }),
        PyValue::Str(s) => json!(s),
        PyValue::Bytes(b) => {
            json!({ "bytes": b.iter().map(|x| format!("{x:02x}")).collect::<String>() })
        }
        PyValue::List(items) => json!({ "list": items.iter().map(canon).collect::<Vec<_>>() }),
        PyValue::Dict(entries) => json!({
            "dict": entries
                .iter()
                .map(|(k, v)| {
                    let key = match k {
                        DictKey::Str(s) => json!(s),
                        DictKey::Int(i) => json!({ "int": i.to_string() }),
                    };
                    json!([key, canon(v)])
                })
                .collect::<Vec<_>>()
        }),
        PyValue::Array(a) => {
            let dtype = match &a.data {
                ArrayData::Bool(_) => "bool",
                ArrayData::U8(_) => "u8",
                ArrayData::I8(_) => "i8",
                ArrayData::U16(_) => "u16",
                ArrayData::I16(_) => "i16",
                ArrayData::U32(_) => "u32",
                ArrayData::I32(_) => "i32",
                ArrayData::U64(_) => "u64",
                ArrayData::I64(_) => "i64",
                ArrayData::F16(_) => "f16",
                ArrayData::F32(_) => "f32",
                ArrayData::F64(_) => "f64",
            };
            let hex: String = a.to_le_bytes().iter().map(|x| format!("{x:02x}")).collect();
            json!({ "array": dtype, "shape": a.shape, "hex": hex })
        }
    }
}

#[test]
fn numpy_and_plain_data_read_like_cpython() {
    let want = common::read_json("numpy_misc_expected.json");
    for name in [
        "numpy_misc_p2.pkl",
        "numpy_misc_p4.pkl",
        "numpy_misc_p5.pkl",
        "numpy_misc_p2_numpy1.pkl",
    ] {
        let v = read_pickle(&data(name)).unwrap_or_else(|e| panic!("{e}"));
        if let Some(d) = first_difference(&want, &canon(&v), name) {
            panic!("{d}");
        }
    }
    // Spot checks that the canonical form does not hide: byte order, Fortran order, 0-d.
    let v = read_pickle(&data("numpy_misc_p4.pkl")).unwrap();
    let PyValue::Array(be) = v.get("f64_be").unwrap() else {
        panic!()
    };
    assert_eq!(be.to_f64(), [1.5, -2.25, 1e300, std::f64::consts::PI]);
    let PyValue::Array(f) = v.get("fortran").unwrap() else {
        panic!()
    };
    assert_eq!(f.shape, [3, 4]);
    assert_eq!(f.to_f64(), (0..12).map(f64::from).collect::<Vec<_>>());
    let PyValue::Array(z) = v.get("zero_d").unwrap() else {
        panic!()
    };
    assert!(z.shape.is_empty());
    assert_eq!(z.to_f64(), [3.5]);
    assert_eq!(v.get("np_f32"), Some(&PyValue::Float(f64::from(0.1f32))));
}

#[test]
fn refused_content_is_named() {
    let cases = [
        ("evil_os_system.pkl", "`posix.system` is not allowed"),
        (
            "torch_tensor.pkl",
            "`torch._utils._rebuild_tensor_v2` is a torch object",
        ),
        ("custom_class.pkl", "`__main__.Custom` is not allowed"),
        (
            "numpy_complex.pkl",
            "numpy dtype `c8` (complex numbers) is not supported",
        ),
        ("numpy_structured.pkl", "structured"),
    ];
    for (name, needle) in cases {
        let e = read_pickle(&data(name)).expect_err(name).to_string();
        assert!(e.contains(needle), "{name}: {e}");
        assert!(e.contains(name), "{name}: the message names the file: {e}");
        assert!(!e.contains('\n'), "{name}: one line: {e}");
    }
    // Where in the tree: the evil object sits under "frame_0".
    let e = read_pickle(&data("evil_os_system.pkl"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("at root[\"frame_0\"]"), "{e}");
}

/// A simple xorshift for reproducible corruptions.
fn xorshift(state: &mut u64) -> u64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    *state
}

#[test]
fn truncated_and_corrupted_pickles_never_panic() {
    for name in [
        "numpy_misc_p4.pkl",
        "numpy_misc_p2.pkl",
        "numpy_misc_p5.pkl",
    ] {
        let bytes = std::fs::read(data(name)).unwrap();
        for cut in 0..bytes.len() {
            assert!(
                parse_pickle(&bytes[..cut]).is_err(),
                "{name}: {cut}-byte prefix parsed"
            );
        }
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut refused = 0;
        for _ in 0..3000 {
            let mut bad = bytes.clone();
            let r = xorshift(&mut state);
            let pos = (r % bytes.len() as u64) as usize;
            bad[pos] = (r >> 40) as u8;
            refused += usize::from(parse_pickle(&bad).is_err());
        }
        assert!(refused > 0, "{name}: no corruption was noticed");
    }
    // An array whose declared shape disagrees with its bytes.
    let good = std::fs::read(data("numpy_misc_p2.pkl")).unwrap();
    assert!(parse_pickle(&good).is_ok());
}

#[test]
fn data_length_must_match_the_shape() {
    use gagavatar_formats::numpy::NdArray;
    use gagavatar_formats::pickle::to_pickle;
    let v = PyValue::Array(NdArray {
        shape: vec![2, 2],
        data: ArrayData::F32(vec![1.0, 2.0, 3.0, 4.0]),
    });
    let mut bytes = to_pickle(&v).unwrap();
    // The shape tuple is `K\x02 K\x02 \x86`: claim 2x3 instead.
    let at = bytes
        .windows(5)
        .position(|w| w == b"K\x02K\x02\x86")
        .unwrap();
    bytes[at + 3] = 3;
    let e = parse_pickle(&bytes).unwrap_err();
    assert!(e.contains("16 bytes, expected 24"), "{e}");
}
