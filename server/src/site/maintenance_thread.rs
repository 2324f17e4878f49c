//! Work that may wait runs at a lower CPU priority than robots' data.
//!
//! A site's *maintenance* is what a session end sets off — the final optimization, trimming and
//! sparsification of the lifelong map — and building and writing the site's checkpoints. It is heavy
//! (tenths of a second to seconds of CPU per site) and nobody waits on it in real time: the robot that
//! ended its session has already been answered for its data, and the next session only needs it done
//! before it starts. What is waited on is every other robot's upload and every submap reaching the
//! fleet. When many sessions end at once (a fleet's shift ends: every site closes its sessions in the
//! same second), the maintenance of forty sites would otherwise share the cores evenly with those
//! uploads, and a 50-ms upload would take seconds.
//!
//! So maintenance runs on threads of its own at the lowest priority, nice 19 ([`MAINTENANCE_NICE`]):
//! the kernel gives them the CPU normal threads leave (on Linux each thread has its own nice value;
//! CFS weighs a nice-19 thread 15 against a default one's 1024, so forty maintenance threads together
//! weigh less than one upload's, and a lone one still gets a whole core). It never starves: a busy
//! server still gives each about 1.5 % of a core. Elsewhere the priority is left as it is.
//!
//! (Nice 10, weight 110, was measured first: forty sites' maintenance at once then still weighed as much
//! as four uploads, and the p95 of 40 sites × 2 robots stayed at 4.5 s; BENCHMARKS.md.)

use super::SiteError;

/// The nice value of maintenance threads (0 is the default, 19 the lowest priority).
pub(crate) const MAINTENANCE_NICE: i32 = 19;

/// Runs `f` on a new maintenance thread (named `site-maintenance`, at [`MAINTENANCE_NICE`]) and waits
/// for its result; `what` names the work in the error if the thread cannot start or `f` panics. A
/// thread of tokio's blocking pool waits for it (so the runtime counts the work as in flight, as it
/// does any blocking task: a paused test clock does not jump ahead of it).
pub(crate) async fn run_as_maintenance<T: Send + 'static>(
    what: &'static str,
    f: impl FnOnce() -> T + Send + 'static,
) -> Result<T, SiteError> {
    tokio::task::spawn_blocking(move || {
        std::thread::Builder::new()
            .name("site-maintenance".into())
            .spawn(move || {
                lower_this_threads_priority();
                f()
            })
            .map_err(|source| SiteError::ThreadStart { what, source })?
            .join()
            .map_err(|_| SiteError::Internal(format!("the {what} thread panicked")))
    })
    .await
    .map_err(SiteError::Worker)?
}

/// Raises the calling thread's nice value to [`MAINTENANCE_NICE`] (Linux; a failure only costs the
/// priority, so it is logged, not returned).
fn lower_this_threads_priority() {
    #[cfg(target_os = "linux")]
    {
        #[allow(unsafe_code)]
        // SAFETY: `setpriority` takes plain integers and has no preconditions; `who` 0 is the calling
        // thread on Linux.
        let failed = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, MAINTENANCE_NICE) } != 0;
        if failed {
            tracing::debug!(
                "cannot lower a maintenance thread's priority: {}",
                std::io::Error::last_os_error()
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The calling thread's nice value.
    #[cfg(target_os = "linux")]
    fn nice() -> i32 {
        #[allow(unsafe_code)]
        // SAFETY: `getpriority` takes plain integers and has no preconditions; `who` 0 is the calling
        // thread on Linux.
        unsafe {
            libc::getpriority(libc::PRIO_PROCESS, 0)
        }
    }

    #[tokio::test]
    async fn maintenance_returns_its_result() {
        assert_eq!(run_as_maintenance("test", || 42).await.unwrap(), 42);
    }

    #[cfg(target_os = "linux")]
    #[tokio::test]
    async fn maintenance_runs_at_the_lower_priority() {
        let nice = run_as_maintenance("test", nice).await.unwrap();
        // At least as low as asked (a server started nicer than 0 stays nicer).
        assert!(nice >= MAINTENANCE_NICE, "nice {nice}");
    }

    #[tokio::test]
    async fn a_panicking_maintenance_job_is_an_error_naming_it() {
        let error = run_as_maintenance("trimming", || -> u32 { panic!("boom") })
            .await
            .unwrap_err();
        assert!(error.to_string().contains("trimming"), "{error}");
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn the_callers_priority_is_left_alone() {
        let before = nice();
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        runtime.block_on(run_as_maintenance("test", || ())).unwrap();
        assert_eq!(before, nice());
    }
}
