//! Resource use of this process, for reports.

/// Peak resident set size of this process in MiB (`VmHWM` from `/proc/self/status`), if the platform
/// reports it.
pub fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Resident set size of this process now, in MiB (`VmRSS` from `/proc/self/status`), if the platform
/// reports it.
pub fn current_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// CPU time (user + system) this process has used so far, seconds (`/proc/self/stat`, in clock ticks of
/// 1/100 s, the value of `CLK_TCK` on Linux), if the platform reports it.
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name (field 2) may hold spaces; the fields after its closing parenthesis are fixed.
    let rest = stat.get(stat.rfind(')')? + 1..)?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line, 12 and 13 after the parenthesis.
    let user: f64 = fields.get(11)?.parse().ok()?;
    let system: f64 = fields.get(12)?.parse().ok()?;
    Some((user + system) / 100.0)
}

/// CPU time the calling thread has run so far, milliseconds (`/proc/thread-self/schedstat`, in
/// nanoseconds), if the platform reports it: the cost of work done on this thread whatever else the
/// machine runs (wall time on a loaded machine measures the machine).
pub fn thread_cpu_ms() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: f64 = text.split_whitespace().next()?.parse().ok()?;
    Some(ns * 1e-6)
}

#[cfg(test)]
mod tests {
    #[test]
    #[cfg(target_os = "linux")]
    fn peak_rss_is_positive_on_linux() {
        assert!(super::peak_rss_mb().is_some_and(|mb| mb > 0.0));
    }

    /// Spins until `read` has grown by more than `by`, or 20 s of wall time have passed (a loaded machine
    /// may give this thread only a fraction of a core); returns the readings before and after.
    #[cfg(target_os = "linux")]
    fn spin_until_it_grows(read: impl Fn() -> f64, by: f64) -> (f64, f64) {
        let before = read();
        let started = std::time::Instant::now();
        let mut x = 0u64;
        let mut after = before;
        while after - before <= by && started.elapsed() < std::time::Duration::from_secs(20) {
            for _ in 0..1_000_000 {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
            }
            std::hint::black_box(x);
            after = read();
        }
        (before, after)
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn thread_cpu_time_grows_with_work() {
        let (before, after) =
            spin_until_it_grows(|| super::thread_cpu_ms().expect("thread cpu time"), 50.0);
        assert!(after - before > 50.0, "{before} -> {after}");
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn current_rss_is_positive_and_at_most_the_peak_on_linux() {
        let now = super::current_rss_mb().expect("VmRSS");
        let peak = super::peak_rss_mb().expect("VmHWM");
        assert!(
            now > 0.0 && now <= peak + 1e-9,
            "{now} MiB now, {peak} MiB peak"
        );
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn cpu_time_grows_with_work() {
        let (before, after) = spin_until_it_grows(|| super::cpu_seconds().expect("cpu time"), 0.1);
        assert!(after - before > 0.1, "{before} -> {after}");
    }

    /// Without `/proc` every reading is `None`, so reports leave the field out instead of showing a
    /// made-up figure. (Android has Linux's `/proc`, so it is left out of this check.)
    #[test]
    #[cfg(not(any(target_os = "linux", target_os = "android")))]
    fn every_reading_is_none_without_procfs() {
        assert_eq!(super::peak_rss_mb(), None);
        assert_eq!(super::current_rss_mb(), None);
        assert_eq!(super::cpu_seconds(), None);
        assert_eq!(super::thread_cpu_ms(), None);
    }
}
