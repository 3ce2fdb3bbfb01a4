//! Atomic output: every file (and the LMDB directory) is written under a temporary sibling name
//! (`gagavatar_splat::scene::temp_sibling`, the project's one naming scheme) and renamed into
//! place, so a crash never leaves a half-written dataset behind.

use std::io::Write;
use std::path::{Path, PathBuf};

pub use gagavatar_splat::scene::temp_sibling;

use crate::error::{io_err, Result};

/// Writes `bytes` to a temp file beside `path`, syncs it, then renames it over `path`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = temp_sibling(path);
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(io_err(path, "cannot write"))
}

/// Puts the finished directory `tmp` at `dir`. An existing `dir` is first moved to a second
/// temp name and deleted only after the new one is in place (a directory cannot be renamed
/// over a non-empty one); if the second rename fails the old one is moved back.
pub(crate) fn replace_dir(tmp: &Path, dir: &Path) -> Result<()> {
    if !dir.exists() {
        return std::fs::rename(tmp, dir)
            .map_err(io_err(dir, "cannot move the new directory into place"));
    }
    let old: PathBuf = {
        let mut name = temp_sibling(dir).into_os_string();
        name.push(".old");
        name.into()
    };
    let _ = std::fs::remove_dir_all(&old);
    std::fs::rename(dir, &old).map_err(io_err(dir, "cannot move the old directory aside"))?;
    if let Err(e) = std::fs::rename(tmp, dir) {
        let _ = std::fs::rename(&old, dir);
        return Err(io_err(dir, "cannot move the new directory into place")(e));
    }
    // The new data is in place; failing to delete the old copy loses nothing.
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}
