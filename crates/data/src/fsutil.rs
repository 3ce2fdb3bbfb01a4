//! Atomic output: every file (and the LMDB directory) is written under a temporary sibling name
//! (`gagavatar_splat::scene::temp_sibling`, the project's one naming scheme) and renamed into
//! place, so a crash never leaves a half-written dataset behind.

use std::path::Path;

pub use gagavatar_splat::scene::temp_sibling;
use gagavatar_splat::scene::write_via_temp;

use crate::error::{io_err, Result};

/// Writes `bytes` to a temp file beside `path`, syncs it, then renames it over `path`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via_temp(
        path,
        |tmp| std::fs::write(tmp, bytes).map_err(io_err(path, "cannot write")),
        |e| io_err(path, "cannot write")(e),
    )
}

/// Puts the finished directory `tmp` at `dir`, replacing an existing one (see
/// [`gagavatar_splat::scene::replace_dir`]).
pub(crate) fn replace_dir(tmp: &Path, dir: &Path) -> Result<()> {
    gagavatar_splat::scene::replace_dir(tmp, dir)
        .map_err(io_err(dir, "cannot move the new directory into place"))
}
