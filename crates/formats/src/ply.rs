//! PLY point clouds: a reader of one `vertex` element of scalar properties (ascii or binary
//! little endian; other elements must come after it and are ignored), and a writer of binary
//! little-endian float properties, the layout 3DGS viewers read. What the properties mean
//! (positions, opacities, spherical harmonics) is the caller's business.

use std::path::Path;

use crate::atomic::write_atomic;
use crate::error::{label_of, FormatError, Result};

/// A parsed vertex element.
#[derive(Debug, Clone, PartialEq)]
pub struct Ply {
    /// Property names in file order.
    pub names: Vec<String>,
    /// `comment` lines of the header, trimmed, with the `comment` keyword.
    pub comments: Vec<String>,
    pub rows: usize,
    /// Row-major values: row `r`, property `c` at `r * names.len() + c`.
    pub values: Vec<f64>,
}

impl Ply {
    /// The column of a property.
    pub fn column(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|p| p == name)
    }

    /// Value of property column `c` in row `r`.
    pub fn value(&self, r: usize, c: usize) -> f64 {
        self.values[r * self.names.len() + c]
    }
}

#[derive(Clone, Copy)]
enum Ty {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Ty {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Ty::I8,
            "uchar" | "uint8" => Ty::U8,
            "short" | "int16" => Ty::I16,
            "ushort" | "uint16" => Ty::U16,
            "int" | "int32" => Ty::I32,
            "uint" | "uint32" => Ty::U32,
            "float" | "float32" => Ty::F32,
            "double" | "float64" => Ty::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Ty::I8 | Ty::U8 => 1,
            Ty::I16 | Ty::U16 => 2,
            Ty::I32 | Ty::U32 | Ty::F32 => 4,
            Ty::F64 => 8,
        }
    }

    /// `b` holds exactly `size()` bytes.
    fn read(self, b: &[u8]) -> f64 {
        let mut a = [0u8; 8];
        a[..b.len()].copy_from_slice(b);
        match self {
            Ty::I8 => a[0] as i8 as f64,
            Ty::U8 => a[0] as f64,
            Ty::I16 => i16::from_le_bytes([a[0], a[1]]) as f64,
            Ty::U16 => u16::from_le_bytes([a[0], a[1]]) as f64,
            Ty::I32 => i32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            Ty::U32 => u32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            Ty::F32 => f32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            Ty::F64 => f64::from_le_bytes(a),
        }
    }
}

/// Upper bound on the vertex count, so a corrupt header cannot ask for absurd memory.
pub const MAX_ROWS: usize = 100_000_000;
/// Upper bound on the header (a 3DGS header with a few hundred properties is a few kB).
const MAX_HEADER: usize = 1 << 20;

/// Parses PLY bytes; the error is one line without the file name.
pub fn parse_ply(bytes: &[u8]) -> std::result::Result<Ply, String> {
    let search = &bytes[..bytes.len().min(MAX_HEADER)];
    let end = search
        .windows(11)
        .position(|w| w == b"end_header\n")
        .ok_or("no `end_header` line in the first MiB: not a PLY file")?;
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "the header is not text")?;
    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err("the file does not start with the `ply` magic line".into());
    }
    let mut binary = None;
    let mut rows = None;
    let mut in_vertex = false;
    let mut names = Vec::new();
    let mut types = Vec::new();
    let mut comments = Vec::new();
    for line in lines {
        let parts: Vec<&str> = line.split_whitespace().collect();
        match parts.as_slice() {
            ["format", "binary_little_endian", _] => binary = Some(true),
            ["format", "ascii", _] => binary = Some(false),
            ["format", f, ..] => return Err(format!("unsupported format `{f}`")),
            ["comment", ..] => comments.push(line.trim().to_string()),
            ["element", "vertex", n] => {
                if rows.is_some() {
                    return Err("more than one vertex element".into());
                }
                let n: usize = n.parse().map_err(|_| format!("bad vertex count `{n}`"))?;
                if n > MAX_ROWS {
                    return Err(format!("vertex count {n} exceeds {MAX_ROWS}"));
                }
                rows = Some(n);
                in_vertex = true;
            }
            ["element", ..] => {
                if rows.is_none() {
                    return Err("elements before `vertex` are not supported".into());
                }
                in_vertex = false;
            }
            ["property", "list", ..] if in_vertex => {
                return Err("list properties on vertices are not supported".into())
            }
            ["property", ty, name] if in_vertex => {
                let t = Ty::parse(ty).ok_or_else(|| format!("unknown property type `{ty}`"))?;
                types.push(t);
                names.push(name.to_string());
            }
            _ => {}
        }
    }
    let binary = binary.ok_or("the header has no format line")?;
    let rows = rows.ok_or("the header has no vertex element")?;
    let body = &bytes[end + 11..];
    let count = rows
        .checked_mul(names.len())
        .ok_or("the vertex count times the property count overflows")?;
    let mut values;
    if binary {
        let stride: usize = types.iter().map(|t| t.size()).sum();
        let need = rows
            .checked_mul(stride)
            .ok_or("the vertex data size overflows")?;
        if body.len() < need {
            return Err(format!(
                "the body is truncated: {} bytes for {rows} vertices of {stride} bytes",
                body.len()
            ));
        }
        values = Vec::with_capacity(count);
        for row in body[..need].chunks_exact(stride.max(1)).take(rows) {
            let mut off = 0;
            for t in &types {
                values.push(t.read(&row[off..off + t.size()]));
                off += t.size();
            }
        }
    } else {
        let text = std::str::from_utf8(body).map_err(|_| "the ascii body is not text")?;
        // Every value takes at least two bytes (a digit and a separator), so a header that
        // promises more than the body can hold fails before anything is allocated for it.
        if count > body.len() / 2 + 1 {
            return Err(format!(
                "the body is truncated: {} bytes for {count} ascii values",
                body.len()
            ));
        }
        values = Vec::with_capacity(count);
        let mut it = text.split_whitespace();
        for _ in 0..count {
            let tok = it.next().ok_or("the ascii body is truncated")?;
            values.push(tok.parse().map_err(|_| format!("bad number `{tok}`"))?);
        }
    }
    Ok(Ply {
        names,
        comments,
        rows,
        values,
    })
}

/// Reads and parses a PLY file; errors name it.
pub fn read_ply(path: &Path) -> Result<Ply> {
    let bytes = std::fs::read(path).map_err(FormatError::io(path, "cannot read"))?;
    parse_ply(&bytes).map_err(|reason| FormatError::Ply {
        label: label_of(path),
        reason,
    })
}

/// Binary little-endian PLY bytes of one vertex element with float properties `names`;
/// `values` holds the rows one after another. `comments` are written as `comment ...` lines.
pub fn ply_bytes(
    comments: &[&str],
    names: &[&str],
    values: &[f32],
) -> std::result::Result<Vec<u8>, String> {
    if names.is_empty() {
        return Err("a PLY vertex needs at least one property".into());
    }
    if !values.len().is_multiple_of(names.len()) {
        return Err(format!(
            "{} values are not whole rows of {} properties",
            values.len(),
            names.len()
        ));
    }
    let rows = values.len() / names.len();
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    for c in comments {
        if c.contains('\n') {
            return Err("a comment holds a line break".into());
        }
        header.push_str(&format!("comment {c}\n"));
    }
    header.push_str(&format!("element vertex {rows}\n"));
    for n in names {
        if n.is_empty() || n.contains(char::is_whitespace) {
            return Err(format!("property name {n:?} is empty or holds white space"));
        }
        header.push_str(&format!("property float {n}\n"));
    }
    header.push_str("end_header\n");
    let mut buf = header.into_bytes();
    buf.reserve(values.len() * 4);
    for v in values {
        buf.extend_from_slice(&v.to_le_bytes());
    }
    Ok(buf)
}

/// Writes [`ply_bytes`] to `path` atomically (temp sibling + rename).
pub fn write_ply(path: &Path, comments: &[&str], names: &[&str], values: &[f32]) -> Result<()> {
    let bytes = ply_bytes(comments, names, values).map_err(|reason| FormatError::Write {
        path: path.to_owned(),
        reason,
    })?;
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn written_files_read_back() {
        let bytes = ply_bytes(&["gagavatar"], &["x", "y"], &[1.0, 2.0, -3.0, 4.5]).unwrap();
        let p = parse_ply(&bytes).unwrap();
        assert_eq!(p.names, ["x", "y"]);
        assert_eq!(p.comments, ["comment gagavatar"]);
        assert_eq!(p.rows, 2);
        assert_eq!(p.values, [1.0, 2.0, -3.0, 4.5]);
        assert_eq!(p.value(1, p.column("y").unwrap()), 4.5);
    }

    #[test]
    fn ascii_and_mixed_types_parse() {
        let text =
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty uchar a\nproperty double b\n\
element face 0\nproperty list uchar int vertex_indices\nend_header\n255 -1.5\n0 2e3\n";
        let p = parse_ply(text).unwrap();
        assert_eq!(p.values, [255.0, -1.5, 0.0, 2000.0]);
    }

    #[test]
    fn headers_that_promise_more_than_the_body_fail_before_allocating() {
        let text = b"ply\nformat ascii 1.0\nelement vertex 99999999\nproperty float a\n\
property float b\nproperty float c\nend_header\n1 2 3\n";
        let e = parse_ply(text).unwrap_err();
        assert!(e.contains("truncated"), "{e}");
        let bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\n\
property float a\nend_header\n\0\0\0\0";
        let e = parse_ply(bin).unwrap_err();
        assert!(e.contains("truncated"), "{e}");
        for bad in [&b"ply\n"[..], b"", b"end_header\n", b"ply\nend_header\n"] {
            assert!(parse_ply(bad).is_err());
        }
    }
}
