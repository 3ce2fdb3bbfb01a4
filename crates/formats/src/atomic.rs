//! Atomic output, the project's one mechanism: a file (or a directory) is written under a hidden
//! temporary sibling name and renamed into place when complete, so a crash or a kill never leaves
//! a half-written output at the real path (at worst a hidden `.NAME.tmpPID.N` beside it).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::FormatError;

/// A hidden temporary name beside `path` (same directory, so a rename replaces `path`
/// atomically). Unique per process and per call, so concurrent writers never share one.
pub fn temp_sibling(path: &Path) -> PathBuf {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    dir.join(format!(".{name}.tmp{}.{n}", std::process::id()))
}

/// Names a pause, in milliseconds, between a finished temporary output and its rename into
/// place. For kill tests only: with it, a `kill -9` lands inside the write on any machine
/// instead of racing a rename that takes microseconds. Unset (the default) means no pause.
pub const PAUSE_BEFORE_RENAME_ENV: &str = "GAGAVATAR_TEST_PAUSE_BEFORE_RENAME_MS";

/// Sleeps for [`PAUSE_BEFORE_RENAME_ENV`] milliseconds (read once; no pause when unset or not
/// a number). Every writer calls it just before renaming a finished temporary into place.
pub fn pause_before_rename() {
    use std::sync::OnceLock;
    static PAUSE: OnceLock<u64> = OnceLock::new();
    let ms = *PAUSE.get_or_init(|| {
        std::env::var(PAUSE_BEFORE_RENAME_ENV)
            .ok()
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(0)
    });
    if ms > 0 {
        std::thread::sleep(std::time::Duration::from_millis(ms));
    }
}

/// `write(tmp)` fills a temp sibling of `path` (see [`temp_sibling`]), which is then synced and
/// renamed over `path`. On any failure the temp file is removed and `path` is left as it was.
pub fn write_via_temp<E>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_err: impl Fn(std::io::Error) -> E,
) -> Result<(), E> {
    let tmp = temp_sibling(path);
    let result = write(&tmp)
        .and_then(|()| {
            std::fs::File::open(&tmp)
                .and_then(|f| f.sync_all())
                .map_err(&io_err)
        })
        .and_then(|()| {
            pause_before_rename();
            std::fs::rename(&tmp, path).map_err(&io_err)
        });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes `bytes` to a temp file beside `path`, syncs it, then renames it over `path`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FormatError> {
    write_via_temp(
        path,
        |tmp| std::fs::write(tmp, bytes).map_err(FormatError::io(path, "cannot write")),
        |e| FormatError::io(path, "cannot write")(e),
    )
}

/// Puts the finished directory `tmp` at `dir`. An existing `dir` is first moved to a second temp
/// name and deleted only after the new one is in place (a directory cannot be renamed over a
/// non-empty one); if the second rename fails the old one is moved back.
pub fn replace_dir(tmp: &Path, dir: &Path) -> std::io::Result<()> {
    pause_before_rename();
    // Writers of one folder at the same moment (two requests tracking the same photo into the
    // cache) can interleave the renames below; each collision is retried, and the folder of
    // the last writer stays.
    let mut collision = None;
    for _ in 0..RACE_RETRIES {
        match replace_once(tmp, dir) {
            Ok(()) => return Ok(()),
            Err(e) if collided(&e) => collision = Some(e),
            Err(e) => return Err(e),
        }
    }
    Err(collision.unwrap_or_else(|| std::io::Error::other("replacing the folder kept colliding")))
}

/// Attempts of [`replace_dir`] when another writer of the same folder gets in between.
const RACE_RETRIES: usize = 16;

/// The errors a concurrent writer of the same folder causes: it appeared (renaming onto a
/// non-empty folder) or vanished (moved away by the other writer) between our steps.
fn collided(e: &std::io::Error) -> bool {
    use std::io::ErrorKind;
    matches!(
        e.kind(),
        ErrorKind::NotFound | ErrorKind::AlreadyExists | ErrorKind::DirectoryNotEmpty
    )
}

fn replace_once(tmp: &Path, dir: &Path) -> std::io::Result<()> {
    if !tmp.is_dir() {
        // Not a collision: our own folder is missing.
        return Err(std::io::Error::other(format!("{} is gone", tmp.display())));
    }
    if !dir.exists() {
        return std::fs::rename(tmp, dir);
    }
    let mut old = temp_sibling(dir).into_os_string();
    old.push(".old");
    let old = PathBuf::from(old);
    std::fs::rename(dir, &old)?;
    if let Err(e) = std::fs::rename(tmp, dir) {
        // Put the old folder back; if another writer's folder took its place, that one stays.
        if std::fs::rename(&old, dir).is_err() {
            let _ = std::fs::remove_dir_all(&old);
        }
        return Err(e);
    }
    // The new data is in place; failing to delete the old copy loses nothing.
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn concurrent_writers_of_one_folder_all_succeed() {
        let root = std::env::temp_dir().join(format!("gagavatar-race-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        let dir = root.join("cached");
        let threads: Vec<_> = (0..8)
            .map(|i| {
                let dir = dir.clone();
                std::thread::spawn(move || {
                    for round in 0..20 {
                        let tmp = temp_sibling(&dir);
                        std::fs::create_dir_all(&tmp).unwrap();
                        std::fs::write(tmp.join("data"), format!("{i} {round}")).unwrap();
                        replace_dir(&tmp, &dir)
                            .unwrap_or_else(|e| panic!("writer {i}, round {round}: {e}"));
                    }
                })
            })
            .collect();
        for t in threads {
            t.join().unwrap();
        }
        // One complete folder, and nothing else left beside it.
        assert!(dir.join("data").is_file());
        let left: Vec<_> = std::fs::read_dir(&root)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(left, vec![std::ffi::OsString::from("cached")], "{left:?}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn write_atomic_replaces_and_leaves_no_temp() {
        let dir = std::env::temp_dir().join(format!("gagavatar-atomic-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("out.txt");
        write_atomic(&path, b"one").unwrap();
        write_atomic(&path, b"two").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"two");
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 1, "left behind: {names:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn failed_write_keeps_the_old_file() {
        let dir = std::env::temp_dir().join(format!("gagavatar-atomic2-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("keep.txt");
        std::fs::write(&path, b"old").unwrap();
        let r: Result<(), std::io::Error> = write_via_temp(
            &path,
            |tmp| {
                std::fs::write(tmp, b"partial")?;
                Err(std::io::Error::other("simulated failure"))
            },
            |e| e,
        );
        assert!(r.is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn temp_names_are_unique_and_hidden() {
        let a = temp_sibling(Path::new("x/out.mp4"));
        let b = temp_sibling(Path::new("x/out.mp4"));
        assert_ne!(a, b);
        let name = a.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with(".out.mp4.tmp"), "{name}");
        assert_eq!(a.parent(), Some(Path::new("x")));
    }
}
