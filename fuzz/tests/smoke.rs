//! The CI fuzz smoke: every harness on its committed seeds, then on a fixed number of
//! deterministic mutations of them (bit flips, byte sets, truncations, splices, duplicated and
//! deleted spans, corrupted length fields) per target, so every run tries the same inputs on any
//! machine. Each case must allocate at most [`MEMORY_LIMIT`] bytes beyond what was live before
//! it (a counting allocator measures it; allocations that would pass a hard ceiling are refused,
//! which aborts the process with a message naming the case file), and must return at all: a
//! case still running after [`HANG_LIMIT`] is a hang (a limit far above any real case, so a slow
//! or busy machine never fails a correct run). The slowest case per target is printed. The case
//! being run is kept in `target/fuzz-smoke/<target>.current`, so a crash, abort or hang can be
//! replayed.
//!
//! `GAGAVATAR_FUZZ_CASES` sets the mutations per target (default [`DEFAULT_CASES`]).

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use gagavatar_fuzz::TARGETS;

/// What one case may allocate beyond what was live before it.
const MEMORY_LIMIT: usize = 256 << 20;
/// Allocations beyond this total are refused outright (the process aborts with a message), so a
/// hostile size cannot take the machine down before the per-case check runs.
const HARD_CEILING: usize = 1 << 30;
/// A case still running after this is a hang. The slowest real cases take well under a second
/// here (the smoke prints them); this only has to tell "never returns" from "slow".
const HANG_LIMIT: Duration = Duration::from_secs(60);
/// Mutations per target: about 8 s a target on a 2-core machine, under 2 minutes for all.
const DEFAULT_CASES: usize = 4000;
/// Inputs the mutator grows to at most.
const MAX_INPUT: usize = 1 << 20;

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
static REFUSED: AtomicBool = AtomicBool::new(false);

fn note_alloc(size: usize) -> bool {
    let now = LIVE.fetch_add(size, Ordering::Relaxed) + size;
    if now > HARD_CEILING {
        LIVE.fetch_sub(size, Ordering::Relaxed);
        REFUSED.store(true, Ordering::Relaxed);
        // No allocation here: write a fixed message straight to stderr.
        let msg = b"\nfuzz smoke: an allocation would pass the 1 GiB ceiling; the case is in \
target/fuzz-smoke/<target>.current\n";
        // SAFETY: writing a valid buffer to fd 2.
        unsafe {
            libc_write(2, msg.as_ptr(), msg.len());
        }
        return false;
    }
    PEAK.fetch_max(now, Ordering::Relaxed);
    true
}

extern "C" {
    #[link_name = "write"]
    fn libc_write(fd: i32, buf: *const u8, n: usize) -> isize;
}

// SAFETY: forwards to the system allocator, only counting sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !note_alloc(layout.size()) {
            return std::ptr::null_mut();
        }
        let p = System.alloc(layout);
        if p.is_null() {
            LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !note_alloc(layout.size()) {
            return std::ptr::null_mut();
        }
        let p = System.alloc_zeroed(layout);
        if p.is_null() {
            LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > layout.size() && !note_alloc(new_size - layout.size()) {
            return std::ptr::null_mut();
        }
        let p = System.realloc(ptr, layout, new_size);
        if p.is_null() {
            if new_size > layout.size() {
                LIVE.fetch_sub(new_size - layout.size(), Ordering::Relaxed);
            }
        } else if new_size < layout.size() {
            LIVE.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
        }
        p
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// A small deterministic generator (xorshift64*).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
}

/// Values that make length and count fields interesting.
const INTERESTING: [u64; 12] = [
    0,
    1,
    0x7f,
    0x80,
    0xff,
    0x7fff,
    0xffff,
    0x7fff_ffff,
    0xffff_ffff,
    0x1_0000_0000,
    0x7fff_ffff_ffff_ffff,
    u64::MAX,
];

/// One mutation of `seed` (and sometimes a second seed to splice in).
fn mutate(rng: &mut Rng, seed: &[u8], other: &[u8]) -> Vec<u8> {
    let mut d = seed.to_vec();
    let rounds = 1 + rng.below(4);
    for _ in 0..rounds {
        let len = d.len();
        match rng.below(9) {
            // Flip a bit.
            0 if len > 0 => {
                let i = rng.below(len);
                d[i] ^= 1 << rng.below(8);
            }
            // Set a byte.
            1 if len > 0 => {
                let i = rng.below(len);
                d[i] = rng.next() as u8;
            }
            // Truncate.
            2 if len > 0 => d.truncate(rng.below(len)),
            // Delete a span.
            3 if len > 1 => {
                let a = rng.below(len);
                let b = (a + 1 + rng.below(64)).min(len);
                d.drain(a..b);
            }
            // Duplicate a span.
            4 if len > 1 && len < MAX_INPUT / 2 => {
                let a = rng.below(len);
                let b = (a + 1 + rng.below(256)).min(len);
                let span: Vec<u8> = d[a..b].to_vec();
                let at = rng.below(len);
                d.splice(at..at, span);
            }
            // Splice in part of another seed.
            5 if !other.is_empty() => {
                let a = rng.below(other.len());
                let b = (a + 1 + rng.below(512)).min(other.len());
                let at = rng.below(len + 1);
                let cut = (at + rng.below(64)).min(len);
                d.splice(at..cut, other[a..b].iter().copied());
            }
            // Overwrite a 1/2/4/8-byte field with an interesting value, either byte order.
            6 | 7 if len > 0 => {
                let width = [1, 2, 4, 8][rng.below(4)];
                let v = INTERESTING[rng.below(INTERESTING.len())]
                    .wrapping_add(rng.below(3) as u64)
                    .wrapping_sub(1);
                let field: Vec<u8> = if rng.below(2) == 0 {
                    v.to_le_bytes()[..width].to_vec()
                } else {
                    v.to_be_bytes()[8 - width..].to_vec()
                };
                let at = rng.below(len);
                for (k, &byte) in field.iter().enumerate() {
                    if at + k < len {
                        d[at + k] = byte;
                    }
                }
            }
            // Insert random bytes.
            _ => {
                let at = rng.below(len + 1);
                let n = 1 + rng.below(16);
                let ins: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
                d.splice(at..at, ins);
            }
        }
    }
    d.truncate(MAX_INPUT);
    d
}

fn corpus_dir(target: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("corpus")
        .join(target)
}

fn seeds(target: &str) -> Vec<(String, Vec<u8>)> {
    let dir = corpus_dir(target);
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_file())
        .map(|e| {
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect();
    out.sort();
    out
}

fn scratch() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/fuzz-smoke");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// What a worker reports per case: (time taken, peak bytes above the case's start).
type Report = std::thread::Result<(Duration, usize)>;

/// Runs cases on one worker thread so a hang can be detected from here.
struct Runner {
    target: &'static str,
    jobs: mpsc::Sender<Vec<u8>>,
    done: mpsc::Receiver<Report>,
    current: PathBuf,
}

impl Runner {
    fn new(target: &'static str, f: fn(&[u8])) -> Self {
        let (jobs, job_rx) = mpsc::channel::<Vec<u8>>();
        let (done_tx, done) = mpsc::channel();
        std::thread::Builder::new()
            .name(format!("fuzz-{target}"))
            .stack_size(64 << 20)
            .spawn(move || {
                while let Ok(case) = job_rx.recv() {
                    let before = LIVE.load(Ordering::Relaxed);
                    PEAK.store(before, Ordering::Relaxed);
                    let t0 = Instant::now();
                    let r = std::panic::catch_unwind(|| f(&case));
                    let peak = PEAK.load(Ordering::Relaxed).saturating_sub(before);
                    drop(case);
                    let _ = done_tx.send(r.map(|()| (t0.elapsed(), peak)));
                }
            })
            .unwrap();
        let current = scratch().join(format!("{target}.current"));
        Runner {
            target,
            jobs,
            done,
            current,
        }
    }

    /// Runs one case and returns its time; a failure message names the saved case file.
    fn run(&self, case: &[u8], what: &str) -> Result<Duration, String> {
        std::fs::write(&self.current, case).unwrap();
        self.jobs.send(case.to_vec()).unwrap();
        let saved = || {
            let p = scratch().join(format!("{}.failure", self.target));
            std::fs::write(&p, case).unwrap();
            p.display().to_string()
        };
        match self.done.recv_timeout(HANG_LIMIT) {
            Ok(Ok((_, peak))) if peak > MEMORY_LIMIT => Err(format!(
                "{}: {what} allocated {} MB (limit {} MB); case saved to {}",
                self.target,
                peak >> 20,
                MEMORY_LIMIT >> 20,
                saved()
            )),
            Ok(Ok((took, _))) => Ok(took),
            Ok(Err(_)) => Err(format!(
                "{}: {what} panicked; case saved to {}",
                self.target,
                saved()
            )),
            Err(_) => Err(format!(
                "{}: {what} ran longer than {:?} (a hang); case saved to {}",
                self.target,
                HANG_LIMIT,
                saved()
            )),
        }
    }
}

fn mutations_per_target() -> usize {
    std::env::var("GAGAVATAR_FUZZ_CASES")
        .ok()
        .and_then(|s| s.parse::<usize>().ok())
        .unwrap_or(DEFAULT_CASES)
}

#[test]
fn every_loader_survives_its_seeds_and_their_mutations() {
    // Panics are caught and reported per case; keep their messages out of the log.
    std::panic::set_hook(Box::new(|_| {}));
    let mut failures = Vec::new();
    let mut summary = Vec::new();
    for &(target, f) in TARGETS {
        let seeds = seeds(target);
        assert!(!seeds.is_empty(), "{target}: no seeds in corpus/{target}");
        let runner = Runner::new(target, f);
        let t0 = Instant::now();
        let mut slowest = Duration::ZERO;
        let mut cases = 0usize;
        for (name, data) in &seeds {
            match runner.run(data, &format!("seed {name}")) {
                Ok(took) => slowest = slowest.max(took),
                Err(e) => failures.push(e),
            }
            if failures.iter().any(|e| e.contains("a hang")) {
                break;
            }
            cases += 1;
        }
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15 ^ target.len() as u64);
        for m in 0..mutations_per_target() {
            if failures.len() >= 20 {
                break;
            }
            let a = &seeds[rng.below(seeds.len())].1;
            let b = &seeds[rng.below(seeds.len())].1;
            let case = mutate(&mut rng, a, b);
            match runner.run(&case, &format!("mutation {m}")) {
                Ok(took) => slowest = slowest.max(took),
                Err(e) => {
                    // A hung worker cannot take more cases.
                    let hung = e.contains("a hang");
                    failures.push(e);
                    if hung {
                        break;
                    }
                }
            }
            cases += 1;
        }
        summary.push(format!(
            "{target}: {} seeds, {cases} cases in {:.1} s, slowest {:.0} ms",
            seeds.len(),
            t0.elapsed().as_secs_f64(),
            slowest.as_secs_f64() * 1e3
        ));
    }
    let _ = std::panic::take_hook();
    eprintln!("fuzz smoke:\n  {}", summary.join("\n  "));
    assert!(
        !REFUSED.load(Ordering::Relaxed),
        "an allocation passed the ceiling"
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn the_mutator_changes_inputs_deterministically() {
    let seed = b"0123456789abcdef".to_vec();
    let mut a = Rng(7);
    let mut b = Rng(7);
    let xs: Vec<Vec<u8>> = (0..50).map(|_| mutate(&mut a, &seed, b"XYZ")).collect();
    let ys: Vec<Vec<u8>> = (0..50).map(|_| mutate(&mut b, &seed, b"XYZ")).collect();
    assert_eq!(xs, ys);
    assert!(xs.iter().filter(|x| **x != seed).count() > 40);
}

/// Replays every input an AFL++ campaign kept (`fuzz/afl/out/<target>/default/{queue,crashes,
/// hangs}`, or the folder in `GAGAVATAR_FUZZ_REPLAY`) through the same checks as the smoke:
/// the hostile-input corpus, run with `cargo test -p gagavatar-fuzz --test smoke -- --ignored`.
#[test]
#[ignore = "needs the output of a long AFL++ campaign"]
fn replay_the_afl_corpora() {
    std::panic::set_hook(Box::new(|_| {}));
    let root = std::env::var_os("GAGAVATAR_FUZZ_REPLAY")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("afl/out"));
    let mut failures = Vec::new();
    let mut total = 0;
    for &(target, f) in TARGETS {
        let runner = Runner::new(target, f);
        let mut n = 0;
        let mut worst = 0usize;
        for sub in ["queue", "crashes", "hangs"] {
            let dir = root.join(target).join("default").join(sub);
            let Ok(rd) = std::fs::read_dir(&dir) else {
                continue;
            };
            let mut files: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).collect();
            files.sort();
            for p in files.iter().filter(|p| p.is_file()) {
                let data = std::fs::read(p).unwrap();
                let before = LIVE.load(Ordering::Relaxed);
                if let Err(e) = runner.run(&data, &p.display().to_string()) {
                    failures.push(e);
                }
                worst = worst.max(PEAK.load(Ordering::Relaxed).saturating_sub(before));
                n += 1;
            }
        }
        eprintln!(
            "{target}: {n} inputs replayed, largest allocation peak {:.1} MB",
            worst as f64 / 1e6
        );
        total += n;
    }
    let _ = std::panic::take_hook();
    assert!(total > 0, "no AFL output under {}", root.display());
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
