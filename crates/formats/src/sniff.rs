//! What a file is, from its first bytes, in words for error messages ("this is a PNG image, not
//! a tracked-frame record"). Only formats with unambiguous magic numbers are named; text formats
//! (JSON, TOML, PLY headers) are left to their parsers.

/// A short description with an article ("a PNG image"), or `None` when the bytes start like
/// none of the binary formats below.
pub fn describe(bytes: &[u8]) -> Option<&'static str> {
    if let Some(kind) = crate::image::sniff(bytes) {
        return Some(match kind {
            crate::image::ImageKind::Png => "a PNG image",
            crate::image::ImageKind::Jpeg => "a JPEG image",
            crate::image::ImageKind::WebP => "a WebP image",
            crate::image::ImageKind::Bmp => "a BMP image",
        });
    }
    let at = |i: usize, magic: &[u8]| bytes.get(i..i + magic.len()) == Some(magic);
    Some(if at(0, b"GIF87a") || at(0, b"GIF89a") {
        "a GIF image"
    } else if at(4, b"ftyp") {
        let brand = bytes.get(8..12).unwrap_or(&[]);
        if [&b"heic"[..], b"heix", b"mif1", b"msf1", b"avif"].contains(&brand) {
            "a HEIF/AVIF image"
        } else {
            "an MP4/QuickTime video"
        }
    } else if at(0, &[0x1a, 0x45, 0xdf, 0xa3]) {
        "a Matroska/WebM video"
    } else if at(0, b"RIFF") && at(8, b"AVI ") {
        "an AVI video"
    } else if at(0, b"PK\x03\x04") {
        "a zip archive (a torch checkpoint?)"
    } else if at(0, &[0x80]) && bytes.get(1).is_some_and(|&p| (2..=5).contains(&p)) {
        "a Python pickle"
    } else if at(0, b"\x93NUMPY") {
        "a numpy .npy array"
    } else if bytes.len() >= 9 && at(8, b"{\"") && bytes[..8].iter().any(|&b| b != 0) {
        "a safetensors file"
    } else if at(16, &0xBEEF_C0DEu32.to_le_bytes()) {
        "an LMDB database file"
    } else {
        return None;
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn common_files_are_named_and_text_is_not() {
        assert_eq!(describe(b"\x89PNG\r\n\x1a\n...."), Some("a PNG image"));
        assert_eq!(describe(&[0xff, 0xd8, 0xff, 0xe0]), Some("a JPEG image"));
        assert_eq!(
            describe(b"\0\0\0\x20ftypisom\0\0\0\0"),
            Some("an MP4/QuickTime video")
        );
        assert_eq!(describe(b"\x80\x04\x95..."), Some("a Python pickle"));
        assert_eq!(
            describe(b"PK\x03\x04rest"),
            Some("a zip archive (a torch checkpoint?)")
        );
        assert_eq!(
            describe(b"\x10\0\0\0\0\0\0\0{\"a\":1}"),
            Some("a safetensors file")
        );
        for text in [&b"{\"shapecode\": []}"[..], b"[model]\n", b"", b"ply\n"] {
            assert_eq!(describe(text), None, "{:?}", String::from_utf8_lossy(text));
        }
    }
}
