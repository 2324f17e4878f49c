//! The odometry's clock against the scanner's: the offset between their stamps, estimated online.
//!
//! Wheel odometry and the laser come from different drivers, often different processes or computers, and
//! their stamps rarely agree: against their scans, ACES's odometry is stamped 0.09 s early, MIT CSAIL's
//! 0.14 s, Intel's not at all, and the robustness suite's `lag`, 0.1 s late, adds 0.10 s to each
//! (docs/BENCHMARK-HISTORY.md "Session 69"). [`OdometryClock`] estimates the offset as calibration tools
//! do, from the data: the heading LLO matched over each half second against the odometry's heading change
//! over the same span moved by each candidate offset (every [`OFFSET_STEP_S`] within ±[`MAX_OFFSET_S`]);
//! the offset whose summed error (each span's capped at [`ERROR_CAP_RAD`]) is least over every span since
//! the start, once the robot has turned [`MIN_TURN_RAD`] in all (turning is what tells offsets apart). A
//! fixed offset is estimated; a clock that drifts is not followed. Scans stamped in a burst (a logger that
//! stalled and stamped what it held) carry no time to measure against and bound no span.
//!
//! The estimate is reported (`offline`'s report), not applied: handing the odometry on at its stamps less
//! the offset mends `lag` on Intel exactly, but across the suite it tore ACES `range4` (with a fixed shift
//! too) and the `burst` variants, where the logger stamps scans and odometry together and the order they
//! came in is the only pairing left (the same session's section).

use std::collections::VecDeque;

use super::{OdometryReading, ScanPeriod, Timestamp};
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};

/// Largest offset considered between the odometry's stamps and the scans', seconds (either way).
pub const MAX_OFFSET_S: f64 = 0.3;
/// Spacing of the offsets tried, seconds.
pub const OFFSET_STEP_S: f64 = 0.01;
/// Heading changes are compared over spans of at least this (seconds), from one matched scan to the first
/// one this much later...
pub const PAIR_SPAN_S: f64 = 0.5;
/// ... and of at most this: a longer gap between matched scans starts a new span.
pub const MAX_PAIR_SPAN_S: f64 = 1.0;
/// One span's error counts at most this much (radians): a scan matched wrong, or odometry that slipped,
/// does not decide the estimate.
pub const ERROR_CAP_RAD: f64 = 0.2;
/// The robot must have turned this much (radians, summed over the spans) before an offset is estimated:
/// driving straight, every offset fits.
pub const MIN_TURN_RAD: f64 = std::f64::consts::TAU;
/// Odometry kept for the estimate beyond what pending spans need, seconds.
const ODOMETRY_KEEP_S: f64 = MAX_PAIR_SPAN_S + 2.0 * MAX_OFFSET_S + 1.0;
/// Spans waiting for odometry to cover them: beyond this many, the oldest are given up.
const MAX_PENDING_SPANS: usize = 64;

/// Matched heading over one span, waiting until the odometry covers the span moved by every offset.
#[derive(Clone, Copy, Debug)]
struct Span {
    from: Timestamp,
    to: Timestamp,
    /// The heading LLO matched at `to` less the one at `from`, radians.
    turn: f64,
}

/// The last scan LLO matched, and whether the interval before it was not within a burst.
#[derive(Clone, Copy, Debug)]
struct LastMatch {
    time: Timestamp,
    heading: f64,
    steady_before: bool,
}

/// The estimate (see the module docs).
#[derive(Debug)]
pub struct OdometryClock {
    /// The offset estimated, in steps (`None` before the robot turned enough).
    offset_steps: Option<i32>,
    /// Summed capped error per offset tried, from `-MAX_OFFSET_S` upwards.
    error: Vec<f64>,
    /// Summed absolute matched turn of the spans so far, radians.
    turned: f64,
    /// The period of the matched scans' stamps.
    period: ScanPeriod,
    last_match: Option<LastMatch>,
    /// The last steady matched scan a span may start at: its time and heading.
    span_start: Option<(Timestamp, f64)>,
    pending: VecDeque<Span>,
    /// Odometry as stamped: time and heading.
    odometry: VecDeque<(Timestamp, f64)>,
}

impl Default for OdometryClock {
    fn default() -> Self {
        Self {
            offset_steps: None,
            error: vec![0.0; 2 * max_steps() as usize + 1],
            turned: 0.0,
            period: ScanPeriod::default(),
            last_match: None,
            span_start: None,
            pending: VecDeque::new(),
            odometry: VecDeque::new(),
        }
    }
}

fn max_steps() -> i32 {
    (MAX_OFFSET_S / OFFSET_STEP_S).round() as i32
}

fn seconds(steps: i32) -> f64 {
    f64::from(steps) * OFFSET_STEP_S
}

impl OdometryClock {
    /// The offset estimated, seconds: how late the odometry is stamped against the scans (negative:
    /// early); `None` until the robot has turned enough to tell.
    pub fn offset_s(&self) -> Option<f64> {
        self.offset_steps.map(seconds)
    }

    /// Takes an odometry reading (stamps in order; one not after the last is ignored).
    pub fn add_odometry(&mut self, reading: &OdometryReading) {
        let (time, heading) = (reading.time, reading.pose.theta());
        if self.odometry.back().is_some_and(|(t, _)| time <= *t) || !heading.is_finite() {
            return;
        }
        self.odometry.push_back((time, heading));
        let keep_from = self
            .pending
            .front()
            .map_or(time, |s| s.from.min(time))
            .offset_by(-ODOMETRY_KEEP_S);
        while self.odometry.len() > 2 && self.odometry.get(1).is_some_and(|(t, _)| *t <= keep_from)
        {
            self.odometry.pop_front();
        }
        self.score_pending();
    }

    /// LLO matched the scan taken at `time` at `local_from_tracking`: evidence for the estimate. A scan
    /// stamped in a burst (closer to a neighbour than [`super::BURST_INTERVAL_SHARE`] of the period: a
    /// logger that stalled and stamped what it held) carries no time to measure against, so only scans
    /// with neither neighbour that close bound the spans compared.
    pub fn scan_matched(&mut self, time: Timestamp, local_from_tracking: &Rigid2) {
        let heading = local_from_tracking.theta();
        let Some(last) = self.last_match else {
            self.last_match = Some(LastMatch {
                time,
                heading,
                steady_before: true,
            });
            return;
        };
        if time <= last.time {
            return;
        }
        let interval = time.seconds_since(last.time);
        let burst = self.period.within_burst(interval);
        self.period.add(interval);
        if last.steady_before && !burst {
            self.span_point(last.time, last.heading);
        }
        self.last_match = Some(LastMatch {
            time,
            heading,
            steady_before: !burst,
        });
    }

    /// A steady scan matched at `heading`: ends the span open (if long enough) and starts the next.
    fn span_point(&mut self, time: Timestamp, heading: f64) {
        if let Some((from, start_heading)) = self.span_start {
            let span = time.seconds_since(from);
            if span < PAIR_SPAN_S {
                return;
            }
            if span <= MAX_PAIR_SPAN_S {
                if self.pending.len() == MAX_PENDING_SPANS {
                    self.pending.pop_front();
                }
                self.pending.push_back(Span {
                    from,
                    to: time,
                    turn: normalize_angle(heading - start_heading),
                });
            }
        }
        self.span_start = Some((time, heading));
        self.score_pending();
    }

    /// The odometry's heading at `time` (interpolated between readings), if readings lie on both sides.
    fn odometry_heading(&self, time: Timestamp) -> Option<f64> {
        let i = self.odometry.partition_point(|(t, _)| *t <= time);
        let (ta, a) = *self.odometry.get(i.checked_sub(1)?)?;
        if ta == time {
            return Some(a);
        }
        let (tb, b) = *self.odometry.get(i)?;
        let s = time.seconds_since(ta) / tb.seconds_since(ta);
        Some(a + s * normalize_angle(b - a))
    }

    /// Scores the spans the odometry now covers under every offset, and takes a better offset if one is
    /// clear.
    fn score_pending(&mut self) {
        let Some(&(newest, _)) = self.odometry.back() else {
            return;
        };
        let mut scored = false;
        while let Some(span) = self.pending.front().copied()
            && newest.seconds_since(span.to) >= MAX_OFFSET_S
        {
            self.pending.pop_front();
            let errors: Option<Vec<f64>> = (-max_steps()..=max_steps())
                .map(|k| {
                    let d = seconds(k);
                    let odometry_turn = self.odometry_heading(span.to.offset_by(d))?
                        - self.odometry_heading(span.from.offset_by(d))?;
                    Some(
                        normalize_angle(span.turn - odometry_turn)
                            .abs()
                            .min(ERROR_CAP_RAD),
                    )
                })
                .collect();
            // A span the odometry does not cover under every offset says nothing about them all alike.
            let Some(errors) = errors else { continue };
            for (sum, e) in self.error.iter_mut().zip(errors) {
                *sum += e;
            }
            self.turned += span.turn.abs();
            scored = true;
        }
        if !scored || self.turned < MIN_TURN_RAD {
            return;
        }
        if let Some((best, _)) = self
            .error
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))
        {
            self.offset_steps = Some(best as i32 - max_steps());
        }
    }
}

#[cfg(test)]
mod tests;
