//! What every custom op here needs from candle's CPU storage.

use candle_core::{bail, Layout, Result};

/// The elements of a contiguous operand; an error naming the op and the operand otherwise.
pub(crate) fn contiguous<'a, T>(
    data: &'a [T],
    l: &Layout,
    op: &str,
    what: &str,
) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => bail!("{op}: {what} must be contiguous"),
    }
}
