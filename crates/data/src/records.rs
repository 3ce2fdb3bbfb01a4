//! Tracked-frame records in the release's pickles (`optim.pkl`, `smoothed.pkl`; spec section
//! 10): a dict keyed by frame name, each frame a dict of float32 numpy arrays.
//!
//! Reading requires `shapecode [300]`, `expcode [100]`, `posecode [6]`, `eyecode [6]` and
//! `transform_matrix [3,4]`, each optionally with a leading batch dimension of 1 (`[1,300]`,
//! `[1,3,4]`), as float (or integer) numpy arrays or nested lists of numbers, all finite.
//! `bbox [4]` is read when present and may be missing (driving needs no box; the training
//! dataset reader requires it). Other keys are ignored.
//!
//! Writing produces exactly those six float32 arrays per frame with flat codes, `[3,4]` and
//! `[4]` shapes, frames in natural name order; shorter codes are zero-padded (the meaning
//! `TrackedFrame` gives them), longer ones and missing `bbox` / `transform_matrix` are errors,
//! since the release's loader could not use them.

use std::collections::BTreeMap;
use std::path::Path;

use gagavatar_flame::{FlameError, TrackedFrame};

use crate::error::{DataError, Result};
use crate::names::frame_name_cmp;
use gagavatar_formats::atomic::write_atomic;
use gagavatar_formats::numpy::{ArrayData, NdArray};
use gagavatar_formats::pickle::{read_pickle, to_pickle, DictKey, PyValue};

/// Component counts of the release's codes.
pub const SHAPE_COMPONENTS: usize = 300;
pub const EXPRESSION_COMPONENTS: usize = 100;
pub const POSE_COMPONENTS: usize = 6;
pub const EYE_COMPONENTS: usize = 6;

/// Reads `optim.pkl` / `smoothed.pkl`: frame name -> record.
pub fn read_records(path: &Path) -> Result<BTreeMap<String, TrackedFrame>> {
    let value = read_pickle(path)?;
    records_from_value(path, &value)
}

/// The records of an already-parsed pickle (`path` only names the source in errors).
pub fn records_from_value(path: &Path, value: &PyValue) -> Result<BTreeMap<String, TrackedFrame>> {
    let PyValue::Dict(frames) = value else {
        return Err(DataError::Pickle {
            path: path.to_owned(),
            reason: format!(
                "the top level is {}, expected a dict of frames",
                value.kind()
            ),
        });
    };
    let mut out = BTreeMap::new();
    for (key, frame) in frames {
        let DictKey::Str(name) = key else {
            return Err(DataError::Pickle {
                path: path.to_owned(),
                reason: format!("frame key {key} is not a string"),
            });
        };
        out.insert(name.clone(), frame_from_value(path, name, frame)?);
    }
    Ok(out)
}

/// One frame's record from its dict of arrays.
pub fn frame_from_value(path: &Path, name: &str, value: &PyValue) -> Result<TrackedFrame> {
    if !matches!(value, PyValue::Dict(_)) {
        return Err(DataError::Pickle {
            path: path.to_owned(),
            reason: format!(
                "frame `{name}` is {}, expected a dict of arrays",
                value.kind()
            ),
        });
    }
    let err = |field: &str, reason: String| DataError::Record {
        path: path.to_owned(),
        frame: format!("`{name}`"),
        field: field.to_owned(),
        reason,
    };
    let vector = |field: &str, n: usize| -> Result<Vec<f64>> {
        let v = value
            .get(field)
            .ok_or_else(|| err(field, "is missing".into()))?;
        numbers(v, &[vec![n], vec![1, n]]).map_err(|r| err(field, r))
    };
    let transform = match value.get("transform_matrix") {
        None => return Err(err("transform_matrix", "is missing".into())),
        Some(v) => {
            let m =
                numbers(v, &[vec![3, 4], vec![1, 3, 4]]).map_err(|r| err("transform_matrix", r))?;
            let mut out = [[0.0; 4]; 3];
            for (r, row) in out.iter_mut().enumerate() {
                row.copy_from_slice(&m[r * 4..r * 4 + 4]);
            }
            out
        }
    };
    let bbox = match value.get("bbox") {
        None | Some(PyValue::None) => None,
        Some(v) => {
            let b = numbers(v, &[vec![4], vec![1, 4]]).map_err(|r| err("bbox", r))?;
            Some([b[0], b[1], b[2], b[3]])
        }
    };
    let record = TrackedFrame {
        shapecode: vector("shapecode", SHAPE_COMPONENTS)?,
        expcode: vector("expcode", EXPRESSION_COMPONENTS)?,
        posecode: vector("posecode", POSE_COMPONENTS)?,
        eyecode: vector("eyecode", EYE_COMPONENTS)?,
        transform_matrix: Some(transform),
        bbox,
    };
    // Finite, and within what FLAME codes and cameras are.
    record.validate().map_err(|e| match e {
        FlameError::Record { field, reason } => err(&field, reason),
        other => err("<record>", other.to_string()),
    })?;
    Ok(record)
}

fn shape_text(shape: &[usize]) -> String {
    format!(
        "[{}]",
        shape
            .iter()
            .map(|d| d.to_string())
            .collect::<Vec<_>>()
            .join(", ")
    )
}

/// Row-major values of an array (or nested number lists) whose shape is one of `allowed`.
fn numbers(v: &PyValue, allowed: &[Vec<usize>]) -> std::result::Result<Vec<f64>, String> {
    let expected = allowed
        .iter()
        .map(|s| shape_text(s))
        .collect::<Vec<_>>()
        .join(" or ");
    let (shape, values) = match v {
        PyValue::Array(a) => {
            if matches!(a.data, ArrayData::Bool(_)) {
                return Err(format!(
                    "is a bool array, expected numbers of shape {expected}"
                ));
            }
            (a.shape.clone(), a.to_f64())
        }
        PyValue::List(_) => nested_numbers(v).ok_or_else(|| {
            format!("is a list that is not a regular array of numbers, expected shape {expected}")
        })?,
        other => {
            return Err(format!(
                "is {}, expected an array of shape {expected}",
                other.kind()
            ))
        }
    };
    if !allowed.contains(&shape) {
        return Err(format!(
            "has shape {}, expected {expected}",
            shape_text(&shape)
        ));
    }
    if let Some((i, x)) = values.iter().enumerate().find(|(_, x)| !x.is_finite()) {
        return Err(format!("element {i} is not finite ({x})"));
    }
    Ok(values)
}

/// Shape and values of regularly nested lists of numbers (at most 3 levels).
fn nested_numbers(v: &PyValue) -> Option<(Vec<usize>, Vec<f64>)> {
    fn walk(v: &PyValue, depth: usize, shape: &mut Vec<usize>, out: &mut Vec<f64>) -> Option<()> {
        match v {
            PyValue::Int(i) if depth == shape.len() => out.push(*i as f64),
            PyValue::Float(f) if depth == shape.len() => out.push(*f),
            PyValue::List(items) if depth < 3 => {
                if depth == shape.len() {
                    shape.push(items.len());
                } else if shape.get(depth) != Some(&items.len()) {
                    return None;
                }
                for item in items {
                    walk(item, depth + 1, shape, out)?;
                }
                // Empty lists fix no deeper dimensions; mixing them with non-empty ones is caught
                // by the length check above.
            }
            _ => return None,
        }
        Some(())
    }
    let mut shape = Vec::new();
    let mut out = Vec::new();
    walk(v, 0, &mut shape, &mut out)?;
    let numel: usize = shape.iter().product();
    (numel == out.len()).then_some((shape, out))
}

/// Writes records as the release's pickle (protocol 4, float32 numpy arrays), atomically.
pub fn write_records(path: &Path, records: &BTreeMap<String, TrackedFrame>) -> Result<()> {
    let bytes = records_to_pickle(path, records)?;
    Ok(write_atomic(path, &bytes)?)
}

/// The pickle bytes `write_records` writes (`path` only names the target in errors).
pub fn records_to_pickle(path: &Path, records: &BTreeMap<String, TrackedFrame>) -> Result<Vec<u8>> {
    let mut names: Vec<&String> = records.keys().collect();
    names.sort_by(|a, b| frame_name_cmp(a, b));
    let mut frames = Vec::with_capacity(names.len());
    for name in names {
        let r = &records[name];
        let err = |field: &str, reason: String| DataError::Record {
            path: path.to_owned(),
            frame: format!("`{name}`"),
            field: field.to_owned(),
            reason,
        };
        let arr = |field: &str, shape: Vec<usize>, values: &[f64]| -> Result<PyValue> {
            let mut data = Vec::with_capacity(values.len());
            for (i, &x) in values.iter().enumerate() {
                // `as f32` turns out-of-range values into infinities; refuse those too.
                let y = x as f32;
                if !x.is_finite() || !y.is_finite() {
                    return Err(err(
                        field,
                        format!("element {i} ({x}) is not a finite float32"),
                    ));
                }
                data.push(y);
            }
            Ok(PyValue::Array(NdArray {
                shape,
                data: ArrayData::F32(data),
            }))
        };
        let code = |field: &str, v: &[f64], n: usize| -> Result<PyValue> {
            if v.len() > n {
                return Err(err(
                    field,
                    format!("has {} values, the release format holds {n}", v.len()),
                ));
            }
            let mut padded = v.to_vec();
            padded.resize(n, 0.0);
            arr(field, vec![n], &padded)
        };
        let bbox = r
            .bbox
            .ok_or_else(|| err("bbox", "is missing (the release format requires it)".into()))?;
        let tm = r.transform_matrix.ok_or_else(|| {
            err(
                "transform_matrix",
                "is missing (the release format requires it)".into(),
            )
        })?;
        let tm_flat: Vec<f64> = tm.iter().flatten().copied().collect();
        let fields = vec![
            ("bbox", arr("bbox", vec![4], &bbox)?),
            (
                "shapecode",
                code("shapecode", &r.shapecode, SHAPE_COMPONENTS)?,
            ),
            (
                "expcode",
                code("expcode", &r.expcode, EXPRESSION_COMPONENTS)?,
            ),
            ("posecode", code("posecode", &r.posecode, POSE_COMPONENTS)?),
            ("eyecode", code("eyecode", &r.eyecode, EYE_COMPONENTS)?),
            (
                "transform_matrix",
                arr("transform_matrix", vec![3, 4], &tm_flat)?,
            ),
        ];
        frames.push((
            DictKey::Str(name.clone()),
            PyValue::Dict(
                fields
                    .into_iter()
                    .map(|(k, v)| (DictKey::Str(k.to_owned()), v))
                    .collect(),
            ),
        ));
    }
    to_pickle(&PyValue::Dict(frames)).map_err(|reason| DataError::Write {
        path: path.to_owned(),
        reason,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nested_lists_read_as_arrays() {
        let l = |v: Vec<PyValue>| PyValue::List(v);
        let row = |a: f64| {
            l(vec![
                PyValue::Float(a),
                PyValue::Int(2),
                PyValue::Float(3.0),
                PyValue::Float(4.0),
            ])
        };
        let m = l(vec![row(1.0), row(5.0), row(9.0)]);
        assert_eq!(
            numbers(&m, &[vec![3, 4]]).unwrap(),
            [1.0, 2.0, 3.0, 4.0, 5.0, 2.0, 3.0, 4.0, 9.0, 2.0, 3.0, 4.0]
        );
        let ragged = l(vec![row(1.0), l(vec![PyValue::Float(1.0)]), row(2.0)]);
        assert!(numbers(&ragged, &[vec![3, 4]])
            .unwrap_err()
            .contains("not a regular array"));
        let e = numbers(&l(vec![PyValue::Float(f64::NAN)]), &[vec![1]]).unwrap_err();
        assert!(e.contains("element 0 is not finite"), "{e}");
        let e = numbers(&PyValue::Str("x".into()), &[vec![4], vec![1, 4]]).unwrap_err();
        assert_eq!(e, "is a str, expected an array of shape [4] or [1, 4]");
    }
}
