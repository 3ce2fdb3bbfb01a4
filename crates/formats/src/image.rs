//! Photos as users have them: the format is read from the bytes (PNG data named `.jpg` is common),
//! EXIF orientation is applied (phones store portraits sideways plus a flag), transparency is
//! composited onto black (the model's background), and a photo larger than the caller needs is
//! downscaled *while* it is decoded, so a 10000x10000 photo never exists at full size:
//!
//! - PNG (not interlaced) is decoded row by row into an area-average downscaler;
//! - a baseline JPEG that must shrink is decoded at 1/2, 1/4 or 1/8 size by the IDCT itself
//!   (`jpeg-decoder`), then area-averaged to the exact size;
//! - everything else (WebP, BMP, interlaced PNG, progressive or CMYK JPEG, and photos that need
//!   no downscaling) is decoded whole, and only up to [`MAX_WHOLE_DECODE_BYTES`] of decoded
//!   pixels, so a small hostile file cannot make the decoder allocate hundreds of megabytes.
//!
//! A header that asks for more than [`MAX_SIDE`] per side or [`MAX_PIXELS`] in all is refused
//! before anything is allocated.

use std::io::Cursor;
use std::path::Path;

use image::{DynamicImage, ImageDecoder, ImageFormat, ImageReader, Limits, RgbImage};

use crate::FormatError;

/// Largest width or height accepted (a corrupt or hostile header could otherwise ask for
/// gigabytes).
pub const MAX_SIDE: u32 = 16384;
/// Largest pixel count accepted: 150 MP, above every phone and most camera sensors (RGB at this
/// size is 450 MB).
pub const MAX_PIXELS: u64 = 150_000_000;
/// Allocation bound handed to the decoders: the RGB image at [`MAX_PIXELS`] plus decoder slack.
const MAX_ALLOC: u64 = 1 << 30;
/// Largest decoded buffer (width x height x bytes per pixel as the decoder outputs them) of a
/// photo that cannot be decoded row by row or at reduced size: 96 MiB is a 32-megapixel RGB
/// photo. With the RGB copy made from it, decoding stays under about 200 MB.
pub const MAX_WHOLE_DECODE_BYTES: u64 = 96 << 20;

/// The container formats recognised from the first bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageKind {
    Png,
    Jpeg,
    WebP,
    Bmp,
}

impl ImageKind {
    fn format(self) -> ImageFormat {
        match self {
            ImageKind::Png => ImageFormat::Png,
            ImageKind::Jpeg => ImageFormat::Jpeg,
            ImageKind::WebP => ImageFormat::WebP,
            ImageKind::Bmp => ImageFormat::Bmp,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            ImageKind::Png => "PNG",
            ImageKind::Jpeg => "JPEG",
            ImageKind::WebP => "WebP",
            ImageKind::Bmp => "BMP",
        }
    }
}

/// The image format of `bytes`, from their magic numbers alone.
pub fn sniff(bytes: &[u8]) -> Option<ImageKind> {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Some(ImageKind::Png)
    } else if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
        Some(ImageKind::Jpeg)
    } else if bytes.len() >= 12 && &bytes[0..4] == b"RIFF" && &bytes[8..12] == b"WEBP" {
        Some(ImageKind::WebP)
    } else if bytes.starts_with(b"BM") && bytes.len() >= 26 {
        Some(ImageKind::Bmp)
    } else {
        None
    }
}

/// How to decode.
#[derive(Debug, Clone, Copy)]
pub struct DecodeOptions {
    /// Smallest width and height accepted (after orientation); smaller images are refused with a
    /// clear message instead of going on to find nothing.
    pub min_side: u32,
    /// When set, an image whose longer side exceeds this is downscaled (area average) to fit.
    pub fit_within: Option<u32>,
}

impl Default for DecodeOptions {
    fn default() -> Self {
        DecodeOptions {
            min_side: 1,
            fit_within: None,
        }
    }
}

/// A decoded photo, upright, RGB.
#[derive(Debug, Clone)]
pub struct DecodedImage {
    pub rgb: RgbImage,
    /// The upright size of the photo as stored, before any downscaling.
    pub original_width: u32,
    pub original_height: u32,
    /// `rgb`'s pixel size in original pixels (1.0 when not downscaled): multiply coordinates
    /// found in `rgb` by this to report them in the original photo's pixels.
    pub scale_to_original: f64,
    pub kind: ImageKind,
    /// The EXIF orientation that was applied (`NoTransforms` when none was stored).
    pub orientation: image::metadata::Orientation,
}

/// Reads and decodes an image file; errors name the file.
pub fn read_image(path: &Path, opts: &DecodeOptions) -> Result<DecodedImage, FormatError> {
    let bytes = std::fs::read(path).map_err(FormatError::io(path, "cannot read"))?;
    decode_image(&bytes, &path.display().to_string(), opts)
}

/// Decodes image bytes; `label` names them in errors (a path, or an archive entry).
pub fn decode_image(
    bytes: &[u8],
    label: &str,
    opts: &DecodeOptions,
) -> Result<DecodedImage, FormatError> {
    let err = |reason: String| FormatError::Image {
        label: label.to_owned(),
        reason,
    };
    if bytes.is_empty() {
        return Err(err("the file is empty, not an image".into()));
    }
    let kind = match sniff(bytes) {
        Some(k) => k,
        None => return Err(err(unknown_format_reason(bytes))),
    };
    if kind == ImageKind::Jpeg {
        check_jpeg_data_length(bytes).map_err(err)?;
    }
    let streamed = match kind {
        ImageKind::Png => decode_png_rows(bytes, opts),
        ImageKind::Jpeg => decode_jpeg_scaled(bytes, opts),
        _ => Ok(None),
    }
    .map_err(err)?;
    let d = match streamed {
        Some(d) => d,
        None => decode_whole(bytes, kind, opts).map_err(err)?,
    };
    let mut dynimg = DynamicImage::ImageRgb8(d.rgb);
    dynimg.apply_orientation(d.orientation);
    let DynamicImage::ImageRgb8(rgb) = dynimg else {
        unreachable!("apply_orientation keeps the pixel type")
    };
    let (ow, oh) = upright(d.width, d.height, d.orientation);
    Ok(DecodedImage {
        scale_to_original: ow as f64 / rgb.width().max(1) as f64,
        rgb,
        original_width: ow,
        original_height: oh,
        kind,
        orientation: d.orientation,
    })
}

/// A decoded photo as stored (before orientation), possibly already downscaled.
struct Decoded {
    rgb: RgbImage,
    /// The stored size, before downscaling.
    width: u32,
    height: u32,
    orientation: image::metadata::Orientation,
}

fn upright(w: u32, h: u32, o: image::metadata::Orientation) -> (u32, u32) {
    if swaps_sides(o) {
        (h, w)
    } else {
        (w, h)
    }
}

/// Checks a stored size against the caps and `min_side`, and returns the size to decode to (the
/// stored size, or the downscaled one that fits `fit_within`).
fn target_size(
    w: u32,
    h: u32,
    orientation: image::metadata::Orientation,
    opts: &DecodeOptions,
) -> Result<(u32, u32), String> {
    check_size(w, h)?;
    let (ow, oh) = upright(w, h, orientation);
    if ow.min(oh) < opts.min_side {
        return Err(format!(
            "the image is {ow}x{oh} pixels; at least {m}x{m} is needed",
            m = opts.min_side
        ));
    }
    Ok(match opts.fit_within {
        Some(limit) if w.max(h) > limit.max(1) => {
            let s = limit.max(1) as f64 / w.max(h) as f64;
            (
                ((w as f64 * s).round() as u32).max(1),
                ((h as f64 * s).round() as u32).max(1),
            )
        }
        _ => (w, h),
    })
}

/// Where decoded rows go: straight into the output, or through the area downscaler.
enum RowSink {
    /// Grows with the rows actually decoded, so a header promising a huge image allocates
    /// nothing until its data arrives.
    Copy {
        data: Vec<u8>,
        w: u32,
        h: u32,
    },
    Shrink(AreaDownscaler),
}

impl RowSink {
    fn new(w: u32, h: u32, nw: u32, nh: u32) -> Self {
        if (nw, nh) == (w, h) {
            RowSink::Copy {
                data: Vec::new(),
                w,
                h,
            }
        } else {
            RowSink::Shrink(AreaDownscaler::new(w, h, nw, nh))
        }
    }

    fn push(&mut self, rgb_row: &[u8]) {
        match self {
            RowSink::Copy { data, .. } => data.extend_from_slice(rgb_row),
            RowSink::Shrink(d) => d.push_row(rgb_row),
        }
    }

    fn finish(self) -> Result<RgbImage, String> {
        match self {
            RowSink::Copy { data, w, h } => {
                RgbImage::from_raw(w, h, data).ok_or_else(|| "the image data is truncated".into())
            }
            RowSink::Shrink(d) => Ok(d.finish()),
        }
    }
}

fn png_reason(e: png::DecodingError) -> String {
    match e {
        png::DecodingError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            "the PNG data is truncated".into()
        }
        png::DecodingError::LimitsExceeded => format!(
            "the PNG image is too large to decode (more than {} MiB)",
            MAX_ALLOC >> 20
        ),
        other => format!("corrupt PNG data ({other})"),
    }
}

/// A non-interlaced PNG, row by row into the output size; `None` for an interlaced one.
fn decode_png_rows(bytes: &[u8], opts: &DecodeOptions) -> Result<Option<Decoded>, String> {
    // The size straight from IHDR (always the first chunk), so a header stating an oversized
    // image is called that even when the file ends before its data (the reader below would
    // stop at the missing data first).
    if bytes.len() >= 24 && &bytes[12..16] == b"IHDR" {
        let be = |at: usize| {
            u32::from_be_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
        };
        let (w, h) = (be(16), be(20));
        if w > 0 && h > 0 {
            check_size(w, h)?;
        }
    }
    let mut dec = png::Decoder::new_with_limits(
        Cursor::new(bytes),
        png::Limits {
            bytes: MAX_ALLOC as usize,
        },
    );
    // 8-bit gray, gray + alpha, RGB or RGBA rows (palettes and low bit depths expanded).
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = dec.read_info().map_err(png_reason)?;
    let info = reader.info();
    if info.interlaced {
        return Ok(None);
    }
    let (w, h) = (info.width, info.height);
    let orientation = info
        .exif_metadata
        .as_deref()
        .and_then(image::metadata::Orientation::from_exif_chunk)
        .unwrap_or(image::metadata::Orientation::NoTransforms);
    let (nw, nh) = target_size(w, h, orientation, opts)?;
    let channels = match reader.output_color_type().0 {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Ok(None),
    };
    let mut sink = RowSink::new(w, h, nw, nh);
    let mut line = vec![0u8; w as usize * 3];
    for _ in 0..h {
        let row = reader
            .next_row()
            .map_err(png_reason)?
            .ok_or("the PNG data is truncated")?;
        let data = row.data();
        if data.len() < w as usize * channels {
            return Err("corrupt PNG data (a short row)".into());
        }
        for (px, out) in data.chunks_exact(channels).zip(line.chunks_exact_mut(3)) {
            let (rgb, a) = match channels {
                1 => ([px[0]; 3], 255),
                2 => ([px[0]; 3], px[1]),
                3 => ([px[0], px[1], px[2]], 255),
                _ => ([px[0], px[1], px[2]], px[3]),
            };
            for c in 0..3 {
                out[c] = on_black(rgb[c], a);
            }
        }
        sink.push(&line);
    }
    // Every row can be out before the data stream ends (its checksum, the chunk's CRC, IEND):
    // reading to the end refuses a file cut there, as the whole-image decoders do.
    reader.finish().map_err(png_reason)?;
    Ok(Some(Decoded {
        rgb: sink.finish()?,
        width: w,
        height: h,
        orientation,
    }))
}

/// Refuses a sequential (baseline or extended Huffman) JPEG whose image data is too short for
/// the size its header states: every 8x8 block of every component takes at least two Huffman
/// codes (its DC difference and an end-of-block), each at least one bit. The decoders fill the
/// blocks a truncated file lacks, so without this a 700-byte file saying 6693x6169 cost as
/// much time as a real 41-megapixel photo (seconds; found by fuzzing). Progressive files (whose
/// end-of-band runs legitimately cover many blocks with one code) and headers this cannot
/// read are left to the decoder.
fn check_jpeg_data_length(bytes: &[u8]) -> Result<(), String> {
    // The largest minimum over the sequential frame headers before the first scan, with its
    // size: a file with several frame headers (malformed, but decoders read some of them) is
    // held to the most demanding one, so a decoy header cannot hide a huge one.
    let mut floor: Option<(u64, u64, u64)> = None;
    let mut i = 2;
    while i + 4 <= bytes.len() {
        if bytes[i] != 0xff {
            // The decoders skip garbage between segments, looking for the next marker.
            i += 1;
            continue;
        }
        let marker = bytes[i + 1];
        if marker == 0xff {
            // Fill byte before a marker.
            i += 1;
            continue;
        }
        if marker == 0x01 || (0xd0..=0xd7).contains(&marker) {
            i += 2;
            continue;
        }
        let len = u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]) as usize;
        let Some(segment) = bytes.get(i + 4..i + 2 + len).filter(|_| len >= 2) else {
            return Ok(());
        };
        match marker {
            // Baseline and extended sequential, Huffman coded.
            0xc0 | 0xc1 if segment.len() >= 6 => {
                let h = u64::from(u16::from_be_bytes([segment[1], segment[2]]));
                let w = u64::from(u16::from_be_bytes([segment[3], segment[4]]));
                let comps: Vec<(u64, u64)> = segment[6..]
                    .chunks_exact(3)
                    .take(usize::from(segment[5]))
                    .map(|c| (u64::from(c[1] >> 4), u64::from(c[1] & 15)))
                    .collect();
                let hmax = comps.iter().map(|c| c.0).max().unwrap_or(0);
                let vmax = comps.iter().map(|c| c.1).max().unwrap_or(0);
                if w > 0 && h > 0 && hmax > 0 && vmax > 0 {
                    let blocks: u64 = comps
                        .iter()
                        .map(|&(ch, cv)| {
                            let cw = (w * ch).div_ceil(hmax);
                            let cht = (h * cv).div_ceil(vmax);
                            cw.div_ceil(8) * cht.div_ceil(8)
                        })
                        .sum();
                    let needed = (blocks * 2).div_ceil(8);
                    if floor.is_none_or(|f| needed > f.2) {
                        floor = Some((w, h, needed));
                    }
                }
            }
            // Start of scan: the entropy-coded data follows.
            0xda => {
                let have = (bytes.len() - (i + 2 + len)) as u64;
                return match floor {
                    Some((w, h, needed)) if have < needed => Err(format!(
                        "the JPEG data is truncated: a {w}x{h} image needs at least {needed} bytes \
                         of image data, the file has {have}"
                    )),
                    _ => Ok(()),
                };
            }
            _ => {}
        }
        i += 2 + len;
    }
    Ok(())
}

/// A colour channel with alpha, composited onto black (rounded).
fn on_black(c: u8, a: u8) -> u8 {
    ((c as u32 * a as u32 + 127) / 255) as u8
}

/// A baseline 8-bit gray or RGB JPEG larger than `fit_within`, decoded at the smallest IDCT
/// scale (1/8 .. 1) still at least the output size, then area-averaged to it. `None` when the
/// JPEG needs no downscaling or is of a kind this path does not take (the whole decode then
/// handles it).
fn decode_jpeg_scaled(bytes: &[u8], opts: &DecodeOptions) -> Result<Option<Decoded>, String> {
    let Some(limit) = opts.fit_within else {
        return Ok(None);
    };
    let mut dec = jpeg_decoder::Decoder::new(Cursor::new(bytes));
    if dec.read_info().is_err() {
        // Let the whole decode give its own message.
        return Ok(None);
    }
    let Some(info) = dec.info() else {
        return Ok(None);
    };
    let (w, h) = (u32::from(info.width), u32::from(info.height));
    if w.max(h) <= limit.max(1)
        || !matches!(
            info.pixel_format,
            jpeg_decoder::PixelFormat::L8 | jpeg_decoder::PixelFormat::RGB24
        )
    {
        return Ok(None);
    }
    let orientation = dec
        .exif_data()
        .and_then(image::metadata::Orientation::from_exif_chunk)
        .unwrap_or(image::metadata::Orientation::NoTransforms);
    let (nw, nh) = target_size(w, h, orientation, opts)?;
    if info.coding_process == jpeg_decoder::CodingProcess::DctProgressive {
        // Progressive scans keep every coefficient of the full-size image (2 bytes a sample).
        let channels: u64 = if info.pixel_format == jpeg_decoder::PixelFormat::L8 {
            1
        } else {
            3
        };
        if w as u64 * h as u64 * channels * 2 > MAX_WHOLE_DECODE_BYTES {
            return Err(format!(
                "the progressive JPEG is {w}x{h} pixels, too large to decode here (at most \
                 {} MiB of coefficients); save it as a baseline JPEG or PNG, or downscale it",
                MAX_WHOLE_DECODE_BYTES >> 20
            ));
        }
    }
    let (sw, sh) = match dec.scale(
        nw.min(u16::MAX as u32) as u16,
        nh.min(u16::MAX as u32) as u16,
    ) {
        Ok((sw, sh)) => (u32::from(sw), u32::from(sh)),
        Err(_) => return Ok(None),
    };
    dec.set_max_decoding_buffer_size(MAX_ALLOC as usize);
    let pixels = match dec.decode() {
        Ok(p) => p,
        Err(jpeg_decoder::Error::Io(io)) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            return Err("the JPEG data is truncated".into())
        }
        Err(jpeg_decoder::Error::Format(m)) => return Err(format!("corrupt JPEG data ({m})")),
        // Unsupported features: the whole decode may still read it.
        Err(_) => return Ok(None),
    };
    let rgb: Vec<u8> = if info.pixel_format == jpeg_decoder::PixelFormat::L8 {
        pixels.iter().flat_map(|&g| [g, g, g]).collect()
    } else {
        pixels
    };
    let scaled = RgbImage::from_raw(sw, sh, rgb).ok_or("corrupt JPEG data (short output)")?;
    let rgb = if (sw, sh) == (nw, nh) {
        scaled
    } else {
        area_downscale(&scaled, nw, nh)
    };
    Ok(Some(Decoded {
        rgb,
        width: w,
        height: h,
        orientation,
    }))
}

/// The whole image through the `image` crate, refusing decoded buffers above
/// [`MAX_WHOLE_DECODE_BYTES`], then downscaled when it exceeds `fit_within`.
fn decode_whole(bytes: &[u8], kind: ImageKind, opts: &DecodeOptions) -> Result<Decoded, String> {
    let mut reader = ImageReader::with_format(Cursor::new(bytes), kind.format());
    let mut limits = Limits::default();
    limits.max_image_width = Some(MAX_SIDE);
    limits.max_image_height = Some(MAX_SIDE);
    limits.max_alloc = Some(MAX_ALLOC);
    reader.limits(limits);
    let mut decoder = reader.into_decoder().map_err(|e| decode_reason(kind, e))?;
    let (w, h) = decoder.dimensions();
    // A missing or unreadable orientation tag means "as stored", like every viewer does.
    let orientation = decoder
        .orientation()
        .unwrap_or(image::metadata::Orientation::NoTransforms);
    let (nw, nh) = target_size(w, h, orientation, opts)?;
    let decoded_bytes = decoder.total_bytes();
    if decoded_bytes > MAX_WHOLE_DECODE_BYTES {
        return Err(format!(
            "the {} image is {w}x{h} pixels, too large to decode in one piece here (at most {} \
             MiB decoded); save it as a baseline JPEG or a non-interlaced PNG, which are read at \
             reduced size, or downscale it",
            kind.name(),
            MAX_WHOLE_DECODE_BYTES >> 20
        ));
    }
    let img = DynamicImage::from_decoder(decoder).map_err(|e| decode_reason(kind, e))?;
    let rgb = to_rgb_on_black(img);
    let rgb = if (nw, nh) == (w, h) {
        rgb
    } else {
        area_downscale(&rgb, nw, nh)
    };
    Ok(Decoded {
        rgb,
        width: w,
        height: h,
        orientation,
    })
}

fn swaps_sides(o: image::metadata::Orientation) -> bool {
    use image::metadata::Orientation::*;
    matches!(o, Rotate90 | Rotate270 | Rotate90FlipH | Rotate270FlipH)
}

fn check_size(w: u32, h: u32) -> Result<(), String> {
    if w == 0 || h == 0 {
        return Err(format!("the image header says {w}x{h} pixels (empty)"));
    }
    if w > MAX_SIDE || h > MAX_SIDE || w as u64 * h as u64 > MAX_PIXELS {
        return Err(format!(
            "the image is {w}x{h} pixels, too large: this tool accepts at most {MAX_SIDE} px per \
             side and {} MP; downscale it first",
            MAX_PIXELS / 1_000_000
        ));
    }
    Ok(())
}

fn unknown_format_reason(bytes: &[u8]) -> String {
    if bytes.len() >= 12 && &bytes[4..8] == b"ftyp" {
        let brand = String::from_utf8_lossy(&bytes[8..12]).into_owned();
        if ["heic", "heix", "mif1", "msf1", "heim", "heis", "avif"].contains(&brand.as_str()) {
            return format!(
                "a HEIF/AVIF photo (brand '{brand}'), which this tool cannot decode; convert it to \
                 JPEG or PNG first"
            );
        }
        return format!("an ISO media file (brand '{brand}'), not an image");
    }
    let head: Vec<String> = bytes.iter().take(8).map(|b| format!("{b:02x}")).collect();
    format!(
        "not an image this tool reads (PNG, JPEG, WebP or BMP); it starts with bytes {}",
        head.join(" ")
    )
}

fn decode_reason(kind: ImageKind, e: image::ImageError) -> String {
    match e {
        image::ImageError::Limits(_) => format!(
            "the {} image is too large to decode (more than {MAX_SIDE} px per side or {} MiB)",
            kind.name(),
            MAX_ALLOC >> 20
        ),
        image::ImageError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            format!("the {} data is truncated", kind.name())
        }
        other => format!("corrupt {} data ({other})", kind.name()),
    }
}

/// Any pixel type to 8-bit RGB; transparent pixels are composited onto black, the background the
/// model was trained on.
fn to_rgb_on_black(img: DynamicImage) -> RgbImage {
    match img {
        DynamicImage::ImageRgb8(rgb) => rgb,
        img if img.color().has_alpha() => {
            let rgba = img.into_rgba8();
            let (w, h) = rgba.dimensions();
            let mut out = RgbImage::new(w, h);
            for (o, p) in out.pixels_mut().zip(rgba.pixels()) {
                for c in 0..3 {
                    o.0[c] = on_black(p.0[c], p.0[3]);
                }
            }
            out
        }
        img => img.into_rgb8(),
    }
}

/// Exact area-average downscale (each output pixel is the mean of the source area it covers,
/// fractional pixels weighted by their coverage), see [`AreaDownscaler`].
pub fn area_downscale(src: &RgbImage, nw: u32, nh: u32) -> RgbImage {
    let (w, h) = src.dimensions();
    let mut d = AreaDownscaler::new(w, h, nw, nh);
    for line in src.as_raw().chunks_exact((w as usize * 3).max(1)) {
        d.push_row(line);
    }
    d.finish()
}

/// The area-average downscale fed one source row at a time (RGB u8), so the source never has to
/// exist as a whole. A source row touches at most two output rows and rows arrive in order, so
/// only two output rows are accumulated (in f32) at a time; finished rows are rounded into the
/// output as they complete.
pub struct AreaDownscaler {
    hx: Vec<[Option<(usize, f32)>; 2]>,
    hy: Vec<[Option<(usize, f32)>; 2]>,
    nw: usize,
    nh: usize,
    /// Output rows `base` and `base + 1`.
    acc: Vec<f32>,
    base: usize,
    row: Vec<f32>,
    out: Vec<u8>,
    y: usize,
}

impl AreaDownscaler {
    /// From `w` x `h` to `nw` x `nh` (each at least 1 and at most the source's).
    pub fn new(w: u32, h: u32, nw: u32, nh: u32) -> Self {
        let (w, h) = (w.max(1) as usize, h.max(1) as usize);
        let (nw, nh) = ((nw.max(1) as usize).min(w), (nh.max(1) as usize).min(h));
        AreaDownscaler {
            hx: coverage(w, nw),
            hy: coverage(h, nh),
            nw,
            nh,
            acc: vec![0f32; 2 * nw * 3],
            base: 0,
            row: vec![0f32; nw * 3],
            out: Vec::with_capacity(nw * nh * 3),
            y: 0,
        }
    }

    /// Rounds output row `base` into the output and moves the window down one row.
    fn flush_row(&mut self) {
        let n = self.nw * 3;
        self.out.extend(
            self.acc[..n]
                .iter()
                .map(|v| v.round().clamp(0.0, 255.0) as u8),
        );
        self.acc.copy_within(n.., 0);
        self.acc[n..].iter_mut().for_each(|v| *v = 0.0);
        self.base += 1;
    }

    /// Adds the next source row (`w * 3` bytes); rows beyond `h` are ignored.
    pub fn push_row(&mut self, line: &[u8]) {
        let Some(ys) = self.hy.get(self.y).copied() else {
            return;
        };
        self.y += 1;
        self.row.iter_mut().for_each(|v| *v = 0.0);
        for (xs, px) in self.hx.iter().zip(line.chunks_exact(3)) {
            for &(ox, wx) in xs.iter().flatten() {
                for (acc, &v) in self.row[ox * 3..ox * 3 + 3].iter_mut().zip(px) {
                    *acc += wx * v as f32;
                }
            }
        }
        let n = self.nw * 3;
        for &(oy, wy) in ys.iter().flatten() {
            while oy >= self.base + 2 {
                self.flush_row();
            }
            let at = (oy - self.base) * n;
            for (d, r) in self.acc[at..at + n].iter_mut().zip(&self.row) {
                *d += wy * r;
            }
        }
    }

    pub fn finish(mut self) -> RgbImage {
        while self.base < self.nh {
            self.flush_row();
        }
        RgbImage::from_raw(self.nw as u32, self.nh as u32, self.out).expect("buffer sized nw*nh*3")
    }
}

/// For each of `n` source pixels, the (at most two) output pixels of `m` it overlaps and the
/// weight (overlap / output pixel width in source pixels), for `m <= n`.
fn coverage(n: usize, m: usize) -> Vec<[Option<(usize, f32)>; 2]> {
    let step = n as f64 / m as f64;
    (0..n)
        .map(|i| {
            let (a, b) = (i as f64, i as f64 + 1.0);
            let o = ((a / step) as usize).min(m - 1);
            let end = (o as f64 + 1.0) * step;
            if b <= end + 1e-9 || o + 1 >= m {
                [Some((o, (1.0 / step) as f32)), None]
            } else {
                let first = end - a;
                [
                    Some((o, (first / step) as f32)),
                    Some((o + 1, ((b - end) / step) as f32)),
                ]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png_bytes(img: &RgbImage) -> Vec<u8> {
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Png)
            .unwrap();
        out
    }

    fn gradient(w: u32, h: u32) -> RgbImage {
        RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, (x ^ y) as u8]))
    }

    #[test]
    fn png_named_jpg_decodes_by_content() {
        let img = gradient(20, 10);
        let d = decode_image(&png_bytes(&img), "photo.jpg", &DecodeOptions::default()).unwrap();
        assert_eq!(d.kind, ImageKind::Png);
        assert_eq!(d.rgb, img);
        assert_eq!((d.original_width, d.original_height), (20, 10));
    }

    #[test]
    fn bad_inputs_are_clear_errors() {
        let opts = DecodeOptions::default();
        let e = decode_image(b"", "a.jpg", &opts).unwrap_err().to_string();
        assert!(e.contains("empty"), "{e}");
        let e = decode_image(b"hello world, not a picture", "a.jpg", &opts)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("a.jpg: not an image"), "{e}");
        let full = png_bytes(&gradient(64, 64));
        let e = decode_image(&full[..full.len() / 2], "t.png", &opts)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("t.png: "), "{e}");
        let heic = b"\0\0\0\x18ftypheic\0\0\0\0mif1heic";
        let e = decode_image(heic, "p.heic", &opts).unwrap_err().to_string();
        assert!(e.contains("HEIF"), "{e}");
        let e = decode_image(
            &png_bytes(&gradient(1, 1)),
            "one.png",
            &DecodeOptions {
                min_side: 16,
                fit_within: None,
            },
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("1x1") && e.contains("16x16"), "{e}");
    }

    fn jpeg_bytes(img: &RgbImage) -> Vec<u8> {
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90)
            .encode_image(img)
            .unwrap();
        out
    }

    /// A baseline JPEG whose header states a size its data cannot hold is refused before
    /// decoding (the decoders would fill the missing blocks, as slow as a real photo that size).
    #[test]
    fn a_jpeg_too_short_for_its_size_is_truncated() {
        let small = jpeg_bytes(&gradient(64, 48));
        let sof = small
            .windows(2)
            .position(|w| w == [0xff, 0xc0])
            .expect("a baseline SOF0");
        let mut big = small.clone();
        big[sof + 5..sof + 7].copy_from_slice(&6169u16.to_be_bytes());
        big[sof + 7..sof + 9].copy_from_slice(&6693u16.to_be_bytes());
        for fit in [None, Some(2048)] {
            let opts = DecodeOptions {
                min_side: 1,
                fit_within: fit,
            };
            assert!(decode_image(&small, "s.jpg", &opts).is_ok());
            let e = decode_image(&big, "big.jpg", &opts)
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with("big.jpg: the JPEG data is truncated: a 6693x6169 image needs"),
                "{e}"
            );
        }
        // The case AFL++ saved as a hang (688 bytes stating 6693x6169; 5 s to decode before).
        let hang = std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("tests/data/fuzz/afl_hang_tiny_jpeg_6693x6169.jpg"),
        )
        .unwrap();
        let opts = DecodeOptions {
            min_side: 1,
            fit_within: Some(2048),
        };
        let e = decode_image(&hang, "hang.jpg", &opts)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("truncated") && e.contains("needs at least"),
            "{e}"
        );
        // The second: a decoy arithmetic-coded frame header before a 784x6080 baseline one (742
        // bytes, 0.2 s, saved as a hang on a loaded machine).
        let decoy = std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("tests/data/fuzz/afl_slow_jpeg_decoy_sof.jpg"),
        )
        .unwrap();
        let e = decode_image(&decoy, "decoy.jpg", &opts)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("784x6080") && e.contains("needs at least"),
            "{e}"
        );
        // A flat image, the most compressible real data, is not mistaken for a short one.
        let flat = jpeg_bytes(&RgbImage::from_pixel(2048, 1536, image::Rgb([90, 90, 90])));
        let d = decode_image(&flat, "flat.jpg", &DecodeOptions::default()).unwrap();
        assert_eq!(d.rgb.dimensions(), (2048, 1536));
    }

    /// PNG's chunk checksum (so a hand-edited header still parses).
    fn crc32(bytes: &[u8]) -> u32 {
        let mut c = !0u32;
        for &b in bytes {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xedb8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }

    #[test]
    fn huge_header_is_refused_before_allocation() {
        // A PNG header claiming 60000x60000 followed by nothing.
        let mut png = png_bytes(&gradient(2, 2));
        png[16..20].copy_from_slice(&60000u32.to_be_bytes());
        png[20..24].copy_from_slice(&60000u32.to_be_bytes());
        let crc = crc32(&png[12..29]);
        png[29..33].copy_from_slice(&crc.to_be_bytes());
        let e = decode_image(&png, "big.png", &DecodeOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("60000x60000") && e.contains("too large"), "{e}");
        // A BMP header claiming 16000x9000 (432 MB of RGB), which is not decoded row by row.
        let mut bmp = b"BM".to_vec();
        bmp.extend(70u32.to_le_bytes()); // file size (unchecked)
        bmp.extend([0; 4]);
        bmp.extend(54u32.to_le_bytes()); // pixel data offset
        bmp.extend(40u32.to_le_bytes()); // BITMAPINFOHEADER
        bmp.extend(16000i32.to_le_bytes());
        bmp.extend(9000i32.to_le_bytes());
        bmp.extend(1u16.to_le_bytes());
        bmp.extend(24u16.to_le_bytes());
        bmp.extend([0; 24]);
        bmp.extend([0; 16]);
        let e = decode_image(&bmp, "big.bmp", &DecodeOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("too large to decode in one piece"), "{e}");
    }

    #[test]
    fn area_downscale_averages_exactly() {
        // 4x2 -> 2x1: each output is the mean of a 2x2 block.
        let src = RgbImage::from_raw(
            4,
            2,
            vec![
                0, 0, 0, 10, 10, 10, 100, 0, 0, 200, 0, 0, //
                20, 20, 20, 30, 30, 30, 0, 50, 0, 0, 50, 0,
            ],
        )
        .unwrap();
        let out = area_downscale(&src, 2, 1);
        assert_eq!(out.as_raw(), &vec![15, 15, 15, 75, 25, 0]);
        // A constant image stays constant at fractional ratios.
        let flat = RgbImage::from_pixel(37, 23, image::Rgb([77, 128, 200]));
        let out = area_downscale(&flat, 10, 7);
        assert!(out.pixels().all(|p| p.0 == [77, 128, 200]));
    }

    #[test]
    fn fit_within_downscales_and_reports_scale() {
        let img = gradient(200, 100);
        let d = decode_image(
            &png_bytes(&img),
            "x.png",
            &DecodeOptions {
                min_side: 1,
                fit_within: Some(50),
            },
        )
        .unwrap();
        assert_eq!(d.rgb.dimensions(), (50, 25));
        assert_eq!((d.original_width, d.original_height), (200, 100));
        assert!((d.scale_to_original - 4.0).abs() < 1e-12);
    }

    #[test]
    fn exif_orientation_is_applied() {
        // A 4x2 JPEG with an APP1 Exif segment saying "rotate 90 clockwise" (orientation 6).
        let img = RgbImage::from_fn(4, 2, |x, _| {
            if x < 2 {
                image::Rgb([255, 255, 255])
            } else {
                image::Rgb([0, 0, 0])
            }
        });
        let mut jpg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpg, 100)
            .encode_image(&img)
            .unwrap();
        let tiff: Vec<u8> = [
            &b"MM\0\x2a\0\0\0\x08"[..],
            &[0, 1],
            &[0x01, 0x12, 0, 3, 0, 0, 0, 1, 0, 6, 0, 0],
            &[0, 0, 0, 0],
        ]
        .concat();
        let mut app1 = vec![0xff, 0xe1];
        let len = (2 + 6 + tiff.len()) as u16;
        app1.extend_from_slice(&len.to_be_bytes());
        app1.extend_from_slice(b"Exif\0\0");
        app1.extend_from_slice(&tiff);
        let with_exif: Vec<u8> = [&jpg[..2], &app1[..], &jpg[2..]].concat();
        let d = decode_image(&with_exif, "rot.jpg", &DecodeOptions::default()).unwrap();
        assert_eq!(d.orientation, image::metadata::Orientation::Rotate90);
        assert_eq!(d.rgb.dimensions(), (2, 4));
        assert_eq!((d.original_width, d.original_height), (2, 4));
        // Rotating 90 degrees clockwise puts the left (white) half on top.
        assert!(
            d.rgb.get_pixel(0, 0).0[0] > 200,
            "{:?}",
            d.rgb.get_pixel(0, 0)
        );
        assert!(
            d.rgb.get_pixel(0, 3).0[0] < 60,
            "{:?}",
            d.rgb.get_pixel(0, 3)
        );
    }

    #[test]
    fn alpha_is_composited_on_black() {
        let rgba =
            image::RgbaImage::from_raw(2, 1, vec![200, 100, 50, 255, 200, 100, 50, 0]).unwrap();
        let mut bytes = Vec::new();
        rgba.write_to(&mut Cursor::new(&mut bytes), ImageFormat::Png)
            .unwrap();
        let d = decode_image(&bytes, "a.png", &DecodeOptions::default()).unwrap();
        assert_eq!(d.rgb.as_raw(), &vec![200, 100, 50, 0, 0, 0]);
    }
}
