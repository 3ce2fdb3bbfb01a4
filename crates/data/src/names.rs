//! Frame names `<video>_<frame>` (spec section 10) and their natural order.
//!
//! The video part may itself contain underscores, so a name splits at its LAST underscore; the
//! frame part is a number when it is all ASCII digits. Names sort by video (naturally: digit
//! runs compare as numbers, so `id9` < `id10`), then by frame number, then by the raw text, so
//! `vid_2` < `vid_10` and distinct spellings (`vid_02`, `vid_2`) still have a fixed order.

use std::cmp::Ordering;
use std::collections::BTreeMap;

/// `(video, frame number)`; a name without `_<digits>` at its end is all video.
pub fn split_frame_name(name: &str) -> (&str, Option<u64>) {
    match name.rfind('_') {
        Some(at) => {
            let (video, frame) = (&name[..at], &name[at + 1..]);
            if !frame.is_empty() && frame.bytes().all(|b| b.is_ascii_digit()) {
                // Absurdly long digit runs saturate instead of failing; the raw text
                // tie-break still orders them.
                let n = frame.parse::<u64>().unwrap_or(u64::MAX);
                (video, Some(n))
            } else {
                (name, None)
            }
        }
        None => (name, None),
    }
}

/// The video a frame belongs to (the whole name when it has no `_<digits>` suffix).
pub fn video_of(name: &str) -> &str {
    split_frame_name(name).0
}

/// Natural comparison of two strings: runs of ASCII digits compare by value (leading zeros
/// ignored, then shorter runs first), everything else byte by byte.
pub fn natural_str_cmp(a: &str, b: &str) -> Ordering {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i].is_ascii_digit() && b[j].is_ascii_digit() {
            let si = i;
            while i < a.len() && a[i].is_ascii_digit() {
                i += 1;
            }
            let sj = j;
            while j < b.len() && b[j].is_ascii_digit() {
                j += 1;
            }
            let da = trim_zeros(&a[si..i]);
            let db = trim_zeros(&b[sj..j]);
            let ord = da.len().cmp(&db.len()).then_with(|| da.cmp(db));
            if ord != Ordering::Equal {
                return ord;
            }
        } else {
            let ord = a[i].cmp(&b[j]);
            if ord != Ordering::Equal {
                return ord;
            }
            i += 1;
            j += 1;
        }
    }
    (a.len() - i).cmp(&(b.len() - j))
}

fn trim_zeros(d: &[u8]) -> &[u8] {
    let start = d.iter().position(|&c| c != b'0').unwrap_or(d.len());
    &d[start..]
}

/// The order of frame names (see the module docs); a total order consistent with equality.
pub fn frame_name_cmp(a: &str, b: &str) -> Ordering {
    let (va, fa) = split_frame_name(a);
    let (vb, fb) = split_frame_name(b);
    natural_str_cmp(va, vb)
        .then_with(|| fa.cmp(&fb))
        .then_with(|| a.cmp(b))
}

/// Sorts frame names in natural order.
pub fn sort_frame_names<S: AsRef<str>>(names: &mut [S]) {
    names.sort_by(|a, b| frame_name_cmp(a.as_ref(), b.as_ref()));
}

/// Frames grouped by video, each video's frames in natural order.
pub fn group_by_video<'a>(
    names: impl IntoIterator<Item = &'a str>,
) -> BTreeMap<String, Vec<String>> {
    let mut out: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for name in names {
        out.entry(video_of(name).to_owned())
            .or_default()
            .push(name.to_owned());
    }
    for frames in out.values_mut() {
        sort_frame_names(frames);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splits_at_the_last_underscore() {
        assert_eq!(split_frame_name("vid_10"), ("vid", Some(10)));
        assert_eq!(split_frame_name("id_01_clip_007"), ("id_01_clip", Some(7)));
        assert_eq!(split_frame_name("noframe"), ("noframe", None));
        assert_eq!(split_frame_name("vid_x"), ("vid_x", None));
        assert_eq!(split_frame_name("vid_"), ("vid_", None));
        assert_eq!(split_frame_name("_5"), ("", Some(5)));
        assert_eq!(
            split_frame_name("v_99999999999999999999999"),
            ("v", Some(u64::MAX))
        );
    }

    #[test]
    fn natural_order() {
        let mut names = vec![
            "vid_10", "vid_2", "vid_1", "a_b_3", "vid_02", "id10_0", "id9_5", "a_b_20", "a_b_x",
            "vid_b_0",
        ];
        sort_frame_names(&mut names);
        assert_eq!(
            names,
            [
                "a_b_3", "a_b_20", "a_b_x", "id9_5", "id10_0", "vid_1", "vid_02", "vid_2",
                "vid_10", "vid_b_0"
            ]
        );
    }

    #[test]
    fn order_is_total_and_antisymmetric() {
        let names = [
            "a", "a_1", "a_01", "a_b", "a_b_1", "a0", "a00", "a_", "_1", "", "9", "09", "a_1_2",
        ];
        for x in names {
            assert_eq!(frame_name_cmp(x, x), Ordering::Equal);
            for y in names {
                let xy = frame_name_cmp(x, y);
                assert_eq!(xy, frame_name_cmp(y, x).reverse(), "{x:?} vs {y:?}");
                assert_eq!(xy == Ordering::Equal, x == y, "{x:?} vs {y:?}");
                for z in names {
                    if xy == Ordering::Less && frame_name_cmp(y, z) == Ordering::Less {
                        assert_eq!(frame_name_cmp(x, z), Ordering::Less, "{x} {y} {z}");
                    }
                }
            }
        }
    }

    #[test]
    fn groups_by_video() {
        let g = group_by_video(["s_a_10", "s_a_2", "s_b_0", "lone"]);
        assert_eq!(g["s_a"], ["s_a_2", "s_a_10"]);
        assert_eq!(g["s_b"], ["s_b_0"]);
        assert_eq!(g["lone"], ["lone"]);
    }
}
