//! The visible "AI-generated" label: a 5x7 bitmap font (our own), scaled by whole pixels with
//! the frame, light text on a dark translucent box in the bottom-right corner.

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

fn glyph(c: char) -> &'static [u8; GLYPH_H] {
    GLYPHS
        .iter()
        .find(|(g, _)| *g == c)
        .map(|(_, rows)| rows)
        .unwrap_or(&UNKNOWN)
}

/// Where the label goes: font scale, lines (right-aligned), and the box in frame pixels.
struct Layout {
    scale: usize,
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
    let fits = |s: usize, lines: &[Vec<char>]| {
        let longest = lines.iter().map(Vec::len).max().unwrap_or(0);
        text_width(longest) * s + 2 * (PAD + MARGIN) * s <= width
            && (lines.len() * LINE - 1) * s + 2 * (PAD + MARGIN) * s <= height
    };
    let one_line = vec![chars.clone()];
    let mut scale = (width.min(height) / PIXELS_PER_SCALE).max(1);
    while scale > 1 && !fits(scale, &one_line) {
        scale -= 1;
    }
    let lines = if fits(scale, &one_line) {
        one_line
    } else {
        // Too wide even at one pixel per font pixel (a 64-pixel thumbnail): break the line.
        let room = width.saturating_sub(2 * (PAD + MARGIN)) + 1;
        wrap(&chars, (room / ADVANCE).max(1))
    };
    let longest = lines.iter().map(Vec::len).max().unwrap_or(0);
    let box_w = (text_width(longest) + 2 * PAD) * scale;
    let box_h = (lines.len() * LINE - 1 + 2 * PAD) * scale;
    let x1 = width.saturating_sub(MARGIN * scale);
    let y1 = height.saturating_sub(MARGIN * scale);
    Some(Layout {
        scale,
        x0: x1.saturating_sub(box_w),
        y0: y1.saturating_sub(box_h),
        x1,
        y1,
        lines,
    })
}

/// The box [`draw_watermark`] darkens, as `[x0, y0, x1, y1]` (exclusive ends), or `None` when
/// nothing would be drawn. Every pixel the watermark changes lies inside it.
pub fn watermark_rect(width: usize, height: usize, text: &str) -> Option<[usize; 4]> {
    layout(width, height, text).map(|l| [l.x0, l.y0, l.x1, l.y1])
}

/// Draws `text` (ASCII; unknown characters as a box) in the bottom-right corner of an RGB u8 HWC
/// frame: light letters on a dark translucent box, scaled by whole pixels with the frame size and
/// broken into lines when it does not fit (at 64 pixels wide "AI-generated" takes two lines).
/// Does nothing when `rgb` is not `width * height * 3` long.
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
                            let (x, y) = (px + dx, py + dy);
                            // Only inside the box (clipped labels on tiny frames).
                            if x < l.x0 as isize
                                || y < l.y0 as isize
                                || x >= l.x1 as isize
                                || y >= l.y1 as isize
                            {
                                continue;
                            }
                            let o = (y as usize * width + x as usize) * 3;
                            rgb[o..o + 3].copy_from_slice(&TEXT_RGB);
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
    fn label_fits_from_64_to_1024() {
        for (w, h, lines, scale) in [
            (64, 64, 2, 1),
            (96, 64, 1, 1),
            (512, 512, 1, 2),
            (1024, 1024, 1, 5),
            (1024, 512, 1, 2),
        ] {
            let l = layout(w, h, WATERMARK_TEXT).unwrap();
            assert_eq!((l.lines.len(), l.scale), (lines, scale), "{w}x{h}");
            assert!(
                l.x0 > 0 && l.y0 > 0 && l.x1 < w && l.y1 < h,
                "{w}x{h}: box clipped"
            );
            // Text pixels exist on every line (nothing was clipped away).
            let art = ascii(w, h, WATERMARK_TEXT);
            assert!(art.lines().count() >= 7 * scale * lines, "{w}x{h}:\n{art}");
        }
        println!("{}", ascii(64, 64, WATERMARK_TEXT));
        println!("{}", ascii(96, 64, WATERMARK_TEXT));
    }
}
