//! When a site was last asked for something its map answers: kept by the site task, and touched too by
//! the handles that answer a robot from the published version beside the task (so that a site whose
//! robots keep fetching its map is not idle).

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use tokio::time::Instant;

/// The time of a site's latest request (on tokio's clock, so paused-time tests see it move).
#[derive(Debug)]
pub(crate) struct RequestClock {
    epoch: Instant,
    /// Nanoseconds from `epoch` to the latest request (only ever grows).
    latest_ns: AtomicU64,
}

impl RequestClock {
    /// A clock whose latest request is now.
    pub fn new() -> Self {
        Self {
            epoch: Instant::now(),
            latest_ns: AtomicU64::new(0),
        }
    }

    /// Notes a request now.
    pub fn touch(&self) {
        let ns = u64::try_from(self.epoch.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.latest_ns.fetch_max(ns, Ordering::Relaxed);
    }

    /// Time since the latest request.
    pub fn idle(&self) -> Duration {
        (self.epoch + Duration::from_nanos(self.latest_ns.load(Ordering::Relaxed))).elapsed()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn a_touch_restarts_the_idle_time_and_time_never_goes_back() {
        let clock = RequestClock::new();
        tokio::time::advance(Duration::from_secs(5)).await;
        assert_eq!(clock.idle(), Duration::from_secs(5));
        clock.touch();
        assert_eq!(clock.idle(), Duration::ZERO);
        tokio::time::advance(Duration::from_secs(2)).await;
        assert_eq!(clock.idle(), Duration::from_secs(2));
    }
}
