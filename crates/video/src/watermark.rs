//! The visible "AI-generated" label: light text on a dark translucent box in the bottom-right
//! corner, below and beside the face, never more than [`MAX_AREA_FRACTION`] of the frame.
//!
//! Two bitmap fonts of our own: a 5x7 one (with descenders) scaled by whole pixels with the
//! frame, and for frames too small for it (below about 128 pixels) a 3x5 capitals font whose
//! one-line "AI-GENERATED" box is 46x7 pixels: 7.9% of a 64x64 thumbnail, still one line.

/// The label drawn on every frame unless watermarking is turned off.
pub const WATERMARK_TEXT: &str = "AI-generated";

const GLYPH_W: usize = 5;
/// 7 rows for capitals and digits, 2 more below the baseline for g, j, p, q, y.
const GLYPH_H: usize = 9;
const ADVANCE: usize = GLYPH_W + 1;
const LINE: usize = GLYPH_H + 1;
/// Font pixels of box padding around the text, and of margin between box and frame edge.
const PAD: usize = 2;
const MARGIN: usize = 2;
/// One font pixel per this many pixels of the shorter frame side (2 at 512, 5 at 1024), so the
/// label keeps roughly the same share of the frame.
const PIXELS_PER_SCALE: usize = 200;
/// The largest share of the frame the box may cover (the "small": at most ~8%).
pub const MAX_AREA_FRACTION: f64 = 0.08;
/// Padding and margin of the small font's box, in pixels.
const SMALL_PAD: usize = 1;
const SMALL_MARGIN: usize = 1;
/// Box darkening: the frame keeps (256 - BOX_ALPHA) / 256 of its brightness under the box.
const BOX_ALPHA: u32 = 160;
const TEXT_RGB: [u8; 3] = [245, 245, 245];

/// Rows top to bottom; bit 4 is the leftmost column.
#[rustfmt::skip]
const GLYPHS: &[(char, [u8; GLYPH_H])] = &[
    (' ', [0, 0, 0, 0, 0, 0, 0, 0, 0]),
    ('A', [0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001, 0, 0]),
    ('B', [0b11110, 0b10001, 0b10001, 0b11110, 0b10001, 0b10001, 0b11110, 0, 0]),
    ('C', [0b01110, 0b10001, 0b10000, 0b10000, 0b10000, 0b10001, 0b01110, 0, 0]),
    ('D', [0b11110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b11110, 0, 0]),
    ('E', [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b11111, 0, 0]),
    ('F', [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b10000, 0, 0]),
    ('G', [0b01110, 0b10001, 0b10000, 0b10111, 0b10001, 0b10001, 0b01111, 0, 0]),
    ('H', [0b10001, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001, 0, 0]),
    ('I', [0b01110, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0]),
    ('J', [0b00111, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100, 0, 0]),
    ('K', [0b10001, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0b10001, 0, 0]),
    ('L', [0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b11111, 0, 0]),
    ('M', [0b10001, 0b11011, 0b10101, 0b10101, 0b10001, 0b10001, 0b10001, 0, 0]),
    ('N', [0b10001, 0b10001, 0b11001, 0b10101, 0b10011, 0b10001, 0b10001, 0, 0]),
    ('O', [0b01110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110, 0, 0]),
    ('P', [0b11110, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000, 0b10000, 0, 0]),
    ('Q', [0b01110, 0b10001, 0b10001, 0b10001, 0b10101, 0b10010, 0b01101, 0, 0]),
    ('R', [0b11110, 0b10001, 0b10001, 0b11110, 0b10100, 0b10010, 0b10001, 0, 0]),
    ('S', [0b01111, 0b10000, 0b10000, 0b01110, 0b00001, 0b00001, 0b11110, 0, 0]),
    ('T', [0b11111, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0, 0]),
    ('U', [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110, 0, 0]),
    ('V', [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0, 0]),
    ('W', [0b10001, 0b10001, 0b10001, 0b10101, 0b10101, 0b10101, 0b01010, 0, 0]),
    ('X', [0b10001, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0b10001, 0, 0]),
    ('Y', [0b10001, 0b10001, 0b01010, 0b00100, 0b00100, 0b00100, 0b00100, 0, 0]),
    ('Z', [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b11111, 0, 0]),
    ('a', [0, 0, 0b01110, 0b00001, 0b01111, 0b10001, 0b01111, 0, 0]),
    ('b', [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b11110, 0, 0]),
    ('c', [0, 0, 0b01110, 0b10000, 0b10000, 0b10001, 0b01110, 0, 0]),
    ('d', [0b00001, 0b00001, 0b01101, 0b10011, 0b10001, 0b10001, 0b01111, 0, 0]),
    ('e', [0, 0, 0b01110, 0b10001, 0b11111, 0b10000, 0b01110, 0, 0]),
    ('f', [0b00110, 0b01001, 0b01000, 0b11100, 0b01000, 0b01000, 0b01000, 0, 0]),
    ('g', [0, 0, 0b01111, 0b10001, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110]),
    ('h', [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001, 0, 0]),
    ('i', [0b00100, 0, 0b01100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0]),
    ('j', [0b00010, 0, 0b00110, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100]),
    ('k', [0b10000, 0b10000, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0, 0]),
    ('l', [0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0]),
    ('m', [0, 0, 0b11010, 0b10101, 0b10101, 0b10001, 0b10001, 0, 0]),
    ('n', [0, 0, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001, 0, 0]),
    ('o', [0, 0, 0b01110, 0b10001, 0b10001, 0b10001, 0b01110, 0, 0]),
    ('p', [0, 0, 0b11110, 0b10001, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000]),
    ('q', [0, 0, 0b01111, 0b10001, 0b10001, 0b10001, 0b01111, 0b00001, 0b00001]),
    ('r', [0, 0, 0b10110, 0b11001, 0b10000, 0b10000, 0b10000, 0, 0]),
    ('s', [0, 0, 0b01111, 0b10000, 0b01110, 0b00001, 0b11110, 0, 0]),
    ('t', [0b01000, 0b01000, 0b11100, 0b01000, 0b01000, 0b01001, 0b00110, 0, 0]),
    ('u', [0, 0, 0b10001, 0b10001, 0b10001, 0b10011, 0b01101, 0, 0]),
    ('v', [0, 0, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0, 0]),
    ('w', [0, 0, 0b10001, 0b10001, 0b10101, 0b10101, 0b01010, 0, 0]),
    ('x', [0, 0, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0, 0]),
    ('y', [0, 0, 0b10001, 0b10001, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110]),
    ('z', [0, 0, 0b11111, 0b00010, 0b00100, 0b01000, 0b11111, 0, 0]),
    ('0', [0b01110, 0b10001, 0b10011, 0b10101, 0b11001, 0b10001, 0b01110, 0, 0]),
    ('1', [0b00100, 0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0]),
    ('2', [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b01000, 0b11111, 0, 0]),
    ('3', [0b11111, 0b00010, 0b00100, 0b00010, 0b00001, 0b10001, 0b01110, 0, 0]),
    ('4', [0b00010, 0b00110, 0b01010, 0b10010, 0b11111, 0b00010, 0b00010, 0, 0]),
    ('5', [0b11111, 0b10000, 0b11110, 0b00001, 0b00001, 0b10001, 0b01110, 0, 0]),
    ('6', [0b00110, 0b01000, 0b10000, 0b11110, 0b10001, 0b10001, 0b01110, 0, 0]),
    ('7', [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0, 0]),
    ('8', [0b01110, 0b10001, 0b10001, 0b01110, 0b10001, 0b10001, 0b01110, 0, 0]),
    ('9', [0b01110, 0b10001, 0b10001, 0b01111, 0b00001, 0b00010, 0b01100, 0, 0]),
    ('-', [0, 0, 0, 0b01110, 0, 0, 0, 0, 0]),
    ('.', [0, 0, 0, 0, 0, 0b01100, 0b01100, 0, 0]),
    (',', [0, 0, 0, 0, 0, 0b01100, 0b00100, 0b01000, 0]),
    (':', [0, 0b01100, 0b01100, 0, 0b01100, 0b01100, 0, 0, 0]),
    ('_', [0, 0, 0, 0, 0, 0, 0, 0, 0b11111]),
    ('/', [0b00001, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b10000, 0, 0]),
    ('(', [0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0b00100, 0b00010, 0, 0]),
    (')', [0b01000, 0b00100, 0b00010, 0b00010, 0b00010, 0b00100, 0b01000, 0, 0]),
    ('!', [0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0, 0b00100, 0, 0]),
    ('+', [0, 0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0, 0, 0]),
    ('=', [0, 0, 0b11111, 0, 0b11111, 0, 0, 0, 0]),
    ('%', [0b11000, 0b11001, 0b00010, 0b00100, 0b01000, 0b10011, 0b00011, 0, 0]),
    ('\'', [0b00100, 0b00100, 0b01000, 0, 0, 0, 0, 0, 0]),
];

/// Drawn for characters the font lacks, so they show up as missing rather than vanish.
const UNKNOWN: [u8; GLYPH_H] = [
    0b11111, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b11111, 0, 0,
];

/// The 3x5 capitals font for small frames: rows top to bottom, bit 2 the leftmost column, and
/// the glyph's width in columns (narrow glyphs keep the one-line label within 8% of 64x64).
const SMALL_H: usize = 5;
#[rustfmt::skip]
const SMALL_GLYPHS: &[(char, u8, [u8; SMALL_H])] = &[
    (' ', 2, [0, 0, 0, 0, 0]),
    ('A', 3, [0b010, 0b101, 0b111, 0b101, 0b101]),
    ('B', 3, [0b110, 0b101, 0b110, 0b101, 0b110]),
    ('C', 3, [0b011, 0b100, 0b100, 0b100, 0b011]),
    ('D', 3, [0b110, 0b101, 0b101, 0b101, 0b110]),
    ('E', 3, [0b111, 0b100, 0b110, 0b100, 0b111]),
    ('F', 3, [0b111, 0b100, 0b110, 0b100, 0b100]),
    ('G', 3, [0b011, 0b100, 0b101, 0b101, 0b011]),
    ('H', 3, [0b101, 0b101, 0b111, 0b101, 0b101]),
    ('I', 1, [0b1, 0b1, 0b1, 0b1, 0b1]),
    ('J', 3, [0b001, 0b001, 0b001, 0b101, 0b010]),
    ('K', 3, [0b101, 0b101, 0b110, 0b101, 0b101]),
    ('L', 3, [0b100, 0b100, 0b100, 0b100, 0b111]),
    ('M', 3, [0b101, 0b111, 0b111, 0b101, 0b101]),
    ('N', 3, [0b110, 0b101, 0b101, 0b101, 0b101]),
    ('O', 3, [0b010, 0b101, 0b101, 0b101, 0b010]),
    ('P', 3, [0b110, 0b101, 0b110, 0b100, 0b100]),
    ('Q', 3, [0b010, 0b101, 0b101, 0b110, 0b011]),
    ('R', 3, [0b110, 0b101, 0b110, 0b101, 0b101]),
    ('S', 3, [0b011, 0b100, 0b010, 0b001, 0b110]),
    ('T', 3, [0b111, 0b010, 0b010, 0b010, 0b010]),
    ('U', 3, [0b101, 0b101, 0b101, 0b101, 0b111]),
    ('V', 3, [0b101, 0b101, 0b101, 0b101, 0b010]),
    ('W', 3, [0b101, 0b101, 0b111, 0b111, 0b101]),
    ('X', 3, [0b101, 0b101, 0b010, 0b101, 0b101]),
    ('Y', 3, [0b101, 0b101, 0b010, 0b010, 0b010]),
    ('Z', 3, [0b111, 0b001, 0b010, 0b100, 0b111]),
    ('0', 3, [0b111, 0b101, 0b101, 0b101, 0b111]),
    ('1', 2, [0b01, 0b11, 0b01, 0b01, 0b01]),
    ('2', 3, [0b110, 0b001, 0b010, 0b100, 0b111]),
    ('3', 3, [0b110, 0b001, 0b010, 0b001, 0b110]),
    ('4', 3, [0b101, 0b101, 0b111, 0b001, 0b001]),
    ('5', 3, [0b111, 0b100, 0b110, 0b001, 0b110]),
    ('6', 3, [0b011, 0b100, 0b111, 0b101, 0b111]),
    ('7', 3, [0b111, 0b001, 0b010, 0b010, 0b010]),
    ('8', 3, [0b111, 0b101, 0b111, 0b101, 0b111]),
    ('9', 3, [0b111, 0b101, 0b111, 0b001, 0b110]),
    ('-', 2, [0, 0, 0b11, 0, 0]),
    ('.', 1, [0, 0, 0, 0, 0b1]),
];

/// A small glyph (lowercase drawn as capitals): width and rows.
fn small_glyph(c: char) -> (usize, [u8; SMALL_H]) {
    let c = c.to_ascii_uppercase();
    SMALL_GLYPHS
        .iter()
        .find(|(g, _, _)| *g == c)
        .map(|(_, w, rows)| (usize::from(*w), *rows))
        .unwrap_or((3, [0b111, 0b101, 0b101, 0b101, 0b111]))
}

fn small_text_width(line: &[char]) -> usize {
    line.iter()
        .map(|&c| small_glyph(c).0 + 1)
        .sum::<usize>()
        .saturating_sub(1)
}

fn glyph(c: char) -> &'static [u8; GLYPH_H] {
    GLYPHS
        .iter()
        .find(|(g, _)| *g == c)
        .map(|(_, rows)| rows)
        .unwrap_or(&UNKNOWN)
}

/// Where the label goes: font scale, lines (right-aligned), and the box in frame pixels.
struct Layout {
    /// Font pixels per frame pixel of the 5x7 font; 1 for the small font.
    scale: usize,
    /// The 3x5 capitals font (frames too small for the 5x7 one).
    small: bool,
    lines: Vec<Vec<char>>,
    /// Box corners, x0..x1 and y0..y1 (exclusive), clipped to the frame.
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

fn text_width(chars: usize) -> usize {
    (chars * ADVANCE).saturating_sub(1)
}

/// Greedy line breaks after '-' and at spaces, each line at most `max_chars` where possible.
fn wrap(text: &[char], max_chars: usize) -> Vec<Vec<char>> {
    // Words keep their trailing '-'; spaces separate words and are dropped at line breaks.
    let mut words: Vec<Vec<char>> = Vec::new();
    let mut cur = Vec::new();
    for &c in text {
        if c == ' ' {
            if !cur.is_empty() {
                words.push(std::mem::take(&mut cur));
            }
        } else {
            cur.push(c);
            if c == '-' {
                words.push(std::mem::take(&mut cur));
            }
        }
    }
    if !cur.is_empty() {
        words.push(cur);
    }
    let mut lines: Vec<Vec<char>> = Vec::new();
    let mut line: Vec<char> = Vec::new();
    for word in words {
        let joiner = usize::from(!line.is_empty() && line.last() != Some(&'-'));
        if !line.is_empty() && line.len() + joiner + word.len() > max_chars {
            lines.push(std::mem::take(&mut line));
        } else if joiner == 1 {
            line.push(' ');
        }
        line.extend(word);
    }
    if !line.is_empty() {
        lines.push(line);
    }
    lines
}

fn layout(width: usize, height: usize, text: &str) -> Option<Layout> {
    let chars: Vec<char> = text.chars().collect();
    if chars.iter().all(|&c| c == ' ') || width == 0 || height == 0 {
        return None;
    }
    let max_area = MAX_AREA_FRACTION * (width * height) as f64;
    let place = |box_w: usize, box_h: usize, margin: usize| {
        let x1 = width.saturating_sub(margin);
        let y1 = height.saturating_sub(margin);
        (x1.saturating_sub(box_w), y1.saturating_sub(box_h), x1, y1)
    };
    // The 5x7 font on one line, at the largest whole scale up to one font pixel per
    // PIXELS_PER_SCALE frame pixels that fits the frame and the area budget.
    let box_5x7 = |s: usize| {
        (
            (text_width(chars.len()) + 2 * PAD) * s,
            (GLYPH_H + 2 * PAD) * s,
        )
    };
    let mut scale = (width.min(height) / PIXELS_PER_SCALE).max(1);
    loop {
        let (bw, bh) = box_5x7(scale);
        let fits = bw + 2 * MARGIN * scale <= width && bh + 2 * MARGIN * scale <= height;
        if fits && (bw * bh) as f64 <= max_area {
            let (x0, y0, x1, y1) = place(bw, bh, MARGIN * scale);
            return Some(Layout {
                scale,
                small: false,
                lines: vec![chars],
                x0,
                y0,
                x1,
                y1,
            });
        }
        if scale == 1 {
            break;
        }
        scale -= 1;
    }
    // The 3x5 font: one pixel of padding, one of margin; on narrow frames broken into lines.
    let room = width.saturating_sub(2 * SMALL_PAD + 2 * SMALL_MARGIN);
    let lines = if small_text_width(&chars) <= room {
        vec![chars]
    } else {
        wrap(&chars, (room / 4).max(1))
    };
    let longest = lines.iter().map(|l| small_text_width(l)).max().unwrap_or(0);
    let bw = longest + 2 * SMALL_PAD;
    let bh = lines.len() * (SMALL_H + 1) - 1 + 2 * SMALL_PAD;
    let (x0, y0, x1, y1) = place(bw, bh, SMALL_MARGIN);
    Some(Layout {
        scale: 1,
        small: true,
        lines,
        x0,
        y0,
        x1,
        y1,
    })
}

/// The box [`draw_watermark`] darkens, as `[x0, y0, x1, y1]` (exclusive ends), or `None` when
/// nothing would be drawn. Every pixel the watermark changes lies inside it.
pub fn watermark_rect(width: usize, height: usize, text: &str) -> Option<[usize; 4]> {
    layout(width, height, text).map(|l| [l.x0, l.y0, l.x1, l.y1])
}

/// Draws `text` (ASCII; unknown characters as a box) in the bottom-right corner of an RGB u8 HWC
/// frame: light letters on a dark translucent box, scaled by whole pixels with the frame size,
/// within [`MAX_AREA_FRACTION`] of the frame (small frames get the 3x5 capitals font; "AI-GENERATED"
/// stays one line down to 64 pixels wide). Does nothing when `rgb` is not `width * height * 3`
/// long.
pub fn draw_watermark(rgb: &mut [u8], width: usize, height: usize, text: &str) {
    if width.checked_mul(height).and_then(|n| n.checked_mul(3)) != Some(rgb.len()) {
        return;
    }
    let Some(l) = layout(width, height, text) else {
        return;
    };
    for y in l.y0..l.y1 {
        for x in l.x0..l.x1 {
            let p = &mut rgb[(y * width + x) * 3..][..3];
            for c in p {
                *c = ((u32::from(*c) * (256 - BOX_ALPHA) + 128) >> 8) as u8;
            }
        }
    }
    let mut set = |x: isize, y: isize| {
        // Only inside the box (clipped labels on tiny frames).
        if x < l.x0 as isize || y < l.y0 as isize || x >= l.x1 as isize || y >= l.y1 as isize {
            return;
        }
        let o = (y as usize * width + x as usize) * 3;
        rgb[o..o + 3].copy_from_slice(&TEXT_RGB);
    };
    if l.small {
        let inner_right = (l.x1 - SMALL_PAD) as isize;
        for (li, line) in l.lines.iter().enumerate() {
            let mut x = inner_right - small_text_width(line) as isize;
            let y0 = (l.y0 + SMALL_PAD + li * (SMALL_H + 1)) as isize;
            for &ch in line {
                let (w, rows) = small_glyph(ch);
                for (gy, &bits) in rows.iter().enumerate() {
                    for gx in 0..w {
                        if bits & (1 << (w - 1 - gx)) != 0 {
                            set(x + gx as isize, y0 + gy as isize);
                        }
                    }
                }
                x += w as isize + 1;
            }
        }
        return;
    }
    let s = l.scale;
    let inner_right = l.x1 - PAD * s;
    for (li, line) in l.lines.iter().enumerate() {
        let line_x0 = inner_right as isize - (text_width(line.len()) * s) as isize;
        let line_y0 = (l.y0 + PAD * s + li * LINE * s) as isize;
        for (ci, &ch) in line.iter().enumerate() {
            let rows = glyph(ch);
            for (gy, &bits) in rows.iter().enumerate() {
                for gx in 0..GLYPH_W {
                    if bits & (1 << (GLYPH_W - 1 - gx)) == 0 {
                        continue;
                    }
                    let px = line_x0 + ((ci * ADVANCE + gx) * s) as isize;
                    let py = line_y0 + (gy * s) as isize;
                    for dy in 0..s as isize {
                        for dx in 0..s as isize {
                            set(px + dx, py + dy);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Renders the label's text pixels as '#' to look at (`cargo test -- --nocapture`).
    fn ascii(width: usize, height: usize, text: &str) -> String {
        let mut rgb = vec![0u8; width * height * 3];
        draw_watermark(&mut rgb, width, height, text);
        let mut s = String::new();
        for y in 0..height {
            let row: String = (0..width)
                .map(|x| {
                    if rgb[(y * width + x) * 3] > 200 {
                        '#'
                    } else {
                        '.'
                    }
                })
                .collect();
            if row.contains('#') {
                s.push_str(&row);
                s.push('\n');
            }
        }
        s
    }

    #[test]
    fn every_glyph_is_distinct_and_five_wide() {
        for (i, (c, rows)) in GLYPHS.iter().enumerate() {
            assert!(rows.iter().all(|&r| r < 32), "glyph {c:?} wider than 5");
            for (d, other) in GLYPHS.iter().skip(i + 1) {
                assert!(
                    c == &' ' || rows != other,
                    "glyphs {c:?} and {d:?} are identical"
                );
            }
        }
    }

    #[test]
    fn wraps_at_hyphen_when_too_wide() {
        assert_eq!(
            wrap(&"AI-generated".chars().collect::<Vec<_>>(), 9),
            vec![
                "AI-".chars().collect::<Vec<_>>(),
                "generated".chars().collect()
            ]
        );
        assert_eq!(
            wrap(&"made by AI".chars().collect::<Vec<_>>(), 7),
            vec![
                "made by".chars().collect::<Vec<_>>(),
                "AI".chars().collect()
            ]
        );
    }

    #[test]
    fn label_is_small_legible_and_in_the_corner_from_64_to_1024() {
        let mut sizes: Vec<(usize, usize)> = (64..=1024).step_by(16).map(|s| (s, s)).collect();
        sizes.extend([(128, 64), (64, 128), (1024, 512), (96, 64), (2048, 1024)]);
        for (w, h) in sizes {
            let l = layout(w, h, WATERMARK_TEXT).unwrap();
            let area = (l.x1 - l.x0) * (l.y1 - l.y0);
            let frac = area as f64 / (w * h) as f64;
            // The small font's 46x7 box is 7.9% of 64x64.
            assert!(
                frac <= MAX_AREA_FRACTION + 0.001,
                "{w}x{h}: box covers {:.1}%",
                100.0 * frac
            );
            assert_eq!(l.lines.len(), 1, "{w}x{h}: one line");
            assert!(
                l.x0 > 0 && l.y0 > 0 && l.x1 < w && l.y1 < h,
                "{w}x{h}: box clipped"
            );
            // Off the face: in the bottom eighth of the frame (the release crops put the chin
            // above it) and on the right.
            assert!(8 * l.y0 >= 7 * h - 8, "{w}x{h}: box starts at row {}", l.y0);
            assert!(2 * l.x1 > w, "{w}x{h}");
            // Every character drawn: the text's pixels span the box's text area.
            let art = ascii(w, h, WATERMARK_TEXT);
            let rows = if l.small { SMALL_H } else { 7 * l.scale };
            assert!(art.lines().count() >= rows, "{w}x{h}:\n{art}");
            // The 5x7 font whenever its 75x13 box fits the frame and the budget.
            let big_fits = 75 * 13 <= (w * h) * 8 / 100 && 79 <= w && 17 <= h;
            assert_eq!(l.small, !big_fits, "{w}x{h}");
        }
        println!("{}", ascii(64, 64, WATERMARK_TEXT));
        println!("{}", ascii(128, 128, WATERMARK_TEXT));
    }

    #[test]
    fn small_glyphs_are_distinct() {
        for (i, (c, w, rows)) in SMALL_GLYPHS.iter().enumerate() {
            assert!(
                rows.iter().all(|&r| r < (1 << w)),
                "glyph {c:?} wider than {w}"
            );
            for (d, w2, other) in SMALL_GLYPHS.iter().skip(i + 1) {
                assert!(
                    c == &' ' || (w, rows) != (w2, other),
                    "{c:?} and {d:?} are identical"
                );
            }
        }
        assert_eq!(
            small_text_width(&"AI-GENERATED".chars().collect::<Vec<_>>()),
            44
        );
    }
}
