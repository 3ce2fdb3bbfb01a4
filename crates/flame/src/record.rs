//! A tracked-frame record (spec section 10) as JSON: `shapecode`, `expcode`, `posecode`,
//! `eyecode`, optional `transform_matrix` [3][4] and `bbox` [4]. Codes may be flat arrays or a
//! single nested row (`[[...]]`, as a `[1, N]` numpy array dumps). Shorter codes are zero-padded
//! to the model's counts, because trackers often keep fewer components; longer ones are an error,
//! because silently dropping components would change the head.
//!
//! Values far outside what FLAME codes and cameras are (a shape code of 1e30 renders a black
//! frame, not an error of its own) are refused when a record is read: codes beyond
//! [`MAX_CODE_ABS`], camera and box values beyond [`MAX_CAMERA_ABS`].

use std::path::Path;

use candle_core::Tensor;
use serde_json::Value;

use crate::error::{FlameError, Result};
use crate::lbs::{FlameModel, FlameParams};

/// Largest magnitude accepted in `shapecode`, `expcode`, `posecode`, `eyecode`. FLAME's shape
/// and expression codes are in standard deviations (trackers keep them within about ±5) and the
/// poses in radians; 1000 is far beyond any head and still catches units mistakes and garbage.
pub const MAX_CODE_ABS: f64 = 1e3;
/// Largest magnitude accepted in `transform_matrix` and `bbox` (rotations are within ±1, the
/// release's camera sits about 10 units away, boxes are in pixels).
pub const MAX_CAMERA_ABS: f64 = 1e6;

#[derive(Debug, Clone, PartialEq)]
pub struct TrackedFrame {
    pub shapecode: Vec<f64>,
    pub expcode: Vec<f64>,
    pub posecode: Vec<f64>,
    pub eyecode: Vec<f64>,
    pub transform_matrix: Option<[[f64; 4]; 3]>,
    pub bbox: Option<[f64; 4]>,
}

fn rec_err(field: &str, reason: impl Into<String>) -> FlameError {
    FlameError::Record {
        field: field.to_owned(),
        reason: reason.into(),
    }
}

fn numbers(field: &str, v: &Value) -> Result<Vec<f64>> {
    let arr = match v {
        Value::Array(a) if a.len() == 1 && a[0].is_array() => match &a[0] {
            Value::Array(inner) => inner,
            _ => a,
        },
        Value::Array(a) => a,
        _ => return Err(rec_err(field, "is not an array of numbers")),
    };
    arr.iter()
        .enumerate()
        .map(|(i, x)| match x.as_f64() {
            Some(f) if f.is_finite() => Ok(f),
            Some(f) => Err(rec_err(field, format!("element {i} is not finite ({f})"))),
            None => Err(rec_err(field, format!("element {i} is not a number ({x})"))),
        })
        .collect()
}

fn required(obj: &serde_json::Map<String, Value>, field: &str) -> Result<Vec<f64>> {
    let v = obj.get(field).ok_or_else(|| rec_err(field, "is missing"))?;
    numbers(field, v)
}

impl TrackedFrame {
    pub fn from_json_str(text: &str) -> Result<Self> {
        // JSON has no NaN/Infinity literals; serde_json rejects them (and out-of-range numbers)
        // here, so such records fail with the parser's position.
        let v: Value = serde_json::from_str(text).map_err(|e| rec_err("<json>", e.to_string()))?;
        Self::from_json_value(&v)
    }

    /// A record that is part of a larger JSON document (a driving sequence's `frames` entry).
    /// Keys other than the record's fields are ignored.
    pub fn from_json_value(v: &Value) -> Result<Self> {
        let obj = v
            .as_object()
            .ok_or_else(|| rec_err("<json>", "top level is not an object"))?;
        let transform_matrix = match obj.get("transform_matrix") {
            None | Some(Value::Null) => None,
            Some(tm) => {
                let rows = match tm {
                    Value::Array(r) => r,
                    _ => return Err(rec_err("transform_matrix", "is not a 3x4 array")),
                };
                // Accept [3][4] or a single batch row [1][3][4].
                let rows = match rows.as_slice() {
                    [Value::Array(inner)] if inner.len() == 3 => inner,
                    _ => rows,
                };
                if rows.len() != 3 {
                    return Err(rec_err(
                        "transform_matrix",
                        format!("has {} rows, expected 3", rows.len()),
                    ));
                }
                let mut m = [[0.0; 4]; 3];
                for (r, row) in rows.iter().enumerate() {
                    let vals = numbers("transform_matrix", row)?;
                    if vals.len() != 4 {
                        return Err(rec_err(
                            "transform_matrix",
                            format!("row {r} has {} values, expected 4", vals.len()),
                        ));
                    }
                    m[r].copy_from_slice(&vals);
                }
                Some(m)
            }
        };
        let bbox = match obj.get("bbox") {
            None | Some(Value::Null) => None,
            Some(b) => {
                let vals = numbers("bbox", b)?;
                let arr: [f64; 4] = vals.try_into().map_err(|v: Vec<f64>| {
                    rec_err("bbox", format!("has {} values, expected 4", v.len()))
                })?;
                Some(arr)
            }
        };
        let r = Self {
            shapecode: required(obj, "shapecode")?,
            expcode: required(obj, "expcode")?,
            posecode: required(obj, "posecode")?,
            eyecode: required(obj, "eyecode")?,
            transform_matrix,
            bbox,
        };
        r.validate()?;
        Ok(r)
    }

    /// Checks that every value is one a FLAME record can hold: finite, codes within
    /// [`MAX_CODE_ABS`], camera and box within [`MAX_CAMERA_ABS`]. The error names the field and
    /// the element.
    pub fn validate(&self) -> Result<()> {
        let check = |field: &str, values: &mut dyn Iterator<Item = f64>, max: f64| {
            for (i, x) in values.enumerate() {
                if !x.is_finite() {
                    return Err(rec_err(field, format!("element {i} is not finite ({x})")));
                }
                if x.abs() > max {
                    return Err(rec_err(
                        field,
                        format!(
                            "element {i} is {x:e}, far outside what a FLAME record holds (at most                              {max:e} in magnitude)"
                        ),
                    ));
                }
            }
            Ok(())
        };
        check(
            "shapecode",
            &mut self.shapecode.iter().copied(),
            MAX_CODE_ABS,
        )?;
        check("expcode", &mut self.expcode.iter().copied(), MAX_CODE_ABS)?;
        check("posecode", &mut self.posecode.iter().copied(), MAX_CODE_ABS)?;
        check("eyecode", &mut self.eyecode.iter().copied(), MAX_CODE_ABS)?;
        if let Some(tm) = &self.transform_matrix {
            check(
                "transform_matrix",
                &mut tm.iter().flatten().copied(),
                MAX_CAMERA_ABS,
            )?;
        }
        if let Some(b) = &self.bbox {
            check("bbox", &mut b.iter().copied(), MAX_CAMERA_ABS)?;
        }
        Ok(())
    }

    /// Reads a JSON record file; every error names the file. A file that is something else (a
    /// photo, a video, a pickle) says what it is.
    pub fn from_json_file(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|err| FlameError::Io {
            path: path.to_owned(),
            err,
        })?;
        let file_err = |field: String, reason: String| FlameError::RecordFile {
            path: path.to_owned(),
            field,
            reason,
        };
        if let Some(kind) = gagavatar_formats::sniff::describe(&bytes) {
            return Err(file_err(
                "<file>".into(),
                format!(
                    "this is {kind}, not a tracked-frame record (JSON with shapecode, expcode,                      posecode, eyecode)"
                ),
            ));
        }
        let text = std::str::from_utf8(&bytes).map_err(|_| {
            file_err(
                "<file>".into(),
                "not text, so not a tracked-frame record (JSON)".into(),
            )
        })?;
        Self::from_json_str(text).map_err(|e| match e {
            FlameError::Record { field, reason } => file_err(field, reason),
            other => other,
        })
    }

    /// A batch of one, zero-padded to the model's component counts.
    pub fn params(&self, model: &FlameModel) -> Result<FlameParams> {
        let pad = |field: &str, v: &[f64], n: usize| -> Result<Tensor> {
            if v.len() > n {
                return Err(rec_err(
                    field,
                    format!("has {} values, the model takes at most {n}", v.len()),
                ));
            }
            let mut out = v.to_vec();
            out.resize(n, 0.0);
            Ok(Tensor::from_vec(out, (1, n), &model.device)?.to_dtype(model.dtype)?)
        };
        Ok(FlameParams {
            shape: pad("shapecode", &self.shapecode, model.config.n_shape)?,
            expression: pad("expcode", &self.expcode, model.config.n_exp)?,
            pose: pad("posecode", &self.posecode, 6)?,
            eye: pad("eyecode", &self.eyecode, 6)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_nested_rows_and_optional_fields() {
        let r = TrackedFrame::from_json_str(
            r#"{"shapecode": [[0.1, 0.2]], "expcode": [1], "posecode": [0,0,0,0.1,0,0],
                "eyecode": [], "bbox": [0.1, 0.2, 0.8, 0.9],
                "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,10]]}"#,
        )
        .unwrap();
        assert_eq!(r.shapecode, vec![0.1, 0.2]);
        assert_eq!(r.transform_matrix.unwrap()[2][3], 10.0);
        assert_eq!(r.bbox.unwrap()[3], 0.9);
    }

    #[test]
    fn rejects_nan_strings_and_missing_fields() {
        let nan = TrackedFrame::from_json_str(
            r#"{"shapecode": [NaN], "expcode": [], "posecode": [], "eyecode": []}"#,
        );
        assert!(matches!(nan, Err(FlameError::Record { .. })), "{nan:?}");
        let s = TrackedFrame::from_json_str(
            r#"{"shapecode": ["a"], "expcode": [], "posecode": [], "eyecode": []}"#,
        );
        assert!(
            matches!(s, Err(FlameError::Record { ref field, .. }) if field == "shapecode"),
            "{s:?}"
        );
        let m = TrackedFrame::from_json_str(r#"{"shapecode": [], "posecode": [], "eyecode": []}"#);
        assert!(
            matches!(m, Err(FlameError::Record { ref field, .. }) if field == "expcode"),
            "{m:?}"
        );
        let big = TrackedFrame::from_json_str(
            r#"{"shapecode": [1e999], "expcode": [], "posecode": [], "eyecode": []}"#,
        );
        assert!(matches!(big, Err(FlameError::Record { .. })), "{big:?}");
    }
}
