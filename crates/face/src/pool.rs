//! The worker threads the face networks split their larger ops over.
//!
//! The networks run a few hundred ops per image, most of them small, so a fork must cost well
//! under a microsecond to pay off; rayon's workers sleep between ops and take tens of
//! microseconds to wake, which made two threads slower than one. Here helper threads spin for
//! a short while after each task (about the gap between two ops of a forward pass) before
//! they park, as XNNPACK's thread pool does: within a forward pass a fork is a few atomic
//! operations, between frames the helpers sleep.
//!
//! One fork runs at a time; a fork requested while another is running (from a task, or from a
//! second caller thread) runs its tasks on the calling thread.

use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// How long an idle helper spins before it parks.
const SPIN: Duration = Duration::from_micros(300);

type Task<'a> = dyn Fn(usize) + Sync + 'a;

struct Shared {
    /// `(fork number << 32) | next task index`: a task is claimed by a compare-exchange that
    /// also checks the fork number, so a helper still finishing one fork can never take a
    /// task of the next.
    state: AtomicU64,
    /// The current fork: its task function (valid while its tasks remain), task count and
    /// number.
    fork: Mutex<Option<Fork>>,
    /// Tasks of the current fork not yet finished.
    remaining: AtomicUsize,
    /// Helpers that are parked (a fork must wake them).
    parked: AtomicUsize,
    /// Set when the pool is dropped: helpers exit.
    shutdown: AtomicBool,
    /// A task of the current fork panicked.
    panicked: AtomicBool,
    wake: Condvar,
    wake_lock: Mutex<()>,
}

#[derive(Clone, Copy)]
struct Fork {
    f: *const Task<'static>,
    n: usize,
    id: u32,
}
// SAFETY: the task function is `Sync` and outlives every use (the forking thread waits for all
// of its tasks before returning, see `Pool::run`).
unsafe impl Send for Fork {}

/// A fixed set of helper threads.
pub struct Pool {
    shared: Arc<Shared>,
    helpers: usize,
    /// Held by the thread whose fork is running.
    busy: AtomicBool,
    forks: AtomicU64,
}

thread_local! {
    /// Set on helper threads and inside forks: nested forks run inline.
    static INSIDE: Cell<bool> = const { Cell::new(false) };
}

static THREADS: AtomicUsize = AtomicUsize::new(0);
static POOL: OnceLock<Pool> = OnceLock::new();

/// Sets the number of threads the face networks use (the caller plus helpers), before their
/// first use; later calls have no effect. Default: the machine's available parallelism.
pub fn set_threads(n: usize) {
    THREADS.store(n.max(1), Ordering::Relaxed);
}

/// The number of threads forks use.
pub fn threads() -> usize {
    pool().helpers + 1
}

fn pool() -> &'static Pool {
    POOL.get_or_init(|| {
        let n = match THREADS.load(Ordering::Relaxed) {
            0 => std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1),
            n => n,
        };
        Pool::new(n - 1)
    })
}

/// Runs `f(0..n)`, split over the pool's threads (the caller included); returns when all
/// have run.
pub fn run(n: usize, f: &(dyn Fn(usize) + Sync)) {
    pool().run(n, f)
}

impl Pool {
    fn new(helpers: usize) -> Pool {
        let shared = Arc::new(Shared {
            state: AtomicU64::new(0),
            fork: Mutex::new(None),
            remaining: AtomicUsize::new(0),
            parked: AtomicUsize::new(0),
            shutdown: AtomicBool::new(false),
            panicked: AtomicBool::new(false),
            wake: Condvar::new(),
            wake_lock: Mutex::new(()),
        });
        let mut started = 0;
        for i in 0..helpers {
            let s = shared.clone();
            let spawned = std::thread::Builder::new()
                .name(format!("face-worker-{i}"))
                .spawn(move || helper(&s));
            if spawned.is_err() {
                // Fewer helpers: forks still complete, the caller runs what is left.
                break;
            }
            started += 1;
        }
        Pool {
            shared,
            helpers: started,
            busy: AtomicBool::new(false),
            forks: AtomicU64::new(0),
        }
    }

    fn run(&self, n: usize, f: &Task<'_>) {
        let inline = || {
            for i in 0..n {
                f(i)
            }
        };
        if n <= 1 || self.helpers == 0 || INSIDE.with(|c| c.get()) || n >= u32::MAX as usize {
            return inline();
        }
        if self.busy.swap(true, Ordering::Acquire) {
            return inline();
        }
        let s = &*self.shared;
        let id = (self.forks.fetch_add(1, Ordering::Relaxed) + 1) as u32;
        // SAFETY (lifetime erasure): the pointer is only dereferenced for tasks of this fork,
        // claimed before `remaining` reaches 0, and this function does not return before it does.
        let fp = unsafe { std::mem::transmute::<&Task<'_>, &'static Task<'static>>(f) }
            as *const Task<'static>;
        s.remaining.store(n, Ordering::Relaxed);
        if let Ok(mut g) = s.fork.lock() {
            *g = Some(Fork { f: fp, n, id });
        }
        s.state.store((id as u64) << 32, Ordering::Release);
        if s.parked.load(Ordering::Acquire) > 0 {
            let _g = s.wake_lock.lock();
            s.wake.notify_all();
        }
        INSIDE.with(|c| c.set(true));
        work(s, f as *const Task<'_>, n, id);
        INSIDE.with(|c| c.set(false));
        // Wait for tasks a helper is still running. After a short spin, yield: on a busy
        // machine the helper may be waiting for this very core.
        let mut spins = 0u32;
        while s.remaining.load(Ordering::Acquire) > 0 {
            spins = spins.saturating_add(1);
            if spins > 2000 {
                std::thread::yield_now();
            } else {
                std::hint::spin_loop();
            }
        }
        let panicked = s.panicked.swap(false, Ordering::AcqRel);
        self.busy.store(false, Ordering::Release);
        if panicked {
            panic!("a task of a face-pool fork panicked");
        }
    }
}

impl Drop for Pool {
    fn drop(&mut self) {
        self.shared.shutdown.store(true, Ordering::Release);
        let _g = self.shared.wake_lock.lock();
        self.shared.wake.notify_all();
    }
}

/// Claims and runs tasks of fork `id` until none are left. `f` is only dereferenced after a
/// task was claimed: the fork is then known to be waiting for it, so `f` is alive.
fn work(s: &Shared, f: *const Task<'_>, n: usize, id: u32) {
    let mut cur = s.state.load(Ordering::Acquire);
    loop {
        let (fork, i) = ((cur >> 32) as u32, (cur & 0xffff_ffff) as usize);
        if fork != id || i >= n {
            return;
        }
        match s
            .state
            .compare_exchange_weak(cur, cur + 1, Ordering::AcqRel, Ordering::Acquire)
        {
            Ok(_) => {
                // SAFETY: task i of fork `id` is claimed and not finished, so the forking
                // thread is still inside `Pool::run`, where `f` lives.
                let f = unsafe { &*f };
                // A panicking task must still count as done (or the fork would wait forever);
                // the forking thread re-raises it.
                if std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(i))).is_err() {
                    s.panicked.store(true, Ordering::Release);
                }
                s.remaining.fetch_sub(1, Ordering::Release);
                cur = s.state.load(Ordering::Acquire);
            }
            Err(now) => cur = now,
        }
    }
}

fn helper(s: &Shared) {
    INSIDE.with(|c| c.set(true));
    let mut seen = 0u32;
    loop {
        let idle = Instant::now();
        let mut spins = 0u32;
        loop {
            let fork = (s.state.load(Ordering::Acquire) >> 32) as u32;
            if fork != seen {
                seen = fork;
                break;
            }
            spins = spins.wrapping_add(1);
            if spins.is_multiple_of(256) {
                // Let other work on this core run between checks (sched_yield returns at once
                // on an idle machine).
                std::thread::yield_now();
            }
            if spins.is_multiple_of(64) && idle.elapsed() > SPIN {
                if s.shutdown.load(Ordering::Acquire) {
                    return;
                }
                // Park until the next fork.
                let Ok(mut g) = s.wake_lock.lock() else {
                    return;
                };
                s.parked.fetch_add(1, Ordering::AcqRel);
                while (s.state.load(Ordering::Acquire) >> 32) as u32 == seen {
                    if s.shutdown.load(Ordering::Acquire) {
                        return;
                    }
                    g = match s.wake.wait_timeout(g, Duration::from_millis(100)) {
                        Ok((g, _)) => g,
                        Err(_) => return,
                    };
                }
                s.parked.fetch_sub(1, Ordering::AcqRel);
                spins = 0;
                continue;
            }
            std::hint::spin_loop();
        }
        let fork = s.fork.lock().ok().and_then(|g| *g);
        if let Some(Fork { f, n, id }) = fork {
            if id == seen {
                work(s, f, n, id);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicU32;

    #[test]
    fn every_task_runs_once() {
        let p = Pool::new(1);
        for n in [0, 1, 2, 7, 100] {
            let hits: Vec<AtomicU32> = (0..n).map(|_| AtomicU32::new(0)).collect();
            p.run(n, &|i| {
                hits[i].fetch_add(1, Ordering::Relaxed);
            });
            assert!(
                hits.iter().all(|h| h.load(Ordering::Relaxed) == 1),
                "{n} tasks"
            );
        }
    }

    #[test]
    fn a_panicking_task_is_reraised_and_the_pool_survives() {
        let p = Pool::new(1);
        // Whichever thread runs the panicking task (the caller or the helper), the fork
        // returns by re-raising it, and the pool keeps working.
        for round in 0..20 {
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                p.run(4, &|i| {
                    if i == round % 4 {
                        panic!("task {i}");
                    }
                })
            }));
            assert!(r.is_err(), "round {round}");
            assert!(
                !p.busy.load(Ordering::Acquire),
                "round {round}: pool left busy"
            );
        }
        let hits = AtomicU32::new(0);
        p.run(5, &|_| {
            hits.fetch_add(1, Ordering::Relaxed);
        });
        assert_eq!(hits.load(Ordering::Relaxed), 5);
    }

    #[test]
    fn nested_and_concurrent_forks_complete() {
        let p = Arc::new(Pool::new(2));
        let total = AtomicU32::new(0);
        std::thread::scope(|sc| {
            for _ in 0..3 {
                sc.spawn(|| {
                    for _ in 0..50 {
                        p.run(4, &|_| {
                            p.run(3, &|_| {
                                total.fetch_add(1, Ordering::Relaxed);
                            });
                        });
                    }
                });
            }
        });
        assert_eq!(total.load(Ordering::Relaxed), 3 * 50 * 12);
    }
}
