//! Scans a stalled driver delivered at once, put back at the times they were taken.
//!
//! A scanner's driver that stamps scans when it reads them (many do) delivers a backlog in a burst after
//! the host starved it: several scans stamped within a millisecond, after a gap about as long as the scans
//! they carry, while the odometry, another process, kept coming through the gap. Taken at those stamps, the
//! first scan of the burst is predicted where the odometry says the robot is at the burst's end, up to the
//! whole stall of driving ahead of where it was scanned, and the rest where the odometry says it did not
//! move: LLO tears (the robustness suite's `scanburst`: ACES 4.2 m, MIT CSAIL 6.0 m; see
//! docs/BENCHMARK-HISTORY.md "Session 67"). [`ScanBacklog`] re-times such a burst into its gap, one scan
//! period apart and ending at its last stamp. It is left alone where the odometry fell silent in the gap
//! too (one logger stalled for both: the burst then holds both streams in the order they came, which is
//! already right; Intel's recording is stamped so) or where the burst holds fewer scans than the gap is
//! missing (scans lost, not held back).
//!
//! Events are taken in stamp order and handed on in stamp order but for the re-timed scans, which may come
//! after odometry stamped up to [`BACKLOG_GAP_PERIODS`] scan periods later than they (the collator,
//! [`super::LloCollator`], orders them after the odometry that covers them). Once a scan is
//! [`BACKLOG_GAP_PERIODS`] periods late, everything after it is held until the next scans show whether they
//! are a backlog, [`MAX_BACKLOG_HOLD_S`] at most.

use super::{ScanPeriod, SensorEvent, Timestamp};

/// A gap: this many scan periods without a scan (the period: [`ScanPeriod`]).
pub const BACKLOG_GAP_PERIODS: f64 = 3.0;
/// A backlog: the burst holds at least this share of the scans its gap is missing (gap / period).
pub const MIN_BACKLOG_SHARE: f64 = 0.7;
/// The odometry kept coming through the gap: it was never silent for more than this share of it.
pub const MAX_ODOMETRY_SILENCE_SHARE: f64 = 0.5;
/// Longest time (seconds of stream time) events are held waiting for scans after a gap; then they go on
/// as they are.
pub const MAX_BACKLOG_HOLD_S: f64 = 5.0;

/// One re-timed scan: the stamp it came with and the time it is now given.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Retimed {
    /// The scan's own stamp.
    pub stamped: Timestamp,
    /// When it was taken, as recovered.
    pub taken: Timestamp,
}

/// The stage (see the module docs): push events in stamp order, take what comes out.
#[derive(Debug, Default)]
pub struct ScanBacklog {
    /// The scanner's period.
    period: ScanPeriod,
    /// The stamp of the last scan pushed.
    last_scan: Option<Timestamp>,
    /// The last time the odometry spoke since `last_scan` (or `last_scan` itself), and its longest silence
    /// so far since `last_scan`.
    odometry_mark: Option<Timestamp>,
    longest_silence_s: f64,
    /// Events held since a gap began, in the order they came.
    held: Vec<SensorEvent>,
    /// The gap under way: the last scan before it.
    gap_after: Option<Timestamp>,
    /// The burst under way after the gap: its first and last scans' stamps, its scans, and the
    /// odometry's longest silence in the gap.
    burst: Option<Burst>,
    /// Scans re-timed so far, until taken by [`Self::take_retimed`].
    retimed: Vec<Retimed>,
}

#[derive(Clone, Copy, Debug)]
struct Burst {
    first: Timestamp,
    last: Timestamp,
    scans: usize,
    silence_s: f64,
}

impl ScanBacklog {
    /// Takes the next event (in stamp order) and appends to `out` what can go on now.
    pub fn push(&mut self, event: SensorEvent, out: &mut Vec<SensorEvent>) {
        let time = event.time();
        let period = self.period.seconds();
        if let Some(burst) = self.burst
            && period.is_some()
            && !self.period.within_burst(time.seconds_since(burst.last))
        {
            self.resolve(out);
        }
        if let Some(after) = self.gap_after
            && self.burst.is_none()
            && time.seconds_since(after) > MAX_BACKLOG_HOLD_S
        {
            self.release(out);
        }
        match &event {
            SensorEvent::Scan(_) => self.push_scan(event, period, out),
            SensorEvent::Odometry(_) => {
                if self.burst.is_none() {
                    self.note_odometry(time);
                }
                self.push_other(event, period, out);
            }
            SensorEvent::Imu(_) => self.push_other(event, period, out),
        }
    }

    /// The end of the stream: hands on everything still held.
    pub fn finish(&mut self, out: &mut Vec<SensorEvent>) {
        // Resolving a burst (or none) hands on everything held.
        self.resolve(out);
    }

    /// The scans re-timed since the last call.
    pub fn take_retimed(&mut self) -> Vec<Retimed> {
        std::mem::take(&mut self.retimed)
    }

    /// `events` (in stamp order) with every backlog re-timed, and the scans re-timed.
    pub fn retime(events: &[SensorEvent]) -> (Vec<SensorEvent>, Vec<Retimed>) {
        let mut stage = Self::default();
        let mut out = Vec::with_capacity(events.len());
        for event in events {
            stage.push(event.clone(), &mut out);
        }
        stage.finish(&mut out);
        (out, stage.take_retimed())
    }

    fn push_scan(&mut self, event: SensorEvent, period: Option<f64>, out: &mut Vec<SensorEvent>) {
        let time = event.time();
        if let Some(last) = self.last_scan {
            self.period.add(time.seconds_since(last));
        }
        if let Some(burst) = &mut self.burst {
            // Closer than the burst interval to the last (else the burst was resolved above).
            burst.last = time;
            burst.scans += 1;
            self.held.push(event);
        } else if let Some(after) = self.gap_after {
            let gap_is_long =
                period.is_some_and(|p| time.seconds_since(after) >= BACKLOG_GAP_PERIODS * p);
            if gap_is_long {
                let silence_s = self.silence_until(time);
                self.burst = Some(Burst {
                    first: time,
                    last: time,
                    scans: 1,
                    silence_s,
                });
                self.held.push(event);
            } else {
                self.release(out);
                out.push(event);
            }
        } else {
            out.push(event);
        }
        self.last_scan = Some(time);
        self.odometry_mark = Some(time);
        self.longest_silence_s = 0.0;
    }

    fn push_other(&mut self, event: SensorEvent, period: Option<f64>, out: &mut Vec<SensorEvent>) {
        if self.gap_after.is_some() {
            self.held.push(event);
            return;
        }
        let late = match (self.last_scan, period) {
            (Some(last), Some(p)) => event.time().seconds_since(last) >= BACKLOG_GAP_PERIODS * p,
            _ => false,
        };
        if late {
            self.gap_after = self.last_scan;
            self.held.push(event);
        } else {
            out.push(event);
        }
    }

    fn note_odometry(&mut self, time: Timestamp) {
        if let Some(mark) = self.odometry_mark {
            self.longest_silence_s = self.longest_silence_s.max(time.seconds_since(mark));
        }
        self.odometry_mark = Some(time);
    }

    /// The odometry's longest silence since the last scan, up to `time`.
    fn silence_until(&self, time: Timestamp) -> f64 {
        self.odometry_mark.map_or(f64::INFINITY, |mark| {
            self.longest_silence_s.max(time.seconds_since(mark))
        })
    }

    /// The burst is over: re-time it if it is a backlog, then hand on everything held.
    fn resolve(&mut self, out: &mut Vec<SensorEvent>) {
        let (Some(burst), Some(after), Some(period)) =
            (self.burst.take(), self.gap_after, self.period.seconds())
        else {
            self.release(out);
            return;
        };
        let gap = burst.first.seconds_since(after);
        let n = burst.scans as f64;
        let backlog = burst.scans >= 2
            && burst.silence_s < MAX_ODOMETRY_SILENCE_SHARE * gap
            && n >= MIN_BACKLOG_SHARE * gap / period;
        if backlog {
            let spacing = period.min(gap / n);
            let mut k = 0usize;
            for event in &mut self.held {
                if let SensorEvent::Scan(scan) = event
                    && scan.time >= burst.first
                {
                    let taken = burst
                        .last
                        .offset_by(-((burst.scans - 1 - k) as f64) * spacing);
                    self.retimed.push(Retimed {
                        stamped: scan.time,
                        taken,
                    });
                    scan.time = taken;
                    k += 1;
                }
            }
            // Stable: what was held keeps its order where stamps tie.
            self.held.sort_by_key(SensorEvent::time);
        }
        self.release(out);
    }

    /// Hands on everything held and ends the gap.
    fn release(&mut self, out: &mut Vec<SensorEvent>) {
        out.append(&mut self.held);
        self.gap_after = None;
        self.burst = None;
    }
}

#[cfg(test)]
mod tests;
