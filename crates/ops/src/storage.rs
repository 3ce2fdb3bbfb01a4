//! What every custom op here needs from candle's CPU storage.

use candle_core::backend::BackendStorage;
use candle_core::{bail, CpuStorage, Layout, Result};

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

/// [`contiguous`] for an operand that must be f32.
pub(crate) fn contiguous_f32<'a>(
    s: &'a CpuStorage,
    l: &Layout,
    op: &str,
    what: &str,
) -> Result<&'a [f32]> {
    match s {
        CpuStorage::F32(data) => contiguous(data, l, op, what),
        other => bail!("{op}: {what} must be f32, got {:?}", other.dtype()),
    }
}
