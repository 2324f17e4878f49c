//! Handing memory a session's end freed back to the operating system (the server's sites and the agent's
//! lifelong runs).
//!
//! A session's end trims the map: the stale submaps go, with their nodes, grids and branch-and-bound
//! precomputations — hundreds of MiB on a busy site. glibc's allocator keeps what is freed in its arenas
//! (one per thread that allocated, up to 8 per core) for reuse and returns it to the system only from the
//! top of each heap, so after the blocking pool's threads have built and freed a few maps the process's
//! RSS sat 680–900 MiB above its live heap in the 60-minute soak (docs/BENCHMARK-HISTORY.md, issue 16 §5).
//! [`release_freed_memory`] runs glibc's `malloc_trim`, which returns every arena's free pages; a site
//! calls it after each session end, on a thread of its own ([`release_freed_memory_in_background`]):
//! with a GiB freed it takes 0.1–0.5 s, which the site's next change should not wait for.
//! An idle site that drops its whole map calls [`release_all_freed_memory_in_background`] instead:
//! sites that went idle together free their maps on several threads at once, and what one finishes
//! freeing while another's release runs must still go back (with the first function, five sites
//! unloaded at once left 24–52 MiB of RSS, depending on the order the frees ended in; with this one
//! 23–30 MiB, docs/BENCHMARK-HISTORY.md).
//! Elsewhere (musl, other systems) it does nothing.

use std::sync::atomic::{AtomicBool, Ordering};

/// Returns the allocator's free pages to the operating system (glibc's `malloc_trim(0)`); a no-op on
/// other allocators. Costs a walk of the allocator's arenas and a system call per free run (0.1–0.5 s
/// with a GiB freed between live blocks in four arenas): call it after large frees, not per request.
pub fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[allow(unsafe_code)]
    // SAFETY: `malloc_trim` takes a padding in bytes and only walks glibc's own arenas under their
    // locks; it has no preconditions on the caller.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Releases on a thread of their own, one at a time (see [`release_freed_memory_in_background`] and
/// [`release_all_freed_memory_in_background`]). Thread-safe.
struct Releases {
    /// A release thread is running.
    running: AtomicBool,
    /// A release was asked for that must begin after the call that asked.
    again: AtomicBool,
}

impl Releases {
    const fn new() -> Self {
        Self {
            running: AtomicBool::new(false),
            again: AtomicBool::new(false),
        }
    }

    /// Runs `release` on a thread of its own unless one runs; with `again`, one that runs runs once more
    /// when it ends (calls meanwhile share that one).
    fn start(&'static self, again: bool, release: fn()) {
        if again {
            self.again.store(true, Ordering::Release);
        }
        if self.running.swap(true, Ordering::AcqRel) {
            return;
        }
        let spawned = std::thread::Builder::new()
            .name("memory-release".into())
            .spawn(move || {
                loop {
                    // What was asked for before this release is covered by it.
                    self.again.store(false, Ordering::Release);
                    release();
                    self.running.store(false, Ordering::Release);
                    // Asked for again while it ran, and no other thread took over since: once more.
                    if !self.again.load(Ordering::Acquire)
                        || self.running.swap(true, Ordering::AcqRel)
                    {
                        break;
                    }
                }
            });
        if spawned.is_err() {
            self.running.store(false, Ordering::Release);
        }
    }
}

static RELEASES: Releases = Releases::new();

/// [`release_freed_memory`] on a short-lived thread of its own, unless one is still running (a replay
/// ends hundreds of sessions in a row: one release at a time is enough).
pub fn release_freed_memory_in_background() {
    RELEASES.start(false, release_freed_memory);
}

/// [`release_freed_memory`] on a short-lived thread of its own, beginning after this call: if a release
/// is running, it runs once more when it ends (calls meanwhile share that one). For large frees that
/// come in bursts on several threads (idle sites unloaded together), all of which must go back.
pub fn release_all_freed_memory_in_background() {
    RELEASES.start(true, release_freed_memory);
}

#[cfg(test)]
#[cfg(all(target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::*;

    /// Resident set size of this process, bytes (`/proc/self/statm`'s second field, in pages).
    fn rss_bytes() -> usize {
        let statm = std::fs::read_to_string("/proc/self/statm").unwrap();
        let pages: usize = statm.split_whitespace().nth(1).unwrap().parse().unwrap();
        pages * 4096
    }

    #[test]
    fn memory_freed_between_live_blocks_goes_back_to_the_system() {
        const BLOCK: usize = 16 * 1024;
        const BLOCKS: usize = 12_000; // ~190 MiB
        // On a thread of its own, as the blocking pool's: its own arena.
        let kept = std::thread::Builder::new()
            .name("allocating".into())
            .spawn(|| {
                let mut blocks: Vec<Vec<u8>> = (0..BLOCKS).map(|i| vec![i as u8; BLOCK]).collect();
                // Keep every 16th block alive: the freed memory is between live blocks, not at the top of
                // the arena's heap, so free() alone cannot give it back.
                let kept: Vec<Vec<u8>> =
                    blocks.iter_mut().step_by(16).map(std::mem::take).collect();
                drop(blocks);
                kept
            })
            .unwrap()
            .join()
            .unwrap();
        let before = rss_bytes();
        release_freed_memory();
        let after = rss_bytes();
        assert!(
            before.saturating_sub(after) > 100 << 20,
            "RSS {} MiB before, {} MiB after",
            before >> 20,
            after >> 20
        );
        assert_eq!(kept.len(), BLOCKS / 16);
        assert!(kept.iter().enumerate().all(|(i, b)| b[0] == (i * 16) as u8));
    }
}

#[cfg(test)]
mod releases_tests {
    use std::sync::atomic::AtomicUsize;
    use std::time::{Duration, Instant};

    use super::*;

    static RELEASES: Releases = Releases::new();
    static CALLS: AtomicUsize = AtomicUsize::new(0);
    static OPEN: AtomicBool = AtomicBool::new(false);

    /// A release that counts itself and holds until the test opens the gate.
    fn gated_release() {
        CALLS.fetch_add(1, Ordering::SeqCst);
        let began = Instant::now();
        while !OPEN.load(Ordering::SeqCst) && began.elapsed() < Duration::from_secs(30) {
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    fn until(what: &str, done: impl Fn() -> bool) {
        let began = Instant::now();
        while !done() {
            assert!(began.elapsed() < Duration::from_secs(30), "{what}");
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    #[test]
    fn a_release_asked_for_while_one_runs_runs_after_it_only_when_all_must_go_back() {
        let calls = || CALLS.load(Ordering::SeqCst);
        let idle = || !RELEASES.running.load(Ordering::SeqCst);
        // A session end's release while one runs is skipped.
        RELEASES.start(false, gated_release);
        until("the first release began", || calls() == 1);
        RELEASES.start(false, gated_release);
        OPEN.store(true, Ordering::SeqCst);
        until("the first release ended", idle);
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(calls(), 1);
        assert!(idle());
        // An unload's is run after the running one, once for every call meanwhile.
        OPEN.store(false, Ordering::SeqCst);
        RELEASES.start(false, gated_release);
        until("the second release began", || calls() == 2);
        RELEASES.start(true, gated_release);
        RELEASES.start(true, gated_release);
        OPEN.store(true, Ordering::SeqCst);
        until("the release after it ran and ended", || {
            calls() == 3 && idle()
        });
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(calls(), 3);
        assert!(!RELEASES.again.load(Ordering::SeqCst));
    }
}
