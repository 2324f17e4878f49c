//! A scanner's period, as the median of its last intervals between stamps, and whether a stamp came in a
//! burst: what the stages that judge stamps ([`super::ScanBacklog`], [`super::OdometryClock`]) share.

use std::collections::VecDeque;

/// Scan intervals the period is the median of.
pub const PERIOD_WINDOW: usize = 128;
/// Scans of one burst: stamps closer than this share of the period.
pub const BURST_INTERVAL_SHARE: f64 = 0.2;

/// The median of the last [`PERIOD_WINDOW`] intervals between scans' stamps.
#[derive(Clone, Debug, Default)]
pub struct ScanPeriod {
    /// Oldest first, seconds.
    intervals: VecDeque<f64>,
    period_s: Option<f64>,
}

impl ScanPeriod {
    /// Takes the interval (seconds) between two consecutive scans' stamps.
    pub fn add(&mut self, interval_s: f64) {
        if self.intervals.len() == PERIOD_WINDOW {
            self.intervals.pop_front();
        }
        self.intervals.push_back(interval_s);
        let mut sorted: Vec<f64> = self.intervals.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        self.period_s = sorted.get(sorted.len() / 2).copied();
    }

    /// The period, seconds (`None` before the first interval); of an even count, the upper middle one.
    pub fn seconds(&self) -> Option<f64> {
        self.period_s
    }

    /// Whether an interval (seconds) is one between two scans of a burst.
    pub fn within_burst(&self, interval_s: f64) -> bool {
        self.period_s
            .is_some_and(|period| interval_s < BURST_INTERVAL_SHARE * period)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_period_is_the_median_of_the_last_intervals() {
        let mut period = ScanPeriod::default();
        assert_eq!(period.seconds(), None);
        assert!(!period.within_burst(0.0));
        for interval in [0.2, 0.0005, 0.2, 0.21, 0.0005] {
            period.add(interval);
        }
        assert_eq!(period.seconds(), Some(0.2));
        assert!(period.within_burst(0.0005) && !period.within_burst(0.05));
        for _ in 0..PERIOD_WINDOW {
            period.add(0.1);
        }
        assert_eq!(period.seconds(), Some(0.1));
    }
}
