//! Handing memory the server freed back to the operating system.
//!
//! A session's end trims the map: the stale submaps go, with their nodes, grids and branch-and-bound
//! precomputations — hundreds of MiB on a busy site. glibc's allocator keeps what is freed in its arenas
//! (one per thread that allocated, up to 8 per core) for reuse and returns it to the system only from the
//! top of each heap, so after the blocking pool's threads have built and freed a few maps the process's
//! RSS sat 680–900 MiB above its live heap in the 60-minute soak (BENCHMARKS.md, issue 16 §5).
//! [`release_freed_memory`] runs glibc's `malloc_trim`, which returns every arena's free pages; a site
//! calls it after each session end, on a thread of its own ([`release_freed_memory_in_background`]):
//! with a GiB freed it takes 0.1–0.5 s, which the site's next change should not wait for.
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

/// [`release_freed_memory`] on a short-lived thread of its own, unless one is still running (a replay
/// ends hundreds of sessions in a row: one release at a time is enough).
pub fn release_freed_memory_in_background() {
    static RUNNING: AtomicBool = AtomicBool::new(false);
    if RUNNING.swap(true, Ordering::AcqRel) {
        return;
    }
    let spawned = std::thread::Builder::new()
        .name("memory-release".into())
        .spawn(|| {
            release_freed_memory();
            RUNNING.store(false, Ordering::Release);
        });
    if spawned.is_err() {
        RUNNING.store(false, Ordering::Release);
    }
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
