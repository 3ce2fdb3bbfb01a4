//! The scores: one CSV row per pair (kept on disk as pairs finish, so an interrupted run
//! resumes where it stopped), a JSON summary, and a text table in the paper's column order
//! (self: PSNR, SSIM, LPIPS, CSIM, AED, APD, AKD; cross: CSIM, AED, APD).
//!
//! An empty CSV cell is a score that could not be computed for that pair (no face found on the
//! result, no LPIPS weights); means are over the pairs that have the score, with the count.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::error::{input_err, Result};
use crate::protocol::{EvalPair, Mode};

/// The CSV's columns, in order.
pub const CSV_HEADER: [&str; 12] = [
    "mode",
    "source",
    "driver",
    "psnr",
    "ssim",
    "lpips",
    "csim",
    "aed",
    "apd",
    "akd",
    "realigned",
    "result_face",
];

/// The metrics' names in the paper's order, per mode.
pub const SELF_COLUMNS: [&str; 7] = ["psnr", "ssim", "lpips", "csim", "aed", "apd", "akd"];
pub const CROSS_COLUMNS: [&str; 3] = ["csim", "aed", "apd"];

/// The scores of one pair (`None`: not computed).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PairRow {
    pub pair: EvalPair,
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    pub lpips: Option<f64>,
    pub csim: Option<f64>,
    pub aed: Option<f64>,
    pub apd: Option<f64>,
    pub akd: Option<f64>,
    /// Whether the crop came from the reference's landmarks (else the whole frame).
    pub realigned: bool,
    /// Whether a face was found on the realigned result.
    pub result_face: bool,
}

impl PairRow {
    pub fn new(pair: EvalPair) -> Self {
        Self {
            pair,
            psnr: None,
            ssim: None,
            lpips: None,
            csim: None,
            aed: None,
            apd: None,
            akd: None,
            realigned: false,
            result_face: false,
        }
    }

    pub fn metric(&self, name: &str) -> Option<f64> {
        match name {
            "psnr" => self.psnr,
            "ssim" => self.ssim,
            "lpips" => self.lpips,
            "csim" => self.csim,
            "aed" => self.aed,
            "apd" => self.apd,
            "akd" => self.akd,
            _ => None,
        }
    }
}

fn quote(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

fn num(v: Option<f64>) -> String {
    // `inf` for identical images (PSNR); 17 significant digits round-trip exactly.
    v.map(|x| format!("{x:e}")).unwrap_or_default()
}

/// The CSV text of `rows` (header included).
pub fn to_csv(rows: &[PairRow]) -> String {
    let mut s = CSV_HEADER.join(",");
    s.push('\n');
    for r in rows {
        let cells = [
            r.pair.mode.name().to_string(),
            quote(&r.pair.source),
            quote(&r.pair.driver),
            num(r.psnr),
            num(r.ssim),
            num(r.lpips),
            num(r.csim),
            num(r.aed),
            num(r.apd),
            num(r.akd),
            r.realigned.to_string(),
            r.result_face.to_string(),
        ];
        s += &cells.join(",");
        s.push('\n');
    }
    s
}

/// Splits one CSV line (RFC 4180 quoting, as [`to_csv`] writes).
fn split_line(line: &str) -> Option<Vec<String>> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut chars = line.chars().peekable();
    let mut quoted = false;
    while let Some(c) = chars.next() {
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                chars.next();
                cur.push('"');
            }
            (true, '"') => quoted = false,
            (false, '"') if cur.is_empty() => quoted = true,
            (false, ',') => out.push(std::mem::take(&mut cur)),
            (_, c) => cur.push(c),
        }
    }
    if quoted {
        return None;
    }
    out.push(cur);
    Some(out)
}

/// Rows of a CSV written by [`to_csv`]; a malformed line is an error naming it.
pub fn parse_csv(text: &str, path: &Path) -> Result<Vec<PairRow>> {
    let bad = |line: usize, why: &str| {
        input_err(
            &path.display().to_string(),
            format!("line {line}: {why} (delete the file to start over)"),
        )
    };
    let mut lines = text.lines().enumerate();
    match lines.next() {
        Some((_, h)) if h == CSV_HEADER.join(",") => {}
        Some(_) => return Err(bad(1, "not the evaluation header")),
        None => return Ok(Vec::new()),
    }
    let mut rows = Vec::new();
    for (i, line) in lines {
        if line.is_empty() {
            continue;
        }
        let c = split_line(line).ok_or_else(|| bad(i + 1, "unterminated quote"))?;
        if c.len() != CSV_HEADER.len() {
            return Err(bad(
                i + 1,
                &format!("{} cells, expected {}", c.len(), CSV_HEADER.len()),
            ));
        }
        let mode = Mode::parse(&c[0]).ok_or_else(|| bad(i + 1, "mode must be self or cross"))?;
        let f = |k: usize| -> Result<Option<f64>> {
            if c[k].is_empty() {
                return Ok(None);
            }
            c[k].parse::<f64>()
                .map(Some)
                .map_err(|_| bad(i + 1, &format!("`{}` is not a number", c[k])))
        };
        let b = |k: usize| -> Result<bool> {
            c[k].parse::<bool>()
                .map_err(|_| bad(i + 1, &format!("`{}` is not true/false", c[k])))
        };
        rows.push(PairRow {
            pair: EvalPair {
                mode,
                source: c[1].clone(),
                driver: c[2].clone(),
            },
            psnr: f(3)?,
            ssim: f(4)?,
            lpips: f(5)?,
            csim: f(6)?,
            aed: f(7)?,
            apd: f(8)?,
            akd: f(9)?,
            realigned: b(10)?,
            result_face: b(11)?,
        });
    }
    Ok(rows)
}

/// Rows already in `path` (none when it does not exist).
pub fn read_csv(path: &Path) -> Result<Vec<PairRow>> {
    match std::fs::read_to_string(path) {
        Ok(t) => parse_csv(&t, path),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(input_err(&path.display().to_string(), e.to_string())),
    }
}

/// Writes all rows atomically (temp file + rename).
pub fn write_csv(path: &Path, rows: &[PairRow]) -> Result<()> {
    gagavatar_formats::atomic::write_atomic(path, to_csv(rows).as_bytes())
        .map_err(|e| input_err(&path.display().to_string(), e.to_string()))
}

/// The mean of one metric over the pairs that have it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Mean {
    /// `None` when no pair has the score; `inf` stays `inf` (PSNR of identical images).
    pub mean: Option<f64>,
    pub n: usize,
}

/// Means per mode and metric, in the paper's column order.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ModeSummary {
    pub mode: Mode,
    pub pairs: usize,
    /// Pairs whose crop came from the reference's landmarks.
    pub realigned: usize,
    /// Pairs with a face found on the result.
    pub result_face: usize,
    pub metrics: Vec<(String, Mean)>,
}

pub fn summarize(rows: &[PairRow], mode: Mode) -> ModeSummary {
    let rows: Vec<&PairRow> = rows.iter().filter(|r| r.pair.mode == mode).collect();
    let cols: &[&str] = match mode {
        Mode::SelfReenactment => &SELF_COLUMNS,
        Mode::Cross => &CROSS_COLUMNS,
    };
    let metrics = cols
        .iter()
        .map(|&c| {
            let v: Vec<f64> = rows.iter().filter_map(|r| r.metric(c)).collect();
            let mean = (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
            (c.to_string(), Mean { mean, n: v.len() })
        })
        .collect();
    ModeSummary {
        mode,
        pairs: rows.len(),
        realigned: rows.iter().filter(|r| r.realigned).count(),
        result_face: rows.iter().filter(|r| r.result_face).count(),
        metrics,
    }
}

/// The summary as JSON: `meta` (run settings) plus one object per mode with pairs.
pub fn summary_json(rows: &[PairRow], meta: serde_json::Value) -> serde_json::Value {
    let mut modes = serde_json::Map::new();
    for mode in [Mode::SelfReenactment, Mode::Cross] {
        let s = summarize(rows, mode);
        if s.pairs == 0 {
            continue;
        }
        let mut m: BTreeMap<&str, serde_json::Value> = BTreeMap::new();
        m.insert("pairs", s.pairs.into());
        m.insert("realigned", s.realigned.into());
        m.insert("result_face", s.result_face.into());
        let metrics: serde_json::Map<String, serde_json::Value> = s
            .metrics
            .iter()
            .map(|(k, v)| {
                // JSON has no infinity: PSNR of identical images is written as the string "inf".
                let mean = match v.mean {
                    Some(x) if x.is_finite() => serde_json::json!(x),
                    Some(x) => serde_json::json!(x.to_string()),
                    None => serde_json::Value::Null,
                };
                (k.clone(), serde_json::json!({ "mean": mean, "n": v.n }))
            })
            .collect();
        m.insert("metrics", serde_json::Value::Object(metrics));
        m.insert(
            "columns",
            serde_json::json!(s.metrics.iter().map(|(k, _)| k.clone()).collect::<Vec<_>>()),
        );
        modes.insert(mode.name().to_string(), serde_json::json!(m));
    }
    serde_json::json!({ "meta": meta, "modes": modes })
}

/// A text table of the means, one block per mode, the paper's columns.
pub fn table(rows: &[PairRow]) -> String {
    let mut s = String::new();
    for mode in [Mode::SelfReenactment, Mode::Cross] {
        let sum = summarize(rows, mode);
        if sum.pairs == 0 {
            continue;
        }
        s += &format!(
            "{} reenactment: {} pairs ({} realigned on the reference's face, face found on {} \
             results)\n",
            mode.name(),
            sum.pairs,
            sum.realigned,
            sum.result_face
        );
        let head: Vec<String> = sum
            .metrics
            .iter()
            .map(|(k, _)| format!("{:>9}", k.to_uppercase()))
            .collect();
        s += &head.join(" ");
        s.push('\n');
        let vals: Vec<String> = sum
            .metrics
            .iter()
            .map(|(_, m)| match m.mean {
                Some(x) => format!("{x:>9.4}"),
                None => format!("{:>9}", "-"),
            })
            .collect();
        s += &vals.join(" ");
        s.push('\n');
        let ns: Vec<String> = sum
            .metrics
            .iter()
            .map(|(_, m)| format!("{:>9}", format!("n={}", m.n)))
            .collect();
        s += &ns.join(" ");
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(mode: Mode, d: &str, psnr: Option<f64>, csim: Option<f64>) -> PairRow {
        PairRow {
            psnr,
            csim,
            realigned: true,
            ..PairRow::new(EvalPair {
                mode,
                source: "a,\"b\"_0".into(),
                driver: d.into(),
            })
        }
    }

    #[test]
    fn csv_round_trips_quotes_inf_and_empty_cells() {
        let rows = vec![
            row(
                Mode::SelfReenactment,
                "x_1",
                Some(f64::INFINITY),
                Some(0.1 + 0.2),
            ),
            row(Mode::Cross, "y_3", None, Some(-0.5)),
        ];
        let text = to_csv(&rows);
        let back = parse_csv(&text, Path::new("t.csv")).unwrap();
        assert_eq!(back, rows);
    }

    #[test]
    fn malformed_csv_is_an_error_naming_the_line() {
        let p = Path::new("t.csv");
        assert!(parse_csv("nope\n", p).is_err());
        let mut t = to_csv(&[row(Mode::Cross, "y", None, None)]);
        t += "self,a,b,1\n";
        let e = parse_csv(&t, p).unwrap_err().to_string();
        assert!(e.contains("line 3"), "{e}");
        assert!(parse_csv("", p).unwrap().is_empty());
    }

    #[test]
    fn means_skip_missing_scores_in_paper_order() {
        let rows = vec![
            row(Mode::SelfReenactment, "x_1", Some(20.0), Some(0.5)),
            row(Mode::SelfReenactment, "x_2", Some(30.0), None),
            row(Mode::Cross, "y_1", None, Some(0.25)),
        ];
        let s = summarize(&rows, Mode::SelfReenactment);
        let names: Vec<&str> = s.metrics.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(names, SELF_COLUMNS);
        assert_eq!(
            s.metrics[0].1,
            Mean {
                mean: Some(25.0),
                n: 2
            }
        );
        assert_eq!(
            s.metrics[3].1,
            Mean {
                mean: Some(0.5),
                n: 1
            }
        );
        assert_eq!(s.metrics[2].1, Mean { mean: None, n: 0 });
        let c = summarize(&rows, Mode::Cross);
        assert_eq!(c.metrics.len(), 3);
        assert_eq!(c.metrics[0].1.mean, Some(0.25));
        let j = summary_json(&rows, serde_json::json!({"seed": 1}));
        assert_eq!(j["modes"]["self"]["metrics"]["psnr"]["mean"], 25.0);
        assert!(table(&rows).contains("PSNR"));
    }
}
