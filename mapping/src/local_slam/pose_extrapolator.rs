//! Pose extrapolation between scans: where will the robot be at the next scan's time?
//!
//! With wheel odometry, the prediction is the last matched pose composed with the odometry motion
//! between the two times (interpolated between readings). An IMU, when present, supplies the rotation
//! instead (integrated yaw rate). Without either, a constant-velocity model from matched poses is used.
//! Velocities are only ever estimated over at least `MIN_VELOCITY_WINDOW_S`: recordings deliver
//! messages in bursts (Intel: thousands of intervals under 5 ms), and a velocity from a 0.2 ms gap is
//! noise. Readings that go back in time are dropped and counted. With `resume_from_before_a_stall` (the
//! default), an odometry stream that stalls (repeats one pose while the matched poses move) and comes
//! back with its backlog has that backlog composed on the last pose before the stall, not counted a
//! second time; with `resume_from_before_a_gap` (off by default), so has the motion a stream brings after
//! a gap in its readings, where the scans matched inside the gap already showed it.

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle, rigid2};
use crate::sensor::{ImuReading, OdometryReading, Timestamp};

/// Shortest time span a velocity is estimated over, seconds.
const MIN_VELOCITY_WINDOW_S: f64 = 0.05;
/// How long odometry may be held past its last reading before it is considered stale, seconds.
const MAX_ODOMETRY_HOLD_S: f64 = 0.5;
/// How much history is kept before the last matched pose, seconds.
const HISTORY_S: f64 = 2.0;
/// Matched motion while the odometry repeated one pose beyond which the robot was moving, not standing
/// still: metres …
const STALL_MIN_TRANSLATION_M: f64 = 0.1;
/// … or radians (5°).
const STALL_MIN_ROTATION_RAD: f64 = 5.0 * std::f64::consts::PI / 180.0;
/// Shortest span the odometry's rate before a stall is measured over, seconds.
const STALL_RATE_SPAN_S: f64 = 0.2;

/// How the extrapolator predicts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PoseExtrapolatorOptions {
    /// Shortest span a constant velocity is measured over, as a share of the time it is carried ahead
    /// (at least `MIN_VELOCITY_WINDOW_S`); 0 = only that floor. Default 0.5 (across a gap in the
    /// odometry, one scan's error is otherwise multiplied). Why:
    /// `docs/TUNING.md#llo-min-velocity-span-per-horizon`.
    pub min_velocity_span_per_horizon: f64,
    /// After the odometry stalled (repeated one pose while the matched poses moved) and resumed with
    /// its backlog, compose its motion on the last pose before the stall. Default true (on nine draws of
    /// the robustness suite, MIT CSAIL's `range4` runs over a bound 22 → 2, no cell's median 5 %
    /// worse). Why:
    /// `docs/TUNING.md#llo-resume-from-before-a-stall`.
    pub resume_from_before_a_stall: bool,
    /// After a gap in the odometry stream (no reading for more than 0.5 s) during which scans were matched,
    /// compose the motion the stream brings back on the last pose matched before the gap, where the poses
    /// matched inside the gap disagree with the odometry interpolated across it (more than 0.1 m or 5°)
    /// and the stream has brought at least half the difference by the predicted time (its motion came late,
    /// not wrong). Default false (on three draws of the robustness suite, Intel `lag` −24 % but still over
    /// its bound, 28 draws over a bound against 27). Why: `docs/TUNING.md#llo-resume-from-before-a-gap`.
    pub resume_from_before_a_gap: bool,
}

impl Default for PoseExtrapolatorOptions {
    fn default() -> Self {
        Self {
            min_velocity_span_per_horizon: 0.5,
            resume_from_before_a_stall: true,
            resume_from_before_a_gap: false,
        }
    }
}

/// Predicts poses from matched poses, odometry and IMU.
#[derive(Clone, Debug, Default)]
pub struct PoseExtrapolator {
    options: PoseExtrapolatorOptions,
    poses: VecDeque<(Timestamp, Rigid2)>,
    odometry: VecDeque<OdometryReading>,
    imu: VecDeque<ImuReading>,
    rejected: usize,
    /// The last matched pose at or before the last odometry reading's time.
    pose_at_last_reading: Option<(Timestamp, Rigid2)>,
    /// The last gap in the odometry stream, while the matched poses have not passed its end.
    gap: Option<OdometryGap>,
}

/// A span with no odometry reading longer than [`MAX_ODOMETRY_HOLD_S`], closed by a reading.
#[derive(Clone, Copy, Debug)]
struct OdometryGap {
    /// The reading before the gap.
    from: Timestamp,
    /// The reading that closed it.
    to: Timestamp,
    /// The last matched pose at or before `from`.
    pose_before: (Timestamp, Rigid2),
}

fn interpolate(a: &OdometryReading, b: &OdometryReading, t: Timestamp) -> Rigid2 {
    let span = b.time.seconds_since(a.time);
    let s = if span > 0.0 {
        (t.seconds_since(a.time) / span).clamp(0.0, 1.0)
    } else {
        1.0
    };
    let d = a.pose.inverse() * b.pose;
    a.pose * rigid2(s * d.x(), s * d.y(), s * d.theta())
}

impl PoseExtrapolator {
    /// An extrapolator with no data and the default options.
    pub fn new() -> Self {
        Self::default()
    }

    /// An extrapolator with no data.
    pub fn with_options(options: PoseExtrapolatorOptions) -> Self {
        Self {
            options,
            ..Self::default()
        }
    }

    /// Readings and poses refused because their time went backwards or they were not finite.
    pub fn rejected(&self) -> usize {
        self.rejected
    }

    /// Adds a wheel-odometry reading.
    pub fn add_odometry(&mut self, reading: &OdometryReading) {
        let finite = reading
            .pose
            .translation
            .vector
            .iter()
            .all(|v| v.is_finite())
            && reading.pose.theta().is_finite();
        if !finite
            || self
                .odometry
                .back()
                .is_some_and(|last| reading.time <= last.time)
        {
            self.rejected += 1;
            return;
        }
        if let Some(previous) = self.odometry.back()
            && reading.time.seconds_since(previous.time) > MAX_ODOMETRY_HOLD_S
        {
            let from = previous.time;
            self.gap = self
                .pose_at_last_reading
                .filter(|(t, _)| *t <= from)
                .map(|pose_before| OdometryGap {
                    from,
                    to: reading.time,
                    pose_before,
                });
        }
        if let Some(covered) = self.poses.iter().rev().find(|(t, _)| *t <= reading.time) {
            self.pose_at_last_reading = Some(*covered);
        }
        self.odometry.push_back(reading.clone());
        self.trim();
    }

    /// Adds an IMU reading.
    pub fn add_imu(&mut self, reading: &ImuReading) {
        if !reading.yaw_rate.is_finite()
            || self
                .imu
                .back()
                .is_some_and(|last| reading.time <= last.time)
        {
            self.rejected += 1;
            return;
        }
        self.imu.push_back(reading.clone());
        self.trim();
    }

    /// Adds a scan-matched pose (`local_from_tracking`).
    pub fn add_pose(&mut self, time: Timestamp, pose: Rigid2) {
        if self.poses.back().is_some_and(|(t, _)| time < *t) {
            self.rejected += 1;
            return;
        }
        if self.odometry.back().is_some_and(|o| time <= o.time) {
            self.pose_at_last_reading = Some((time, pose));
        }
        self.poses.push_back((time, pose));
        self.trim();
    }

    /// The time of the last matched pose.
    pub fn last_pose_time(&self) -> Option<Timestamp> {
        self.poses.back().map(|(t, _)| *t)
    }

    /// The motion between the last two matched poses, in the frame of the earlier one.
    pub fn last_motion(&self) -> Option<Rigid2> {
        let n = self.poses.len();
        let (_, before) = self.poses.get(n.checked_sub(2)?)?;
        let (_, last) = self.poses.back()?;
        Some(before.inverse() * last)
    }

    fn trim(&mut self) {
        let Some(&(last, _)) = self.poses.back() else {
            return;
        };
        while self.poses.len() > 2
            && self
                .poses
                .front()
                .is_some_and(|(t, _)| last.seconds_since(*t) > HISTORY_S)
        {
            self.poses.pop_front();
        }
        // A gap the matched poses have passed is of no more use.
        if self.gap.is_some_and(|g| last >= g.to) {
            self.gap = None;
        }
        // Keep one odometry reading at or before the last pose (the oldest pose kept, when a stall's backlog
        // may be composed on a pose before it), for interpolation.
        let mut keep_from = if self.options.resume_from_before_a_stall {
            self.poses.front().map_or(last, |(t, _)| *t)
        } else {
            last
        };
        if self.options.resume_from_before_a_gap {
            // A gap's pose before it needs the readings around it: kept while the stream is silent (the
            // last pose at or before its last reading) and while the gap may be used.
            let before_a_gap = self.gap.map(|g| g.pose_before.0);
            for t in [self.pose_at_last_reading.map(|(t, _)| t), before_a_gap]
                .into_iter()
                .flatten()
            {
                keep_from = keep_from.min(t);
            }
        }
        while self.odometry.len() > 2 && self.odometry.get(1).is_some_and(|o| o.time <= keep_from) {
            self.odometry.pop_front();
        }
        while self.imu.len() > 1 && self.imu.get(1).is_some_and(|i| i.time <= keep_from) {
            self.imu.pop_front();
        }
    }

    fn odometry_at(&self, t: Timestamp) -> Option<Rigid2> {
        let i = self.odometry.partition_point(|o| o.time <= t);
        match (
            i.checked_sub(1).and_then(|k| self.odometry.get(k)),
            self.odometry.get(i),
        ) {
            (Some(a), Some(b)) => Some(interpolate(a, b, t)),
            (Some(a), None) if t.seconds_since(a.time) <= MAX_ODOMETRY_HOLD_S => Some(a.pose),
            _ => None,
        }
    }

    /// Whether the wheel odometry reported exactly no motion between two times although a reading arrived
    /// in between: a stalled stream repeats its last pose, then carries the backlog at once (MIT CSAIL,
    /// 68 s after its first scan: frozen for 0.86 s in a 50°/s turn). A robot standing still looks the same.
    pub fn odometry_frozen(&self, from: Timestamp, to: Timestamp) -> bool {
        let arrived = self.odometry.iter().any(|o| o.time > from && o.time <= to);
        match (self.odometry_at(from), self.odometry_at(to)) {
            (Some(a), Some(b)) => arrived && a == b,
            _ => false,
        }
    }

    /// Integrated IMU yaw between two times, if the IMU covers the span.
    fn imu_rotation(&self, from: Timestamp, to: Timestamp) -> Option<f64> {
        let first = self.imu.front()?;
        if first.time > from || self.imu.back()?.time.seconds_since(to) < -MAX_ODOMETRY_HOLD_S {
            return None;
        }
        let mut angle = 0.0;
        let mut t = from;
        for (k, reading) in self.imu.iter().enumerate() {
            let next_time = self.imu.get(k + 1).map_or(to, |n| n.time.min(to));
            if next_time <= t {
                continue;
            }
            let start = if reading.time > t { reading.time } else { t };
            angle += reading.yaw_rate * next_time.seconds_since(start);
            t = next_time;
            if t >= to {
                break;
            }
        }
        Some(angle)
    }

    /// The motion over `dt` seconds at the velocity of the matched poses, measured over at least
    /// [`MIN_VELOCITY_WINDOW_S`] (and `min_velocity_span_per_horizon` × `dt`, at most the history kept;
    /// from the oldest pose kept when the history is shorter).
    fn constant_velocity_motion(&self, dt: f64) -> Rigid2 {
        let Some(&(t1, p1)) = self.poses.back() else {
            return Rigid2::identity();
        };
        // With `min_velocity_span_per_horizon`, a velocity is not carried far beyond the span it was
        // measured over (Intel: a pose matched 11° off, then a 0.65-s gap in the odometry; the velocity
        // of the last 0.08 s predicted a 68° turn that never happened).
        let window = (self.options.min_velocity_span_per_horizon * dt)
            .clamp(MIN_VELOCITY_WINDOW_S, HISTORY_S);
        let Some(&(t0, p0)) = self
            .poses
            .iter()
            .rev()
            .find(|(t, _)| t1.seconds_since(*t) >= window)
            .or_else(|| {
                self.poses
                    .front()
                    .filter(|(t, _)| t1.seconds_since(*t) >= MIN_VELOCITY_WINDOW_S)
            })
        else {
            return Rigid2::identity();
        };
        let span = t1.seconds_since(t0);
        let d = p0.inverse() * p1;
        let s = dt / span;
        rigid2(d.x() * s, d.y() * s, normalize_angle(d.theta()) * s)
    }

    /// Predicted `local_from_tracking` at `time` from matched poses alone (constant velocity), ignoring
    /// odometry and IMU: a second opinion for when odometry stalls or jumps.
    pub fn extrapolate_constant_velocity(&self, time: Timestamp) -> Rigid2 {
        let Some(&(last_time, last_pose)) = self.poses.back() else {
            return Rigid2::identity();
        };
        last_pose * self.constant_velocity_motion(time.seconds_since(last_time))
    }

    /// The matched pose the odometry's motion up to `time` is composed on: the last one, or the last one
    /// before a stall the stream has come back from with its backlog, or the last one before a gap whose
    /// motion came late (`resume_from_before_a_gap`).
    fn odometry_anchor(&self, time: Timestamp) -> Option<(Timestamp, Rigid2)> {
        let last = *self.poses.back()?;
        if self.options.resume_from_before_a_stall
            && let Some(before) = self.pose_before_a_resumed_stall(last, time)
        {
            return Some(before);
        }
        if self.options.resume_from_before_a_gap
            && let Some(before) = self.pose_before_a_gap(last, time)
        {
            return Some(before);
        }
        Some(last)
    }

    /// The last matched pose before a gap in the odometry that the pose `last` was matched in, once a
    /// reading has closed the gap and `time` is past it, if the odometry lost the gap's timing: the poses
    /// matched since the pose before it disagree with the odometry interpolated at `last` by more than
    /// [`STALL_MIN_TRANSLATION_M`] or [`STALL_MIN_ROTATION_RAD`], and by `time` the odometry has made up
    /// at least half the difference. A logger that stalled and stamped its backlog at once, with the
    /// odometry stamped later than the scans (Intel with the suite's `lag`: 2.2 s of neither, then 11
    /// scans and 22 readings within 10 ms, the readings 0.1 s after the scans): the burst's scans were
    /// matched with no odometry and moved the robot 0.55 m themselves, while the odometry interpolated
    /// across the gap puts almost all of that motion after them, and it was counted twice (0.78 m
    /// predicted for a 0.06-m step, matched in a corridor as predicted).
    fn pose_before_a_gap(
        &self,
        (last_time, last_pose): (Timestamp, Rigid2),
        time: Timestamp,
    ) -> Option<(Timestamp, Rigid2)> {
        let gap = self.gap?;
        // Inside the gap the odometry still says nothing of the motion since the pose before it: composed
        // there, the prediction would be pulled back to it.
        if !(gap.from < last_time && last_time < gap.to && time >= gap.to) {
            return None;
        }
        let (before_time, before_pose) = gap.pose_before;
        let matched = before_pose.inverse() * last_pose;
        let odometry_before = self.odometry_at(before_time)?;
        let at_last = odometry_before.inverse() * self.odometry_at(last_time)?;
        let by_time = odometry_before.inverse() * self.odometry_at(time)?;
        let residual = |odometry: Rigid2| {
            let d = odometry.inverse() * matched;
            d.translation.vector.norm() + normalize_angle(d.theta()).abs()
        };
        let d = at_last.inverse() * matched;
        let disagrees = d.translation.vector.norm() > STALL_MIN_TRANSLATION_M
            || normalize_angle(d.theta()).abs() > STALL_MIN_ROTATION_RAD;
        // The odometry lost the gap's timing: interpolated at the last pose it disagrees with the poses
        // matched since, yet by `time` it has brought at least half of what they matched beyond it. Where
        // it still disagrees as much, the odometry is the one that is wrong (ACES, 540 s: a 3-s gap in both
        // streams over a turn the odometry put at 61° and the scans at 81°), and the last pose stays the
        // anchor.
        (disagrees && residual(by_time) < 0.5 * residual(at_last)).then_some(gap.pose_before)
    }

    /// The last matched pose before the odometry stalled, if the stream repeated one pose while the matched
    /// poses up to `last` moved, has resumed by `time`, and resumed with the stall's backlog.
    fn pose_before_a_resumed_stall(
        &self,
        (last_time, last_pose): (Timestamp, Rigid2),
        time: Timestamp,
    ) -> Option<(Timestamp, Rigid2)> {
        let frozen = self.odometry_at(last_time)?;
        if self.odometry_at(time)? == frozen {
            // Still stalled, or standing still: nothing has come back to count twice.
            return None;
        }
        let mut first_frozen = (last_time, last_pose);
        let mut before = None;
        for &(t, pose) in self.poses.iter().rev().skip(1) {
            if self.odometry_at(t)? != frozen {
                before = Some((t, pose));
                break;
            }
            first_frozen = (t, pose);
        }
        let before = before?;
        let arrived = self
            .odometry
            .iter()
            .any(|o| o.time > first_frozen.0 && o.time <= last_time);
        let moved = first_frozen.1.inverse() * last_pose;
        let moving = moved.translation.vector.norm() > STALL_MIN_TRANSLATION_M
            || normalize_angle(moved.theta()).abs() > STALL_MIN_ROTATION_RAD;
        (arrived && moving && self.resumed_with_a_backlog(last_time, frozen)).then_some(before)
    }

    /// Whether the stream, frozen at `frozen` at `last_time`, came back carrying the motion of its stall
    /// rather than having lost it: a stalled driver either delivers the ticks it held back or drops them.
    /// The jump of the first reading off `frozen` is judged against the stream's own rate before the stall,
    /// carried over the stall and that reading's step (held back) or over the step alone (dropped),
    /// whichever it is nearer (metres plus radians). `false` where the rate cannot be measured.
    fn resumed_with_a_backlog(&self, last_time: Timestamp, frozen: Rigid2) -> bool {
        let Some(r) = self
            .odometry
            .iter()
            .position(|o| o.time > last_time && o.pose != frozen)
        else {
            return false;
        };
        let Some(last_frozen) = r.checked_sub(1).map(|k| &self.odometry[k]) else {
            return false;
        };
        if last_frozen.pose != frozen {
            return false;
        }
        let first = self
            .odometry
            .iter()
            .take(r)
            .rposition(|o| o.pose != frozen)
            .map_or(0, |k| k + 1);
        let (resumed, stall_start) = (&self.odometry[r], &self.odometry[first]);
        let Some(rate_from) = self
            .odometry
            .iter()
            .take(first)
            .rev()
            .find(|o| stall_start.time.seconds_since(o.time) >= STALL_RATE_SPAN_S)
            .or_else(|| self.odometry.front().filter(|o| o.time < stall_start.time))
        else {
            return false;
        };
        let span = stall_start.time.seconds_since(rate_from.time);
        let rate = rate_from.pose.inverse() * stall_start.pose;
        let at_rate = |seconds: f64| {
            let k = seconds / span;
            rigid2(
                rate.x() * k,
                rate.y() * k,
                normalize_angle(rate.theta()) * k,
            )
        };
        let jump = frozen.inverse() * resumed.pose;
        let gap = |expected: Rigid2| {
            let d = expected.inverse() * jump;
            d.translation.vector.norm() + normalize_angle(d.theta()).abs()
        };
        gap(at_rate(resumed.time.seconds_since(stall_start.time)))
            < gap(at_rate(resumed.time.seconds_since(last_frozen.time)))
    }

    /// Predicted `local_from_tracking` at `time` (identity before the first matched pose).
    pub fn extrapolate(&self, time: Timestamp) -> Rigid2 {
        let Some((last_time, last_pose)) = self.odometry_anchor(time) else {
            return Rigid2::identity();
        };
        let mut motion = match (self.odometry_at(last_time), self.odometry_at(time)) {
            (Some(a), Some(b)) => a.inverse() * b,
            _ => self.constant_velocity_motion(time.seconds_since(last_time)),
        };
        if let Some(yaw) = self.imu_rotation(last_time, time) {
            motion = rigid2(motion.x(), motion.y(), yaw);
        }
        last_pose * motion
    }
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;

    use super::*;

    fn s(secs: f64) -> Timestamp {
        Timestamp::from_secs_f64(secs)
    }

    #[test]
    fn odometry_motion_is_applied_in_the_robot_frame() {
        let mut e = PoseExtrapolator::new();
        e.add_pose(s(0.0), rigid2(10.0, 0.0, std::f64::consts::FRAC_PI_2));
        e.add_odometry(&OdometryReading {
            time: s(0.0),
            pose: rigid2(0.0, 0.0, 0.0),
        });
        e.add_odometry(&OdometryReading {
            time: s(1.0),
            pose: rigid2(1.0, 0.0, 0.0),
        });
        // Halfway: 0.5 m forward, which is +y in the local frame.
        assert_relative_eq!(
            e.extrapolate(s(0.5)),
            rigid2(10.0, 0.5, std::f64::consts::FRAC_PI_2),
            epsilon = 1e-9
        );
    }

    /// Turning at 1 rad/s, scans every 0.2 s matched right up to 0.8 s; the odometry stream repeats its
    /// pose from 0.3 s to 0.9 s, then (unless `until` stops it first) its reading at 1.0 s says `resumed`.
    fn stalled_turn(resume: bool, until: u32, resumed: f64) -> PoseExtrapolator {
        let mut e = PoseExtrapolator::with_options(PoseExtrapolatorOptions {
            resume_from_before_a_stall: resume,
            ..PoseExtrapolatorOptions::default()
        });
        for k in 0..=until {
            let t = 0.1 * f64::from(k);
            let reported = match k {
                3..=9 => 0.3,
                10 => resumed,
                _ => t,
            };
            e.add_odometry(&OdometryReading {
                time: s(t),
                pose: rigid2(0.0, 0.0, reported),
            });
            if k % 2 == 0 && k < 10 {
                e.add_pose(s(t), rigid2(0.0, 0.0, t));
            }
        }
        e
    }

    #[test]
    fn a_stalled_streams_backlog_is_composed_on_the_pose_before_the_stall() {
        // The reading at 1.0 s carries the backlog: the whole turn since 0.3 s.
        let e = stalled_turn(true, 10, 1.0);
        assert_relative_eq!(e.extrapolate(s(1.0)), rigid2(0.0, 0.0, 1.0), epsilon = 1e-9);
        // Composed on the last matched pose, the backlog counts the stall's turn twice.
        let counted_twice = stalled_turn(false, 10, 1.0);
        assert_relative_eq!(
            counted_twice.extrapolate(s(1.0)).theta(),
            1.5,
            epsilon = 1e-9
        );
    }

    #[test]
    fn a_stall_that_lost_its_ticks_is_composed_on_the_last_pose() {
        // The driver dropped the ticks of the stall: 0.1 rad after it, not the 0.7 of the turn since 0.3 s.
        let e = stalled_turn(true, 10, 0.4);
        assert_relative_eq!(e.extrapolate(s(1.0)), rigid2(0.0, 0.0, 0.9), epsilon = 1e-9);
    }

    #[test]
    fn a_stream_still_stalled_predicts_from_the_last_pose() {
        // Nothing has come back yet: the prediction is not pulled back to before the stall.
        let e = stalled_turn(true, 9, 0.0);
        assert_relative_eq!(e.extrapolate(s(0.9)), rigid2(0.0, 0.0, 0.8), epsilon = 1e-9);
    }

    #[test]
    fn a_robot_standing_still_is_not_a_stall() {
        let mut e = PoseExtrapolator::with_options(PoseExtrapolatorOptions {
            resume_from_before_a_stall: true,
            ..PoseExtrapolatorOptions::default()
        });
        for k in 0..=10 {
            let t = 0.1 * f64::from(k);
            let x = match k {
                0..=2 => t,
                10 => 0.35,
                _ => 0.3,
            };
            e.add_odometry(&OdometryReading {
                time: s(t),
                pose: rigid2(x, 0.0, 0.0),
            });
            if k % 2 == 0 && k < 10 {
                // LLO sees the robot stop 2 cm short of where the odometry says.
                e.add_pose(s(t), rigid2(x.min(0.28), 0.0, 0.0));
            }
        }
        assert_relative_eq!(
            e.extrapolate(s(1.0)),
            rigid2(0.33, 0.0, 0.0),
            epsilon = 1e-9
        );
    }

    /// A reading of straight-line odometry at `x` metres.
    fn reading_at(t: f64, x: f64) -> OdometryReading {
        OdometryReading {
            time: s(t),
            pose: rigid2(x, 0.0, 0.0),
        }
    }

    /// Readings every 0.1 s up to 0.3 s (x = t) and a pose matched at 0.2 s: the stream before a gap.
    fn before_a_gap(option: bool) -> PoseExtrapolator {
        let mut e = PoseExtrapolator::with_options(PoseExtrapolatorOptions {
            resume_from_before_a_gap: option,
            ..PoseExtrapolatorOptions::default()
        });
        for k in 0..=3 {
            let t = 0.1 * f64::from(k);
            e.add_odometry(&reading_at(t, t));
        }
        e.add_pose(s(0.2), rigid2(0.2, 0.0, 0.0));
        e
    }

    /// A logger stalls 2.1 s, then stamps its backlog at once, the odometry 0.1 s after the scans: after
    /// [`before_a_gap`], no reading until 2.5 s, where a burst brings the stall's metre; scans matched in
    /// the burst at 2.40–2.42 s, already 1 m on. Handed over: the reading at 2.5 s (still 0.33 m), or with
    /// `whole_burst` the burst's too.
    fn lagged_burst(option: bool, whole_burst: bool) -> PoseExtrapolator {
        let mut e = before_a_gap(option);
        e.add_odometry(&reading_at(2.5, 0.33));
        for (t, x) in [(2.40, 1.0), (2.41, 1.1), (2.42, 1.2)] {
            e.add_pose(s(t), rigid2(x, 0.0, 0.0));
        }
        if whole_burst {
            e.add_odometry(&reading_at(2.51, 1.3));
            e.add_odometry(&reading_at(2.6, 1.4));
        }
        e
    }

    #[test]
    fn a_gaps_backlog_is_composed_on_the_pose_before_the_gap() {
        // The odometry's metre over the gap is the metre the burst's scans already matched.
        let e = lagged_burst(true, true);
        assert_relative_eq!(e.extrapolate(s(2.6)), rigid2(1.4, 0.0, 0.0), epsilon = 1e-9);
        // Composed on the last pose, the odometry interpolated at 2.42 s holds only 3 cm of it: the rest
        // is counted twice.
        let counted_twice = lagged_burst(false, true).extrapolate(s(2.6)).x();
        assert!(counted_twice > 2.2, "{counted_twice}");
    }

    #[test]
    fn across_a_gap_the_odometry_got_wrong_the_last_pose_stays_the_anchor() {
        // After [`before_a_gap`], no reading until 2.5 s, which says 0.6 m over the gap where the scans
        // matched 1.3 m (ACES, 540 s: a turn the odometry put at 61° and the scans at 81°).
        let mut e = before_a_gap(true);
        e.add_pose(s(2.4), rigid2(1.5, 0.0, 0.0));
        e.add_odometry(&reading_at(2.5, 0.9));
        e.add_odometry(&reading_at(2.6, 1.0));
        // By 2.6 s the odometry still falls 0.5 m short of the matched motion: not late, wrong. The last
        // pose plus the odometry interpolated since (0.3 + 0.6 × 2.1 / 2.2 at 2.4 s).
        let expected = 1.5 + 1.0 - (0.3 + 0.6 * 2.1 / 2.2);
        assert_relative_eq!(e.extrapolate(s(2.6)).x(), expected, epsilon = 1e-9);
    }

    #[test]
    fn inside_a_gap_the_prediction_is_not_pulled_back_before_it() {
        // A scan inside the gap (2.43 s, handed over once the reading at 2.5 s came): the pose before the
        // gap would put it back near 0.2 m.
        let e = lagged_burst(true, false);
        let p = e.extrapolate(s(2.43));
        assert!((p.x() - 1.2).abs() < 0.01, "{p:?}");
    }

    #[test]
    fn odometry_is_frozen_only_when_readings_arrived_and_repeat_the_pose() {
        let reading = |t: f64, x: f64| OdometryReading {
            time: s(t),
            pose: rigid2(x, 0.0, 0.0),
        };
        let mut e = PoseExtrapolator::new();
        e.add_pose(s(0.0), Rigid2::identity());
        e.add_odometry(&reading(0.0, 1.0));
        // Nothing arrived since: missing, not frozen.
        assert!(!e.odometry_frozen(s(0.0), s(0.3)));
        e.add_odometry(&reading(0.2, 1.0));
        e.add_odometry(&reading(0.4, 1.0));
        assert!(e.odometry_frozen(s(0.0), s(0.4)));
        e.add_odometry(&reading(0.6, 1.5));
        assert!(!e.odometry_frozen(s(0.0), s(0.6)));
    }

    #[test]
    fn time_going_backwards_is_rejected() {
        let mut e = PoseExtrapolator::new();
        e.add_odometry(&OdometryReading {
            time: s(1.0),
            pose: rigid2(0.0, 0.0, 0.0),
        });
        e.add_odometry(&OdometryReading {
            time: s(0.5),
            pose: rigid2(5.0, 0.0, 0.0),
        });
        e.add_odometry(&OdometryReading {
            time: s(1.0),
            pose: rigid2(5.0, 0.0, 0.0),
        });
        e.add_odometry(&OdometryReading {
            time: s(2.0),
            pose: rigid2(f64::NAN, 0.0, 0.0),
        });
        assert_eq!(e.rejected(), 3);
    }

    #[test]
    fn constant_velocity_ignores_bursts() {
        let mut e = PoseExtrapolator::new();
        e.add_pose(s(0.0), rigid2(0.0, 0.0, 0.0));
        e.add_pose(s(0.1), rigid2(0.1, 0.0, 0.0));
        // A burst: 0.2 ms later, 1 cm further (would be 50 m/s from these two alone).
        e.add_pose(s(0.1002), rigid2(0.11, 0.0, 0.0));
        let p = e.extrapolate(s(0.2002));
        assert!((p.x() - 0.21).abs() < 0.02, "{p:?}");
    }

    #[test]
    fn constant_velocity_is_measured_over_the_horizon_it_is_carried_when_asked() {
        // Straight at 1 m/s, then one pose matched 10° off; odometry absent. Carried 0.6 s ahead, the
        // velocity of the last 0.1 s alone turns the prediction by 60° (70° in all); measured over the
        // last 0.3 s, by 20°.
        let mut e = PoseExtrapolator::with_options(PoseExtrapolatorOptions {
            min_velocity_span_per_horizon: 0.5,
            ..PoseExtrapolatorOptions::default()
        });
        let mut plain = PoseExtrapolator::with_options(PoseExtrapolatorOptions {
            min_velocity_span_per_horizon: 0.0,
            ..PoseExtrapolatorOptions::default()
        });
        for k in 0..=10 {
            let pose = rigid2(0.1 * f64::from(k), 0.0, 0.0);
            e.add_pose(s(0.1 * f64::from(k)), pose);
            plain.add_pose(s(0.1 * f64::from(k)), pose);
        }
        e.add_pose(s(1.1), rigid2(1.1, 0.0, 10f64.to_radians()));
        plain.add_pose(s(1.1), rigid2(1.1, 0.0, 10f64.to_radians()));
        let p = e.extrapolate(s(1.7));
        assert!((p.theta().to_degrees() - 30.0).abs() < 1.0, "{p:?}");
        assert!((p.x() - 1.7).abs() < 0.1, "{p:?}");
        // One scan interval ahead the last interval still counts.
        let near = e.extrapolate(s(1.2));
        assert!((near.theta().to_degrees() - 20.0).abs() < 1.0, "{near:?}");
        // By default the last interval's velocity is carried.
        let far = plain.extrapolate(s(1.7));
        assert!((far.theta().to_degrees() - 70.0).abs() < 1.0, "{far:?}");
    }

    #[test]
    fn imu_supplies_rotation() {
        let mut e = PoseExtrapolator::new();
        e.add_pose(s(0.0), Rigid2::identity());
        for k in 0..=10 {
            e.add_imu(&ImuReading {
                time: s(f64::from(k) * 0.1),
                yaw_rate: 0.5,
            });
        }
        let p = e.extrapolate(s(1.0));
        assert!((p.theta() - 0.5).abs() < 1e-6, "{p:?}");
    }
}
