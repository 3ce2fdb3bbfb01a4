//! A pure-Rust reader and writer of LMDB environments (the release's `img_lmdb/`), written from
//! the on-disk format of liblmdb 0.9 (data version 1, 64-bit builds):
//!
//! * Every page starts with a 16-byte header: page number (u64), a pad (u16), flags (u16:
//!   branch 0x01, leaf 0x02, overflow 0x04, meta 0x08), then either the free-space bounds
//!   `lower`, `upper` (u16 each; `(lower - 16) / 2` node offsets (u16) follow the header) or,
//!   on overflow pages, the page count (u32).
//! * Pages 0 and 1 are meta pages; the one with the larger transaction id is current. After the
//!   header: magic 0xBEEFC0DE (u32), version 1 (u32), map address (u64), map size (u64), two
//!   database records (free list, main) of 48 bytes, last used page (u64), txnid (u64). A
//!   database record: pad (u32; the free list's holds the page size), flags (u16), depth (u16),
//!   branch / leaf / overflow page counts, entries, root page (u64 each; all ones = empty).
//! * A node: `lo`, `hi`, `flags`, key size (u16 each), the key, then on leaves the value
//!   (`lo | hi << 16` bytes) or, with flag F_BIGDATA (0x01), the u64 number of the overflow page
//!   whose data follows its header; on branches the child page `lo | hi << 16 | flags << 32`.
//!   The first key of a branch page is not used (children cover `key_i <= k < key_{i+1}`).
//! * Keys sort bytewise (memcmp, then shorter first): Rust's `[u8]` order.
//!
//! The reader reads pages on demand with positioned reads (datasets are gigabytes), checks
//! every offset, size and page number against the page and the file, follows at most
//! `depth` levels, visits each page at most once when listing, and refuses what it does not
//! implement (duplicate-key databases, named sub-databases, integer keys) with an error.
//!
//! The writer builds a fresh environment bottom-up: values too large for a node (the same
//! limit liblmdb uses) go to overflow pages as they arrive, then the sorted leaves and branch
//! levels follow. Meta page 0 holds an empty database at txnid 0 and meta page 1 the data at
//! txnid 1, which is what liblmdb itself leaves after one commit into a new environment. Only
//! `data.mdb` is written: liblmdb creates `lock.mdb` on first open when the directory is
//! writable, and `lmdb.open(path, readonly=True, lock=False)` needs none.

use std::path::{Path, PathBuf};

use crate::atomic::{replace_dir, temp_sibling};
use crate::error::{FormatError, Result};

fn io_err(path: &Path, what: &'static str) -> impl FnOnce(std::io::Error) -> FormatError {
    FormatError::io(path, what)
}

const PAGE_HEADER: usize = 16;
const NODE_HEADER: usize = 8;
const P_BRANCH: u16 = 0x01;
const P_LEAF: u16 = 0x02;
const P_OVERFLOW: u16 = 0x04;
const P_META: u16 = 0x08;
const P_DIRTY: u16 = 0x10;
const P_LEAF2: u16 = 0x20;
const P_SUBP: u16 = 0x40;
const P_LOOSE: u16 = 0x4000;
const P_KEEP: u16 = 0x8000;
const F_BIGDATA: u16 = 0x01;
const F_SUBDATA: u16 = 0x02;
const F_DUPDATA: u16 = 0x04;
const MAGIC: u32 = 0xBEEF_C0DE;
const DATA_VERSION: u32 = 1;
const P_INVALID: u64 = u64::MAX;
/// Meta layout, offsets from the start of the page.
const META_MAGIC: usize = 16;
const META_VERSION: usize = 20;
const META_MAPSIZE: usize = 32;
const META_FREE_DB: usize = 40;
const META_MAIN_DB: usize = 88;
const META_LAST_PAGE: usize = 136;
const META_TXNID: usize = 144;
const META_END: usize = 152;
/// liblmdb keeps trees below 32 levels (its cursor stack).
const MAX_DEPTH: usize = 32;
/// liblmdb's default maximum key size.
pub const MAX_KEY_SIZE: usize = 511;
/// The page size the writer uses (the common OS page size, which liblmdb picks itself).
pub const WRITE_PAGE_SIZE: usize = 4096;

/// Tree statistics of the main database, as `mdb_stat` reports them, plus the meta page used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LmdbStat {
    pub page_size: usize,
    pub depth: usize,
    pub branch_pages: u64,
    pub leaf_pages: u64,
    pub overflow_pages: u64,
    pub entries: u64,
    /// Transaction id of the meta page in use.
    pub txnid: u64,
    /// Highest page number in use.
    pub last_page: u64,
}

#[derive(Debug, Clone, Copy)]
struct DbRecord {
    flags: u16,
    depth: u16,
    branch_pages: u64,
    leaf_pages: u64,
    overflow_pages: u64,
    entries: u64,
    root: u64,
}

enum Source {
    File { file: FileReader, len: u64 },
    Memory(Vec<u8>),
}

#[cfg(unix)]
struct FileReader(std::fs::File);

#[cfg(unix)]
impl FileReader {
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        std::os::unix::fs::FileExt::read_exact_at(&self.0, buf, offset)
    }
}

#[cfg(not(unix))]
struct FileReader(std::sync::Mutex<std::fs::File>);

#[cfg(not(unix))]
impl FileReader {
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        use std::io::{Read, Seek, SeekFrom};
        let mut f = self.0.lock().unwrap_or_else(|e| e.into_inner());
        f.seek(SeekFrom::Start(offset))?;
        f.read_exact(buf)
    }
}

/// A read-only view of an LMDB environment's main database.
pub struct LmdbReader {
    path: PathBuf,
    source: Source,
    psize: usize,
    db: DbRecord,
    txnid: u64,
    last_page: u64,
}

impl std::fmt::Debug for LmdbReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LmdbReader")
            .field("path", &self.path)
            .field("stat", &self.stat())
            .finish()
    }
}

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(a)
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}

fn db_at(b: &[u8], at: usize) -> DbRecord {
    DbRecord {
        flags: u16_at(b, at + 4),
        depth: u16_at(b, at + 6),
        branch_pages: u64_at(b, at + 8),
        leaf_pages: u64_at(b, at + 16),
        overflow_pages: u64_at(b, at + 24),
        entries: u64_at(b, at + 32),
        root: u64_at(b, at + 40),
    }
}

/// A key for error messages: text when printable, else hex (both shortened).
pub(crate) fn show_key(key: &[u8]) -> String {
    match std::str::from_utf8(key) {
        Ok(s) if s.chars().all(|c| !c.is_control()) => {
            let short: String = s.chars().take(60).collect();
            if short.len() < s.len() {
                format!("{short}...")
            } else {
                short
            }
        }
        _ => {
            let hex: String = key.iter().take(30).map(|b| format!("{b:02x}")).collect();
            format!("0x{hex}{}", if key.len() > 30 { "..." } else { "" })
        }
    }
}

/// A validated branch or leaf page.
struct Page {
    pgno: u64,
    bytes: Vec<u8>,
    leaf: bool,
    nkeys: usize,
}

/// What a leaf node holds.
enum LeafValue<'a> {
    Inline(&'a [u8]),
    Overflow { pgno: u64, len: usize },
}

impl LmdbReader {
    /// Opens `path`: an environment directory (holding `data.mdb`) or the data file itself.
    pub fn open(path: &Path) -> Result<Self> {
        let file_path = if path.is_dir() {
            path.join("data.mdb")
        } else {
            path.to_owned()
        };
        let file = std::fs::File::open(&file_path).map_err(io_err(&file_path, "cannot open"))?;
        let len = file
            .metadata()
            .map_err(io_err(&file_path, "cannot read"))?
            .len();
        #[cfg(unix)]
        let reader = FileReader(file);
        #[cfg(not(unix))]
        let reader = FileReader(std::sync::Mutex::new(file));
        Self::with_source(file_path, Source::File { file: reader, len })
    }

    /// Reads an environment held in memory (`name` labels errors).
    pub fn from_bytes(name: &Path, bytes: Vec<u8>) -> Result<Self> {
        Self::with_source(name.to_owned(), Source::Memory(bytes))
    }

    fn err(path: &Path, reason: impl Into<String>) -> FormatError {
        FormatError::Lmdb {
            path: path.to_owned(),
            reason: reason.into(),
        }
    }

    fn corrupt(&self, reason: impl Into<String>) -> FormatError {
        Self::err(&self.path, reason)
    }

    fn source_len(source: &Source) -> u64 {
        match source {
            Source::File { len, .. } => *len,
            Source::Memory(b) => b.len() as u64,
        }
    }

    fn read_raw(path: &Path, source: &Source, offset: u64, len: usize) -> Result<Vec<u8>> {
        let total = Self::source_len(source);
        let end = offset.checked_add(len as u64);
        if end.is_none_or(|e| e > total) {
            return Err(Self::err(
                path,
                format!(
                    "truncated: needs bytes {offset}..{} of a {total}-byte file",
                    offset.saturating_add(len as u64)
                ),
            ));
        }
        match source {
            Source::Memory(b) => {
                // In range: checked against the length above.
                let start = offset as usize;
                Ok(b[start..start + len].to_vec())
            }
            Source::File { file, .. } => {
                let mut buf = vec![0u8; len];
                file.read_exact_at(&mut buf, offset)
                    .map_err(io_err(path, "cannot read"))?;
                Ok(buf)
            }
        }
    }

    fn with_source(path: PathBuf, source: Source) -> Result<Self> {
        let meta0 = Self::read_raw(&path, &source, 0, META_END).map_err(|_| {
            Self::err(
                &path,
                "too short for an LMDB meta page (empty or truncated file)",
            )
        })?;
        let check_meta = |m: &[u8], which: u64| -> Result<()> {
            let flags = u16_at(m, 10);
            if u32_at(m, META_MAGIC) != MAGIC {
                return Err(Self::err(
                    &path,
                    format!(
                        "meta page {which} has no LMDB magic number (not an LMDB file, or corrupt)"
                    ),
                ));
            }
            let version = u32_at(m, META_VERSION);
            if version != DATA_VERSION {
                return Err(Self::err(
                    &path,
                    format!("data format version {version}; only version {DATA_VERSION} (LMDB 0.9) is supported"),
                ));
            }
            if flags & P_META == 0 || u64_at(m, 0) != which {
                return Err(Self::err(
                    &path,
                    format!("meta page {which} has a corrupt header"),
                ));
            }
            Ok(())
        };
        check_meta(&meta0, 0)?;
        let psize = u32_at(&meta0, META_FREE_DB) as usize;
        if !psize.is_power_of_two() || !(256..=65536).contains(&psize) {
            return Err(Self::err(&path, format!("page size {psize} is invalid")));
        }
        let meta1 = Self::read_raw(&path, &source, psize as u64, META_END)
            .map_err(|_| Self::err(&path, "truncated: the second meta page is missing"))?;
        check_meta(&meta1, 1)?;
        if u32_at(&meta1, META_FREE_DB) as usize != psize {
            return Err(Self::err(
                &path,
                "the two meta pages disagree on the page size",
            ));
        }
        let (m, txnid) = {
            let (t0, t1) = (u64_at(&meta0, META_TXNID), u64_at(&meta1, META_TXNID));
            if t1 > t0 {
                (meta1, t1)
            } else {
                (meta0, t0)
            }
        };
        let db = db_at(&m, META_MAIN_DB);
        let last_page = u64_at(&m, META_LAST_PAGE);
        if db.flags != 0 {
            let mut what = Vec::new();
            for (bit, name) in [
                (0x02, "reverse keys"),
                (0x04, "duplicate keys (dupsort)"),
                (0x08, "integer keys"),
                (0x10, "fixed-size duplicates"),
                (0x20, "integer duplicates"),
                (0x40, "reverse duplicates"),
            ] {
                if db.flags & bit != 0 {
                    what.push(name);
                }
            }
            if what.is_empty() {
                what.push("unknown flags");
            }
            return Err(Self::err(
                &path,
                format!(
                    "the main database uses {} (flags 0x{:x}), which is not supported",
                    what.join(", "),
                    db.flags
                ),
            ));
        }
        let reader = Self {
            path,
            source,
            psize,
            db,
            txnid,
            last_page,
        };
        let depth = usize::from(db.depth);
        if db.root == P_INVALID {
            if depth != 0 || db.entries != 0 {
                return Err(
                    reader.corrupt("an empty database with a non-zero depth or entry count")
                );
            }
        } else {
            if depth == 0 || depth > MAX_DEPTH {
                return Err(reader.corrupt(format!("tree depth {depth} is invalid")));
            }
            reader.check_pgno(db.root, "root page")?;
        }
        Ok(reader)
    }

    /// The data file read.
    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn stat(&self) -> LmdbStat {
        LmdbStat {
            page_size: self.psize,
            depth: usize::from(self.db.depth),
            branch_pages: self.db.branch_pages,
            leaf_pages: self.db.leaf_pages,
            overflow_pages: self.db.overflow_pages,
            entries: self.db.entries,
            txnid: self.txnid,
            last_page: self.last_page,
        }
    }

    /// Number of entries (from the meta page).
    pub fn len(&self) -> usize {
        usize::try_from(self.db.entries).unwrap_or(usize::MAX)
    }

    pub fn is_empty(&self) -> bool {
        self.db.entries == 0
    }

    fn check_pgno(&self, pgno: u64, what: &str) -> Result<()> {
        if pgno < 2 || pgno > self.last_page {
            return Err(self.corrupt(format!(
                "{what} {pgno} is outside the pages in use (2..={})",
                self.last_page
            )));
        }
        Ok(())
    }

    fn page(&self, pgno: u64) -> Result<Page> {
        self.check_pgno(pgno, "page")?;
        let offset = pgno
            .checked_mul(self.psize as u64)
            .ok_or_else(|| self.corrupt(format!("page {pgno} is beyond any file")))?;
        let bytes = Self::read_raw(&self.path, &self.source, offset, self.psize)?;
        let bad = |why: &str| self.corrupt(format!("page {pgno} is corrupt: {why}"));
        if u64_at(&bytes, 0) != pgno {
            return Err(bad("its header names another page"));
        }
        let flags = u16_at(&bytes, 10) & !(P_DIRTY | P_LOOSE | P_KEEP);
        if flags & (P_LEAF2 | P_SUBP) != 0 {
            return Err(self.corrupt(format!(
                "page {pgno} belongs to a duplicate-key (dupsort) database, which is not supported"
            )));
        }
        let leaf = match flags {
            P_LEAF => true,
            P_BRANCH => false,
            _ => {
                return Err(bad(&format!(
                    "flags 0x{flags:x} are not a branch or leaf page"
                )))
            }
        };
        let lower = usize::from(u16_at(&bytes, 12));
        let upper = usize::from(u16_at(&bytes, 14));
        if lower < PAGE_HEADER
            || !(lower - PAGE_HEADER).is_multiple_of(2)
            || lower > upper
            || upper > self.psize
        {
            return Err(bad(&format!("free-space bounds {lower}..{upper}")));
        }
        let nkeys = (lower - PAGE_HEADER) / 2;
        let page = Page {
            pgno,
            bytes,
            leaf,
            nkeys,
        };
        // Every node header must lie inside the page; keys and values are checked on use.
        for i in 0..nkeys {
            let ptr = usize::from(u16_at(&page.bytes, PAGE_HEADER + 2 * i));
            if ptr < lower || ptr + NODE_HEADER > self.psize {
                return Err(bad(&format!(
                    "node {i} at offset {ptr} lies outside the page"
                )));
            }
        }
        Ok(page)
    }

    fn node_ptr(page: &Page, i: usize) -> usize {
        usize::from(u16_at(&page.bytes, PAGE_HEADER + 2 * i))
    }

    fn node_key<'p>(&self, page: &'p Page, i: usize) -> Result<&'p [u8]> {
        let ptr = Self::node_ptr(page, i);
        let ksize = usize::from(u16_at(&page.bytes, ptr + 6));
        page.bytes
            .get(ptr + NODE_HEADER..ptr + NODE_HEADER + ksize)
            .ok_or_else(|| {
                self.corrupt(format!(
                    "page {} is corrupt: the key of node {i} runs past the page",
                    page.pgno
                ))
            })
    }

    fn branch_child(&self, page: &Page, i: usize) -> Result<u64> {
        let ptr = Self::node_ptr(page, i);
        let b = &page.bytes;
        let pgno = u64::from(u16_at(b, ptr))
            | (u64::from(u16_at(b, ptr + 2)) << 16)
            | (u64::from(u16_at(b, ptr + 4)) << 32);
        self.check_pgno(pgno, "child page")?;
        Ok(pgno)
    }

    fn leaf_value<'p>(&self, page: &'p Page, i: usize) -> Result<LeafValue<'p>> {
        let ptr = Self::node_ptr(page, i);
        let b = &page.bytes;
        let dsize = usize::from(u16_at(b, ptr)) | (usize::from(u16_at(b, ptr + 2)) << 16);
        let flags = u16_at(b, ptr + 4);
        let ksize = usize::from(u16_at(b, ptr + 6));
        let start = ptr + NODE_HEADER + ksize;
        if flags & (F_SUBDATA | F_DUPDATA) != 0 {
            return Err(self.corrupt(
                "the main database holds named sub-databases or duplicate keys, which are not supported",
            ));
        }
        if flags & F_BIGDATA != 0 {
            let raw = b.get(start..start + 8).ok_or_else(|| {
                self.corrupt(format!(
                    "page {} is corrupt: node {i} runs past the page",
                    page.pgno
                ))
            })?;
            let pgno = u64_at(raw, 0);
            self.check_pgno(pgno, "overflow page")?;
            return Ok(LeafValue::Overflow { pgno, len: dsize });
        }
        b.get(start..start + dsize)
            .map(LeafValue::Inline)
            .ok_or_else(|| {
                self.corrupt(format!(
                    "page {} is corrupt: the value of node {i} runs past the page",
                    page.pgno
                ))
            })
    }

    fn overflow(&self, pgno: u64, len: usize) -> Result<Vec<u8>> {
        let offset = pgno
            .checked_mul(self.psize as u64)
            .ok_or_else(|| self.corrupt(format!("overflow page {pgno} is beyond any file")))?;
        let head = Self::read_raw(&self.path, &self.source, offset, PAGE_HEADER)?;
        let flags = u16_at(&head, 10) & !(P_DIRTY | P_LOOSE | P_KEEP);
        if u64_at(&head, 0) != pgno || flags != P_OVERFLOW {
            return Err(self.corrupt(format!("overflow page {pgno} has a corrupt header")));
        }
        let pages = u64::from(u32_at(&head, 12));
        let needed = (PAGE_HEADER as u64 + len as u64).div_ceil(self.psize as u64);
        if pages < needed || pgno.saturating_add(pages - 1) > self.last_page {
            return Err(self.corrupt(format!(
                "overflow page {pgno} spans {pages} pages; a {len}-byte value needs {needed} within the pages in use"
            )));
        }
        Self::read_raw(&self.path, &self.source, offset + PAGE_HEADER as u64, len)
    }

    /// Index of the first node whose key is >= `key` (nodes `from..nkeys`).
    fn lower_bound(&self, page: &Page, from: usize, key: &[u8]) -> Result<usize> {
        let (mut lo, mut hi) = (from, page.nkeys);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            if self.node_key(page, mid)? < key {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        Ok(lo)
    }

    /// Finds the leaf page and node index holding `key`.
    fn find(&self, key: &[u8]) -> Result<Option<(Page, usize)>> {
        if self.db.root == P_INVALID {
            return Ok(None);
        }
        let depth = usize::from(self.db.depth);
        let mut pgno = self.db.root;
        for level in 0..depth {
            let page = self.page(pgno)?;
            let want_leaf = level + 1 == depth;
            if page.leaf != want_leaf {
                return Err(self.corrupt(format!(
                    "page {pgno} is a {} page at level {level} of a {depth}-level tree",
                    if page.leaf { "leaf" } else { "branch" }
                )));
            }
            if page.leaf {
                let i = self.lower_bound(&page, 0, key)?;
                if i < page.nkeys && self.node_key(&page, i)? == key {
                    return Ok(Some((page, i)));
                }
                return Ok(None);
            }
            if page.nkeys == 0 {
                return Err(self.corrupt(format!("branch page {pgno} has no children")));
            }
            // Child i covers keys from key_i (key_0 unused) up to key_{i+1}.
            let i = self.lower_bound(&page, 1, key)?;
            let child = if i < page.nkeys && self.node_key(&page, i)? == key {
                i
            } else {
                i - 1
            };
            pgno = self.branch_child(&page, child)?;
        }
        Err(self.corrupt("the tree has no leaf level"))
    }

    /// The value stored under `key`.
    pub fn get(&self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        let Some((page, i)) = self.find(key)? else {
            return Ok(None);
        };
        match self.leaf_value(&page, i)? {
            LeafValue::Inline(v) => Ok(Some(v.to_vec())),
            LeafValue::Overflow { pgno, len } => self.overflow(pgno, len).map(Some),
        }
    }

    /// Whether `key` is stored (without reading its value).
    pub fn contains_key(&self, key: &[u8]) -> Result<bool> {
        match self.find(key)? {
            None => Ok(false),
            Some((page, i)) => self.leaf_value(&page, i).map(|_| true),
        }
    }

    /// Every key in sorted order. Reads the branch and leaf pages (not the overflow values);
    /// checks that keys are strictly increasing and that the count matches the meta page.
    pub fn keys(&self) -> Result<Vec<Vec<u8>>> {
        let mut keys: Vec<Vec<u8>> = Vec::with_capacity(self.len().min(1 << 20));
        if self.db.root == P_INVALID {
            return Ok(keys);
        }
        let depth = usize::from(self.db.depth);
        let mut visited = std::collections::HashSet::new();
        let mut stack = vec![(self.db.root, 0usize)];
        while let Some((pgno, level)) = stack.pop() {
            if !visited.insert(pgno) {
                return Err(self.corrupt(format!("page {pgno} is reached twice (a corrupt tree)")));
            }
            let page = self.page(pgno)?;
            let want_leaf = level + 1 == depth;
            if page.leaf != want_leaf {
                return Err(self.corrupt(format!(
                    "page {pgno} is a {} page at level {level} of a {depth}-level tree",
                    if page.leaf { "leaf" } else { "branch" }
                )));
            }
            if page.leaf {
                for i in 0..page.nkeys {
                    let k = self.node_key(&page, i)?;
                    self.leaf_value(&page, i)?;
                    if keys.last().is_some_and(|last| last.as_slice() >= k) {
                        return Err(self.corrupt(format!(
                            "keys out of order at `{}` (a corrupt tree)",
                            show_key(k)
                        )));
                    }
                    keys.push(k.to_vec());
                }
            } else {
                if page.nkeys == 0 {
                    return Err(self.corrupt(format!("branch page {pgno} has no children")));
                }
                for i in (0..page.nkeys).rev() {
                    stack.push((self.branch_child(&page, i)?, level + 1));
                }
            }
        }
        if keys.len() as u64 != self.db.entries {
            return Err(self.corrupt(format!(
                "the tree holds {} entries, the meta page says {}",
                keys.len(),
                self.db.entries
            )));
        }
        Ok(keys)
    }
}

// ---- writer ------------------------------------------------------------------------------

/// Largest node (header + key + inline value) on a page, as liblmdb computes it: values that
/// would make a leaf node larger go to overflow pages.
fn node_max(psize: usize) -> usize {
    (((psize - PAGE_HEADER) / 2) & !1) - 2
}

fn even(n: usize) -> usize {
    n + (n & 1)
}

enum Stored {
    Inline(Vec<u8>),
    Overflow { pgno: u64, len: usize },
}

struct PageWriter {
    out: std::io::BufWriter<std::fs::File>,
    next: u64,
    path: PathBuf,
}

impl PageWriter {
    fn write(&mut self, bytes: &[u8]) -> Result<()> {
        use std::io::Write;
        self.out
            .write_all(bytes)
            .map_err(io_err(&self.path, "cannot write"))
    }
}

fn page_header(pgno: u64, flags: u16) -> Vec<u8> {
    let mut p = vec![0u8; WRITE_PAGE_SIZE];
    p[0..8].copy_from_slice(&pgno.to_le_bytes());
    p[10..12].copy_from_slice(&flags.to_le_bytes());
    p
}

/// Assembles a leaf or branch page from its nodes (each already laid out), in key order.
fn node_page(pgno: u64, flags: u16, nodes: &[Vec<u8>]) -> Vec<u8> {
    let mut p = page_header(pgno, flags);
    let mut upper = WRITE_PAGE_SIZE;
    for (i, node) in nodes.iter().enumerate() {
        upper -= even(node.len());
        p[upper..upper + node.len()].copy_from_slice(node);
        let at = PAGE_HEADER + 2 * i;
        p[at..at + 2].copy_from_slice(&(upper as u16).to_le_bytes());
    }
    let lower = PAGE_HEADER + 2 * nodes.len();
    p[12..14].copy_from_slice(&(lower as u16).to_le_bytes());
    p[14..16].copy_from_slice(&(upper as u16).to_le_bytes());
    p
}

fn leaf_node(key: &[u8], value: &Stored) -> Vec<u8> {
    let (dsize, flags, payload): (usize, u16, Vec<u8>) = match value {
        Stored::Inline(v) => (v.len(), 0, v.clone()),
        Stored::Overflow { pgno, len } => (*len, F_BIGDATA, pgno.to_le_bytes().to_vec()),
    };
    let mut n = Vec::with_capacity(NODE_HEADER + key.len() + payload.len());
    n.extend_from_slice(&((dsize & 0xffff) as u16).to_le_bytes());
    n.extend_from_slice(&((dsize >> 16) as u16).to_le_bytes());
    n.extend_from_slice(&flags.to_le_bytes());
    n.extend_from_slice(&(key.len() as u16).to_le_bytes());
    n.extend_from_slice(key);
    n.extend_from_slice(&payload);
    n
}

fn branch_node(key: &[u8], child: u64) -> Vec<u8> {
    let mut n = Vec::with_capacity(NODE_HEADER + key.len());
    n.extend_from_slice(&((child & 0xffff) as u16).to_le_bytes());
    n.extend_from_slice(&(((child >> 16) & 0xffff) as u16).to_le_bytes());
    n.extend_from_slice(&(((child >> 32) & 0xffff) as u16).to_le_bytes());
    n.extend_from_slice(&(key.len() as u16).to_le_bytes());
    n.extend_from_slice(key);
    n
}

/// Splits `sizes` (bytes each item takes on a page, pointer included) into consecutive pages of
/// at most `capacity` bytes, at least `min_items` per page where there is more than one page.
fn pack(sizes: &[usize], capacity: usize, min_items: usize) -> Vec<std::ops::Range<usize>> {
    let mut pages = Vec::new();
    let mut start = 0;
    let mut used = 0;
    for (i, &s) in sizes.iter().enumerate() {
        if used + s > capacity && i > start {
            pages.push(start..i);
            start = i;
            used = 0;
        }
        used += s;
    }
    if start < sizes.len() {
        pages.push(start..sizes.len());
    }
    // A short last page borrows from the one before (which holds many: items are small next
    // to the page).
    let n = pages.len();
    if n >= 2 {
        while pages[n - 1].len() < min_items && pages[n - 2].len() > min_items {
            pages[n - 2].end -= 1;
            pages[n - 1].start -= 1;
        }
    }
    pages
}

/// Writes `entries` as a new LMDB environment `dir` (its `data.mdb`), replacing any existing
/// one only once the new one is complete. Keys must be unique, 1 to 511 bytes; input order is
/// free. Large values are streamed to disk as they arrive; keys and small values are held in
/// memory until the tree is written.
pub fn write_lmdb(
    dir: &Path,
    entries: impl IntoIterator<Item = (Vec<u8>, Vec<u8>)>,
) -> Result<LmdbStat> {
    let tmp = temp_sibling(dir);
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp)
            .map_err(io_err(&tmp, "cannot remove a stale temporary directory"))?;
    }
    std::fs::create_dir_all(&tmp).map_err(io_err(&tmp, "cannot create"))?;
    let result = write_env(dir, &tmp, entries);
    match result {
        Ok(stat) => {
            replace_dir(&tmp, dir)
                .map_err(io_err(dir, "cannot move the new directory into place"))?;
            Ok(stat)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            Err(e)
        }
    }
}

fn write_env(
    dir: &Path,
    tmp: &Path,
    entries: impl IntoIterator<Item = (Vec<u8>, Vec<u8>)>,
) -> Result<LmdbStat> {
    let psize = WRITE_PAGE_SIZE;
    let data_path = tmp.join("data.mdb");
    let file = std::fs::File::create(&data_path).map_err(io_err(&data_path, "cannot create"))?;
    let mut w = PageWriter {
        out: std::io::BufWriter::with_capacity(1 << 20, file),
        next: 2,
        path: data_path.clone(),
    };
    let write_err = |reason: String| FormatError::Write {
        path: dir.to_owned(),
        reason,
    };
    // Meta pages are filled in at the end.
    w.write(&vec![0u8; 2 * psize])?;

    let mut stored: Vec<(Vec<u8>, Stored)> = Vec::new();
    let mut overflow_pages = 0u64;
    for (index, (key, value)) in entries.into_iter().enumerate() {
        if key.is_empty() || key.len() > MAX_KEY_SIZE {
            return Err(write_err(format!(
                "key #{index} (`{}`) has {} bytes; LMDB keys have 1 to {MAX_KEY_SIZE}",
                show_key(&key),
                key.len()
            )));
        }
        if u32::try_from(value.len()).is_err() {
            return Err(write_err(format!(
                "the value of `{}` is {} bytes; LMDB values are below 4 GiB",
                show_key(&key),
                value.len()
            )));
        }
        if NODE_HEADER + key.len() + value.len() > node_max(psize) {
            let pages = (PAGE_HEADER + value.len()).div_ceil(psize);
            let pgno = w.next;
            let mut head = page_header(pgno, P_OVERFLOW);
            head.truncate(PAGE_HEADER);
            head[12..16].copy_from_slice(&(pages as u32).to_le_bytes());
            w.write(&head)?;
            w.write(&value)?;
            w.write(&vec![0u8; pages * psize - PAGE_HEADER - value.len()])?;
            w.next += pages as u64;
            overflow_pages += pages as u64;
            stored.push((
                key,
                Stored::Overflow {
                    pgno,
                    len: value.len(),
                },
            ));
        } else {
            stored.push((key, Stored::Inline(value)));
        }
    }
    stored.sort_by(|a, b| a.0.cmp(&b.0));
    if let Some(pair) = stored.windows(2).find(|p| p[0].0 == p[1].0) {
        return Err(write_err(format!(
            "the key `{}` is given twice",
            show_key(&pair[0].0)
        )));
    }

    let capacity = psize - PAGE_HEADER;
    let mut db = DbRecord {
        flags: 0,
        depth: 0,
        branch_pages: 0,
        leaf_pages: 0,
        overflow_pages,
        entries: stored.len() as u64,
        root: P_INVALID,
    };
    if !stored.is_empty() {
        // Leaves.
        let nodes: Vec<Vec<u8>> = stored.iter().map(|(k, v)| leaf_node(k, v)).collect();
        let sizes: Vec<usize> = nodes.iter().map(|n| even(n.len()) + 2).collect();
        // (page number, first key) of each page of the level just written.
        let mut level: Vec<(u64, Vec<u8>)> = Vec::new();
        for range in pack(&sizes, capacity, 1) {
            let pgno = w.next;
            w.write(&node_page(pgno, P_LEAF, &nodes[range.clone()]))?;
            w.next += 1;
            db.leaf_pages += 1;
            level.push((pgno, stored[range.start].0.clone()));
        }
        db.depth = 1;
        // Branch levels; liblmdb keeps at least two children per branch page.
        while level.len() > 1 {
            let sizes: Vec<usize> = level
                .iter()
                .map(|(_, k)| even(NODE_HEADER + k.len()) + 2)
                .collect();
            // The first child of each page is stored with an empty key, so it takes less room
            // than `sizes` says: packing with the full size stays safe.
            let mut next_level = Vec::new();
            for range in pack(&sizes, capacity, 2) {
                let nodes: Vec<Vec<u8>> = level[range.clone()]
                    .iter()
                    .enumerate()
                    .map(|(j, (child, key))| branch_node(if j == 0 { &[] } else { key }, *child))
                    .collect();
                let pgno = w.next;
                w.write(&node_page(pgno, P_BRANCH, &nodes))?;
                w.next += 1;
                db.branch_pages += 1;
                next_level.push((pgno, level[range.start].1.clone()));
            }
            level = next_level;
            db.depth += 1;
        }
        db.root = level[0].0;
    }
    let last_page = w.next - 1;

    let mut file = w
        .out
        .into_inner()
        .map_err(|e| io_err(&data_path, "cannot write")(e.into_error()))?;
    let map_size = ((last_page + 1) * psize as u64).div_ceil(1 << 20).max(1) << 20;
    let empty = DbRecord {
        flags: 0,
        depth: 0,
        branch_pages: 0,
        leaf_pages: 0,
        overflow_pages: 0,
        entries: 0,
        root: P_INVALID,
    };
    let meta0 = meta_page(0, map_size, &empty, 1, 0);
    let meta1 = meta_page(1, map_size, &db, last_page, 1);
    {
        use std::io::{Seek, SeekFrom, Write};
        let io = io_err(&data_path, "cannot write");
        (|| {
            file.seek(SeekFrom::Start(0))?;
            file.write_all(&meta0)?;
            file.seek(SeekFrom::Start(psize as u64))?;
            file.write_all(&meta1)?;
            file.sync_all()
        })()
        .map_err(io)?;
    }
    Ok(LmdbStat {
        page_size: psize,
        depth: usize::from(db.depth),
        branch_pages: db.branch_pages,
        leaf_pages: db.leaf_pages,
        overflow_pages: db.overflow_pages,
        entries: db.entries,
        txnid: 1,
        last_page,
    })
}

fn meta_page(pgno: u64, map_size: u64, main: &DbRecord, last_page: u64, txnid: u64) -> Vec<u8> {
    let mut p = page_header(pgno, P_META);
    p.truncate(META_END);
    p[META_MAGIC..META_MAGIC + 4].copy_from_slice(&MAGIC.to_le_bytes());
    p[META_VERSION..META_VERSION + 4].copy_from_slice(&DATA_VERSION.to_le_bytes());
    p[META_MAPSIZE..META_MAPSIZE + 8].copy_from_slice(&map_size.to_le_bytes());
    let free = DbRecord {
        // liblmdb marks the free-list database as integer-keyed.
        flags: 0x08,
        ..DbRecord {
            flags: 0,
            depth: 0,
            branch_pages: 0,
            leaf_pages: 0,
            overflow_pages: 0,
            entries: 0,
            root: P_INVALID,
        }
    };
    put_db(&mut p, META_FREE_DB, &free, WRITE_PAGE_SIZE as u32);
    put_db(&mut p, META_MAIN_DB, main, 0);
    p[META_LAST_PAGE..META_LAST_PAGE + 8].copy_from_slice(&last_page.to_le_bytes());
    p[META_TXNID..META_TXNID + 8].copy_from_slice(&txnid.to_le_bytes());
    p
}

fn put_db(p: &mut [u8], at: usize, db: &DbRecord, pad: u32) {
    p[at..at + 4].copy_from_slice(&pad.to_le_bytes());
    p[at + 4..at + 6].copy_from_slice(&db.flags.to_le_bytes());
    p[at + 6..at + 8].copy_from_slice(&db.depth.to_le_bytes());
    for (i, v) in [
        db.branch_pages,
        db.leaf_pages,
        db.overflow_pages,
        db.entries,
        db.root,
    ]
    .into_iter()
    .enumerate()
    {
        p[at + 8 + 8 * i..at + 16 + 8 * i].copy_from_slice(&v.to_le_bytes());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_limit_matches_liblmdb() {
        // ((4096 - 16) / 2 & -2) - sizeof(indx_t)
        assert_eq!(node_max(4096), 2038);
    }

    #[test]
    fn packing_respects_capacity_and_minimum() {
        let sizes = vec![100; 25];
        let pages = pack(&sizes, 1000, 2);
        assert_eq!(
            pages.iter().map(|r| r.len()).collect::<Vec<_>>(),
            [10, 10, 5]
        );
        let sizes = vec![100; 21];
        let pages = pack(&sizes, 1000, 2);
        assert_eq!(
            pages.iter().map(|r| r.len()).collect::<Vec<_>>(),
            [10, 9, 2]
        );
        assert!(pack(&[], 1000, 2).is_empty());
        // An item larger than the page still gets a page of its own.
        assert_eq!(pack(&[2000, 10], 1000, 1), vec![0..1, 1..2]);
    }
}
