//! Seeded, deterministic perturbations of a recording: the robustness suite's variants.
//!
//! A robot's owner brings a building and a sensor nobody tuned on. The suite predicts how the engine
//! does there by degrading the recordings we have the ways real robots differ: a short-range scanner,
//! fewer beams, worse odometry, wheel slips the odometry never sees, a slow scan rate, people and carts
//! in the beams, a recording that starts elsewhere. Each variant is a [`Perturbation`]; the same
//! recording, variant and seed always give the same events.
//!
//! Variants (`--perturb NAME[,NAME...]`, see [`Perturbation::parse`]):
//!
//! | name | what |
//! |---|---|
//! | `clean` | nothing |
//! | `range8`, `range4` | no return beyond 8 m / 4 m: such readings become `+inf` (REP 117's "no return") |
//! | `sparse` | every other beam |
//! | `dense` | twice the beams, at half the angle: a beam between each two, on their surface where they share one, else the first's return (a 0.5° scanner, as unseen office buildings' SICK units are set) |
//! | `odom` | odometry 3 % long in translation, 2° of heading drift per 10 m, and per-step noise |
//! | `slip` | wheel slips the odometry never saw: 0.2–0.5 m and 3–8°, every 20–60 m of driving |
//! | `slow` | scans at least 0.7 s apart |
//! | `clutter` | 5 % of beams replaced by short returns in blobs of 1–4 beams (people, carts) |
//! | `late` | the first 20 % of the recording's time dropped |
//! | `noise` | Gaussian range noise, σ = 3 cm (a low-cost scanner) |
//! | `stall` | odometry stalls for 0.4–1.0 s every 20–60 m of driving: readings repeat the last pose, then one carries the backlog |
//! | `hard` | `range4` + `slip` + `clutter` + `slow` |
//! | `thin` | `sparse` + `slow`: a low-cost scanner, few beams at a low rate (90 beams at 2° and 1.4 scans/s on Intel) |
//! | `lag` | every odometry reading stamped 0.1 s late (its clock ahead of the scanner's, or its driver's latency stamped at arrival; against their scans, ACES's own odometry is stamped 0.09 s early and MIT CSAIL's 0.14 s early, as `mapping::sensor::OdometryClock` estimates them) |
//! | `burst` | the logger stalls for 0.5–2 s every 10–40 s: what the sensors sent meanwhile is stamped when it resumes, in a burst 0.5 ms apart, in the order it came (Intel's own stamps do this) |
//! | `scanburst` | the same stalls, of the scanner's driver alone: scans stamped in bursts, the odometry on time |
//! | `clock` | the odometry's clock off the scanner's by a constant drawn per seed, uniform in ±20 ms (two drivers' clocks, never quite in step): a deterministic variant made one draw of many, so a seed says how often a near-threshold decision goes each way |
//!
//! `burst` moves scans' stamps away from when they were taken; [`PerturbationReport::capture_time`] gives
//! each scan's own, and a run is scored at those ([`PerturbationReport::relations_at_stamps`] the other
//! way, for a run that asks its questions at the stamps).

use std::collections::BTreeMap;

use mapping::geometry::{Rigid2, Rigid2Ext as _, rigid2};
use mapping::io::relations::Relation;
use mapping::sensor::{
    LaserScan, OdometryReading, SensorEvent, Timestamp, nearest_within_tolerance,
};
use rand::{Rng as _, SeedableRng as _};
use rand_distr::{Distribution as _, Normal};
use rand_pcg::Pcg64;

use crate::source::Recording;

/// Every variant name [`Perturbation::parse`] knows, in the suite's order.
pub const VARIANTS: &[&str] = &[
    "clean",
    "range8",
    "range4",
    "sparse",
    "odom",
    "slip",
    "slow",
    "clutter",
    "late",
    "noise",
    "stall",
    "hard",
    "thin",
    "lag",
    "burst",
    "scanburst",
    "clock",
    "dense",
];

/// Odometry that is wrong the way wheel odometry is: a scale error, a heading drift with distance, and
/// per-step noise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdometryError {
    /// Translation scale error (fraction): 0.03 = every reported step 3 % long.
    pub scale: f64,
    /// Heading drift added per metre driven, radians (2° per 10 m = 0.0035 rad/m).
    pub drift_per_m: f64,
    /// Translation noise per step, as a fraction of the step's length (σ).
    pub translation_noise: f64,
    /// Rotation noise per metre driven, radians (σ, scaled by the step's length).
    pub rotation_noise_per_m: f64,
}

/// Wheel slips the odometry never saw.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Slips {
    /// Distance driven between slips, metres: drawn uniformly from this range each time.
    pub every_m: (f64, f64),
    /// Size of a slip's translation, metres (uniform, in a uniform direction).
    pub translation_m: (f64, f64),
    /// Size of a slip's rotation, radians (uniform, either sign).
    pub rotation_rad: (f64, f64),
}

/// Odometry stalls: the stream keeps coming but repeats its last pose, then catches up at once. The
/// cumulative pose stays right (the ticks are late, not lost): MIT CSAIL's odometry does this once, in a
/// turn (frozen for 0.85 s at t ≈ 170 s, then the backlog over four readings).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdometryStalls {
    /// Distance driven between stalls, metres: drawn uniformly from this range each time.
    pub every_m: (f64, f64),
    /// How long a stall lasts, seconds (uniform).
    pub duration_s: (f64, f64),
}

/// A logger that stalls and then stamps what it buffered on arrival: every message taken during a stall
/// carries the stall's end as its stamp (spread [`BURST_SPACING_S`] apart, in the order the messages
/// came). Intel's recording is stamped this way, scans and odometry alike: a third of its scan intervals
/// are under a fifth of the median, bursts of up to 13 scans after gaps of up to 2 s. With `scans_only`
/// only the scanner's driver stalls: the odometry keeps the stamps of when it was taken.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoggerStalls {
    /// Recording time between stalls, seconds: drawn uniformly from this range each time.
    pub every_s: (f64, f64),
    /// How long a stall lasts, seconds (uniform).
    pub duration_s: (f64, f64),
    /// Only scans are held and restamped.
    pub scans_only: bool,
}

/// Seconds between the stamps of a burst's messages (Intel's bursts: 0.3–1 ms).
pub const BURST_SPACING_S: f64 = 0.0005;

/// Short returns that replace some beams: people and carts between the scanner and the walls.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Clutter {
    /// Share of beams replaced (0..1).
    pub share: f64,
    /// Beams per blob: uniform in `1..=max_blob_beams`.
    pub max_blob_beams: usize,
    /// Nearest and farthest clutter range, metres (never beyond the beam's own return).
    pub range_m: (f32, f32),
}

/// One variant of the suite: what is done to a recording. The default does nothing.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Perturbation {
    /// Readings beyond this range (metres) become `+inf`.
    pub max_range_m: Option<f32>,
    /// Keep every other beam.
    pub sparse: bool,
    /// Twice the beams ([`densify`]).
    pub dense: bool,
    /// Wheel odometry error.
    pub odometry: Option<OdometryError>,
    /// Wheel slips the odometry missed.
    pub slips: Option<Slips>,
    /// Odometry stalls.
    pub stalls: Option<OdometryStalls>,
    /// Scans closer than this (seconds) to the previous kept one are dropped.
    pub min_scan_period_s: Option<f64>,
    /// People and carts in the beams.
    pub clutter: Option<Clutter>,
    /// Share of the recording's time dropped at its start (0..1).
    pub drop_first_share: Option<f64>,
    /// Gaussian range noise (σ, metres) on every return.
    pub range_noise_m: Option<f32>,
    /// Every odometry reading's stamp moved this much later (seconds): the pose it reports is older than
    /// its stamp says.
    pub odometry_lag_s: Option<f64>,
    /// Logger stalls, after which messages come stamped in bursts.
    pub logger_stalls: Option<LoggerStalls>,
    /// The odometry's clock off the scanner's by a constant offset drawn per seed, uniform in ±this
    /// (seconds), on top of `odometry_lag_s`.
    pub odometry_clock_offset_s: Option<f64>,
}

/// A variant name [`Perturbation::parse`] does not know.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("unknown perturbation `{0}` (known: {known})", known = VARIANTS.join(", "))]
pub struct UnknownPerturbation(String);

/// What a perturbation did, for the report.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct PerturbationReport {
    /// Scans before and after.
    pub scans_in: usize,
    /// Scans kept.
    pub scans_out: usize,
    /// Odometry readings kept.
    pub odometry_out: usize,
    /// Slips injected.
    pub slips: usize,
    /// When each slip happened: the stamp (seconds) of the odometry reading that missed it.
    pub slip_stamps_s: Vec<f64>,
    /// Odometry stalls injected.
    pub stalls: usize,
    /// Odometry readings that repeated a stalled pose.
    pub stalled_readings: usize,
    /// Beams cut to `+inf` by the range limit.
    pub beams_cut: usize,
    /// Beams replaced by clutter.
    pub beams_cluttered: usize,
    /// Logger stalls injected.
    pub logger_stalls: usize,
    /// Messages stamped later than taken, in bursts.
    pub messages_restamped: usize,
    /// The odometry clock's offset drawn (seconds, positive: stamped late), 0 without `clock`.
    pub odometry_clock_offset_s: f64,
    /// Each restamped scan's stamp and the stamp of when it was taken.
    #[serde(skip)]
    pub scan_capture_times: BTreeMap<Timestamp, Timestamp>,
}

impl PerturbationReport {
    /// When the scan stamped `stamp` was taken: its stamp, unless the perturbation moved it.
    pub fn capture_time(&self, stamp: Timestamp) -> Timestamp {
        self.scan_capture_times
            .get(&stamp)
            .copied()
            .unwrap_or(stamp)
    }

    /// `relations` (made at the times scans were taken, rounded) at the stamps the scans came with:
    /// [`Self::capture_time`] the other way, for a run that goes by the stamps.
    pub fn relations_at_stamps(&self, relations: Vec<Relation>) -> Vec<Relation> {
        if self.scan_capture_times.is_empty() {
            return relations;
        }
        let stamp_of: BTreeMap<Timestamp, Timestamp> = self
            .scan_capture_times
            .iter()
            .map(|(stamp, capture)| (*capture, *stamp))
            .collect();
        let stamp = |t: Timestamp| nearest_within_tolerance(&stamp_of, t).unwrap_or(t);
        relations
            .into_iter()
            .map(|r| Relation {
                t1: stamp(r.t1),
                t2: stamp(r.t2),
                ..r
            })
            .collect()
    }
}

impl Perturbation {
    /// The perturbation named by a comma-separated list of variants (`range4,slip`); each adds its part.
    pub fn parse(names: &str) -> Result<Self, UnknownPerturbation> {
        let mut p = Self::default();
        for name in names.split(',').map(str::trim).filter(|n| !n.is_empty()) {
            p.add(name)?;
        }
        Ok(p)
    }

    fn add(&mut self, name: &str) -> Result<(), UnknownPerturbation> {
        match name {
            "clean" => {}
            "range8" => self.max_range_m = Some(self.max_range_m.map_or(8.0, |r| r.min(8.0))),
            "range4" => self.max_range_m = Some(self.max_range_m.map_or(4.0, |r| r.min(4.0))),
            "sparse" => self.sparse = true,
            "dense" => self.dense = true,
            "odom" => {
                self.odometry = Some(OdometryError {
                    scale: 0.03,
                    drift_per_m: 0.2f64.to_radians(),
                    translation_noise: 0.02,
                    rotation_noise_per_m: 0.5f64.to_radians(),
                });
            }
            "slip" => {
                self.slips = Some(Slips {
                    every_m: (20.0, 60.0),
                    translation_m: (0.2, 0.5),
                    rotation_rad: (3f64.to_radians(), 8f64.to_radians()),
                });
            }
            "slow" => self.min_scan_period_s = Some(0.7),
            "clutter" => {
                self.clutter = Some(Clutter {
                    share: 0.05,
                    max_blob_beams: 4,
                    range_m: (0.3, 5.0),
                });
            }
            "late" => self.drop_first_share = Some(0.2),
            "noise" => self.range_noise_m = Some(0.03),
            "lag" => self.odometry_lag_s = Some(0.1),
            "clock" => self.odometry_clock_offset_s = Some(0.02),
            "burst" | "scanburst" => {
                self.logger_stalls = Some(LoggerStalls {
                    every_s: (10.0, 40.0),
                    duration_s: (0.5, 2.0),
                    scans_only: name == "scanburst",
                });
            }
            "stall" => {
                self.stalls = Some(OdometryStalls {
                    every_m: (20.0, 60.0),
                    duration_s: (0.4, 1.0),
                });
            }
            "hard" => {
                for part in ["range4", "slip", "clutter", "slow"] {
                    self.add(part)?;
                }
            }
            "thin" => {
                for part in ["sparse", "slow"] {
                    self.add(part)?;
                }
            }
            other => return Err(UnknownPerturbation(other.to_owned())),
        }
        Ok(())
    }

    /// `recording` perturbed, deterministically for `seed`. Each part draws from its own stream, so
    /// adding one part to a variant does not change what the others do.
    pub fn apply(&self, recording: &Recording, seed: u64) -> (Recording, PerturbationReport) {
        let rng =
            |stream: u64| Pcg64::seed_from_u64(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ stream);
        let mut report = PerturbationReport::default();
        let mut events: Vec<SensorEvent> = recording.events.clone();
        report.scans_in = count_scans(&events);

        if let Some(share) = self.drop_first_share
            && let (Some(first), Some(last)) = (events.first(), events.last())
        {
            let cut = first
                .time()
                .offset_by(share * last.time().seconds_since(first.time()));
            events.retain(|e| e.time() >= cut);
        }
        if let Some(period) = self.min_scan_period_s {
            let mut last = None;
            events.retain(|e| match e {
                SensorEvent::Scan(scan) => {
                    let keep = last.is_none_or(|t| scan.time.seconds_since(t) >= period);
                    if keep {
                        last = Some(scan.time);
                    }
                    keep
                }
                _ => true,
            });
        }
        if self.odometry.is_some() || self.slips.is_some() {
            report.slip_stamps_s = self.perturb_odometry(&mut events, &mut rng(1), &mut rng(2));
            report.slips = report.slip_stamps_s.len();
        }
        if let Some(stalls) = self.stalls {
            (report.stalls, report.stalled_readings) =
                stall_odometry(&stalls, &mut events, &mut rng(5));
        }
        if let Some(max) = self.odometry_clock_offset_s {
            report.odometry_clock_offset_s = rng(7).random_range(-max..=max);
        }
        let lag = self.odometry_lag_s.unwrap_or(0.0) + report.odometry_clock_offset_s;
        if lag != 0.0 {
            for event in &mut events {
                if let SensorEvent::Odometry(reading) = event {
                    reading.time = reading.time.offset_by(lag);
                }
            }
            // Stable: readings and scans at the same stamp keep their order.
            events.sort_by_key(SensorEvent::time);
        }
        // After `lag`: a reading that comes late reaches the stalled logger late, and is stamped on
        // arrival like everything else the stall held.
        if let Some(stalls) = self.logger_stalls {
            (
                report.logger_stalls,
                report.messages_restamped,
                report.scan_capture_times,
            ) = stamp_in_bursts(&stalls, &mut events, &mut rng(6));
        }
        let mut clutter_rng = rng(3);
        let mut noise_rng = rng(4);
        for event in &mut events {
            if let SensorEvent::Scan(scan) = event {
                self.perturb_scan(scan, &mut clutter_rng, &mut noise_rng, &mut report);
            }
        }
        report.scans_out = count_scans(&events);
        report.odometry_out = events
            .iter()
            .filter(|e| matches!(e, SensorEvent::Odometry(_)))
            .count();
        (
            Recording {
                events,
                base_from_laser: recording.base_from_laser,
                report: recording.report.clone(),
            },
            report,
        )
    }

    /// Rewrites the odometry poses step by step: each step as recorded, then scaled, drifted and
    /// noised, and at a slip composed with the slip's inverse (the robot moved by the slip, the wheels
    /// did not report it). Returns the stamps (seconds) of the slips.
    fn perturb_odometry(
        &self,
        events: &mut [SensorEvent],
        error_rng: &mut Pcg64,
        slip_rng: &mut Pcg64,
    ) -> Vec<f64> {
        let unit = Normal::new(0.0, 1.0).expect("unit normal");
        let draw_slip_gap = |rng: &mut Pcg64| {
            self.slips.map_or(f64::INFINITY, |s| {
                rng.random_range(s.every_m.0..=s.every_m.1)
            })
        };
        let mut next_slip_m = draw_slip_gap(slip_rng);
        let mut driven_m = 0.0;
        let mut slips = Vec::new();
        let mut previous: Option<(Rigid2, Rigid2)> = None; // (recorded, perturbed)
        for event in events.iter_mut() {
            let SensorEvent::Odometry(OdometryReading { pose, time }) = event else {
                continue;
            };
            let recorded = *pose;
            let Some((last_recorded, last_perturbed)) = previous else {
                previous = Some((recorded, recorded));
                continue;
            };
            let step = last_recorded.inverse() * recorded;
            let length = step.translation.vector.norm();
            let mut step = step.to_xytheta();
            if let Some(e) = self.odometry {
                step.x *= 1.0 + e.scale;
                step.y *= 1.0 + e.scale;
                step.x += e.translation_noise * length * unit.sample(error_rng);
                step.y += e.translation_noise * length * unit.sample(error_rng);
                step.z += e.drift_per_m * length
                    + e.rotation_noise_per_m * length * unit.sample(error_rng);
            }
            let mut step = Rigid2::from_xytheta(&step);
            driven_m += length;
            if let Some(s) = self.slips
                && driven_m >= next_slip_m
            {
                let direction = slip_rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
                let size = slip_rng.random_range(s.translation_m.0..=s.translation_m.1);
                let sign = if slip_rng.random_bool(0.5) { 1.0 } else { -1.0 };
                let turn = sign * slip_rng.random_range(s.rotation_rad.0..=s.rotation_rad.1);
                let slip = rigid2(size * direction.cos(), size * direction.sin(), turn);
                step *= slip.inverse();
                slips.push(time.as_secs_f64());
                driven_m = 0.0;
                next_slip_m = draw_slip_gap(slip_rng);
            }
            let perturbed = last_perturbed * step;
            *pose = perturbed;
            previous = Some((recorded, perturbed));
        }
        slips
    }

    fn perturb_scan(
        &self,
        scan: &mut LaserScan,
        clutter_rng: &mut Pcg64,
        noise_rng: &mut Pcg64,
        report: &mut PerturbationReport,
    ) {
        if self.sparse {
            scan.ranges = scan.ranges.iter().step_by(2).copied().collect();
            scan.angle_increment *= 2.0;
            scan.time_increment *= 2.0;
        }
        if self.dense {
            densify(scan);
        }
        let (range_min, range_max) = (scan.range_min, scan.range_max);
        let is_return = |r: f32| r.is_finite() && r < range_max;
        if let Some(sigma) = self.range_noise_m {
            let normal = Normal::new(0.0, sigma).expect("finite noise");
            for i in 0..scan.ranges.len() {
                if is_return(scan.ranges[i]) {
                    scan.ranges[i] = (scan.ranges[i] + normal.sample(noise_rng)).max(range_min);
                }
            }
        }
        if let Some(c) = self.clutter {
            let mean_blob = (1 + c.max_blob_beams) as f64 / 2.0;
            let start_probability = (c.share / mean_blob).clamp(0.0, 1.0);
            let mut i = 0;
            while i < scan.ranges.len() {
                if clutter_rng.random_bool(start_probability) {
                    let beams = clutter_rng.random_range(1..=c.max_blob_beams.max(1));
                    let range = clutter_rng.random_range(c.range_m.0..=c.range_m.1);
                    for r in scan.ranges.iter_mut().skip(i).take(beams) {
                        // A person stands in front of the wall, never behind it.
                        if !is_return(*r) || range < *r {
                            *r = range.max(range_min);
                            report.beams_cluttered += 1;
                        }
                    }
                    i += beams;
                } else {
                    i += 1;
                }
            }
        }
        if let Some(limit) = self.max_range_m {
            for r in &mut scan.ranges {
                if r.is_finite() && *r > limit {
                    if *r < range_max {
                        report.beams_cut += 1;
                    }
                    *r = f32::INFINITY;
                }
            }
        }
    }
}

/// Makes the odometry stall (see [`OdometryStalls`]): every so many metres driven, the readings of the
/// next `duration_s` repeat the pose of the reading that started the stall; the first reading after it
/// is left as recorded, so it carries the whole backlog. Returns the stalls and the readings changed.
fn stall_odometry(
    stalls: &OdometryStalls,
    events: &mut [SensorEvent],
    rng: &mut Pcg64,
) -> (usize, usize) {
    let draw_gap = |rng: &mut Pcg64| rng.random_range(stalls.every_m.0..=stalls.every_m.1);
    let mut next_stall_m = draw_gap(rng);
    let mut driven_m = 0.0;
    let mut last_recorded: Option<Rigid2> = None;
    // The stall under way: (its end, the pose it repeats).
    let mut stall: Option<(Timestamp, Rigid2)> = None;
    let (mut count, mut changed) = (0, 0);
    for event in events.iter_mut() {
        let SensorEvent::Odometry(OdometryReading { time, pose }) = event else {
            continue;
        };
        let recorded = *pose;
        if let Some(last) = last_recorded {
            driven_m += (last.inverse() * recorded).translation.vector.norm();
        }
        last_recorded = Some(recorded);
        match stall {
            Some((end, frozen)) if *time <= end => {
                *pose = frozen;
                changed += 1;
                continue;
            }
            Some(_) => stall = None,
            None => {}
        }
        if driven_m >= next_stall_m {
            let duration = rng.random_range(stalls.duration_s.0..=stalls.duration_s.1);
            stall = Some((time.offset_by(duration), recorded));
            count += 1;
            driven_m = 0.0;
            next_stall_m = draw_gap(rng);
        }
    }
    (count, changed)
}

/// Makes the logger stall (see [`LoggerStalls`]): every so many seconds, the messages (or the scans) of
/// the next `duration_s` are restamped to the stall's end, [`BURST_SPACING_S`] apart in their order, the
/// last at the end itself; the events are left in time order. Returns the stalls, the messages restamped
/// and each restamped scan's new stamp with its own.
fn stamp_in_bursts(
    stalls: &LoggerStalls,
    events: &mut [SensorEvent],
    rng: &mut Pcg64,
) -> (usize, usize, BTreeMap<Timestamp, Timestamp>) {
    let mut scan_capture_times = BTreeMap::new();
    let Some(first) = events.first().map(SensorEvent::time) else {
        return (0, 0, scan_capture_times);
    };
    let draw_gap = |rng: &mut Pcg64| rng.random_range(stalls.every_s.0..=stalls.every_s.1);
    let mut start = first.offset_by(draw_gap(rng));
    let (mut count, mut changed) = (0, 0);
    // The first event at or after `from` whose stamp satisfies `is`, or the end.
    let next = |events: &[SensorEvent], from: usize, is: &dyn Fn(Timestamp) -> bool| {
        events[from..]
            .iter()
            .position(|e| is(e.time()))
            .map_or(events.len(), |k| from + k)
    };
    let mut i = next(events, 0, &|t| t >= start);
    while i < events.len() {
        let end = start.offset_by(rng.random_range(stalls.duration_s.0..=stalls.duration_s.1));
        let j = next(events, i, &|t| t > end);
        let held = |e: &SensorEvent| !stalls.scans_only || matches!(e, SensorEvent::Scan(_));
        let n = events[i..j].iter().filter(|e| held(e)).count();
        for (k, event) in events[i..j].iter_mut().filter(|e| held(e)).enumerate() {
            // Never before the stall's start, so the events stay in order.
            let stamp = end
                .offset_by(-((n - 1 - k) as f64) * BURST_SPACING_S)
                .max(start);
            match event {
                SensorEvent::Scan(scan) => {
                    scan_capture_times.insert(stamp, scan.time);
                    scan.time = stamp;
                }
                SensorEvent::Odometry(reading) => reading.time = stamp,
                SensorEvent::Imu(reading) => reading.time = stamp,
            }
        }
        if n > 0 {
            count += 1;
            changed += n;
        }
        start = end.offset_by(draw_gap(rng));
        i = next(events, j, &|t| t >= start);
    }
    // Stable: a held scan now comes after the odometry of its stall.
    events.sort_by_key(SensorEvent::time);
    (count, changed, scan_capture_times)
}

/// Relative range difference (of the nearer return) under which two neighbouring beams are taken to lie
/// on one surface, so that a beam between them lands on it.
const SAME_SURFACE: f32 = 0.05;

/// `scan` with a beam between each two of its beams: where both neighbours are returns on one surface
/// (ranges within [`SAME_SURFACE`] of each other), the mean range; elsewhere (a depth edge, a missing
/// return) the first neighbour's reading, as a finer scanner sees one side of the edge or the other.
fn densify(scan: &mut LaserScan) {
    let Some(&last) = scan.ranges.last() else {
        return;
    };
    let range_max = scan.range_max;
    let is_return = |r: f32| r.is_finite() && r < range_max;
    let mut ranges = Vec::with_capacity(2 * scan.ranges.len());
    for pair in scan.ranges.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        ranges.push(a);
        let same_surface = is_return(a) && is_return(b) && (a - b).abs() <= SAME_SURFACE * a.min(b);
        ranges.push(if same_surface { 0.5 * (a + b) } else { a });
    }
    ranges.push(last);
    scan.ranges = ranges;
    scan.angle_increment *= 0.5;
    scan.time_increment *= 0.5;
}

fn count_scans(events: &[SensorEvent]) -> usize {
    events
        .iter()
        .filter(|e| matches!(e, SensorEvent::Scan(_)))
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A straight drive at 1 m/s along x for `seconds`, odometry at 10 Hz and a 5 Hz scan of 181 beams
    /// all reading 6 m.
    fn drive(seconds: u32) -> Recording {
        let mut events = Vec::new();
        for k in 0..seconds * 10 {
            let t = f64::from(k) / 10.0;
            events.push(SensorEvent::Odometry(OdometryReading {
                time: Timestamp::from_secs_f64(t),
                pose: rigid2(t, 0.0, 0.0),
            }));
            if k % 2 == 0 {
                events.push(SensorEvent::Scan(LaserScan {
                    time: Timestamp::from_secs_f64(t),
                    angle_min: -std::f32::consts::FRAC_PI_2,
                    angle_increment: 1f32.to_radians(),
                    time_increment: 0.0,
                    range_min: 0.1,
                    range_max: 30.0,
                    ranges: vec![6.0; 181],
                }));
            }
        }
        Recording {
            events,
            base_from_laser: Rigid2::identity(),
            report: crate::source::ReadReport::default(),
        }
    }

    fn scans(r: &Recording) -> Vec<&LaserScan> {
        r.events
            .iter()
            .filter_map(|e| match e {
                SensorEvent::Scan(s) => Some(s),
                _ => None,
            })
            .collect()
    }

    fn odometry(r: &Recording) -> Vec<&OdometryReading> {
        r.events
            .iter()
            .filter_map(|e| match e {
                SensorEvent::Odometry(o) => Some(o),
                _ => None,
            })
            .collect()
    }

    fn last_odometry(r: &Recording) -> Rigid2 {
        r.events
            .iter()
            .rev()
            .find_map(|e| match e {
                SensorEvent::Odometry(o) => Some(o.pose),
                _ => None,
            })
            .expect("odometry")
    }

    #[test]
    fn every_named_variant_parses_and_unknown_names_are_refused() {
        for name in VARIANTS {
            Perturbation::parse(name).expect(name);
        }
        assert_eq!(
            Perturbation::parse("clean").unwrap(),
            Perturbation::default()
        );
        let hard = Perturbation::parse("hard").unwrap();
        assert_eq!(
            hard,
            Perturbation::parse("range4,slip,clutter,slow").unwrap()
        );
        assert_eq!(
            Perturbation::parse("thin").unwrap(),
            Perturbation::parse("sparse,slow").unwrap()
        );
        let error = Perturbation::parse("range4,wet").unwrap_err();
        assert!(error.to_string().contains("`wet`"), "{error}");
    }

    #[test]
    fn lag_stamps_every_odometry_reading_later_and_keeps_the_events_in_time_order() {
        let recording = drive(10);
        let (lagged, _) = Perturbation::parse("lag").unwrap().apply(&recording, 1);
        let (before, after) = (odometry(&recording), odometry(&lagged));
        assert_eq!(before.len(), after.len());
        for (a, b) in before.iter().zip(&after) {
            assert!((b.time.seconds_since(a.time) - 0.1).abs() < 1e-6);
            assert_eq!(a.pose, b.pose);
        }
        assert_eq!(scans(&lagged).len(), scans(&recording).len());
        assert!(lagged.events.windows(2).all(|w| w[0].time() <= w[1].time()));
    }

    #[test]
    fn clock_moves_every_odometry_stamp_by_one_offset_within_its_bound_drawn_per_seed() {
        let recording = drive(10);
        let clock = Perturbation::parse("clock").unwrap();
        let offset = |seed| {
            let (moved, report) = clock.apply(&recording, seed);
            let (before, after) = (odometry(&recording), odometry(&moved));
            assert_eq!(before.len(), after.len());
            for (a, b) in before.iter().zip(&after) {
                assert!(
                    (b.time.seconds_since(a.time) - report.odometry_clock_offset_s).abs() < 1e-6
                );
            }
            assert!(moved.events.windows(2).all(|w| w[0].time() <= w[1].time()));
            assert_eq!(scans(&moved), scans(&recording));
            report.odometry_clock_offset_s
        };
        let offsets: Vec<f64> = (1..=8).map(offset).collect();
        assert!(offsets.iter().all(|o| o.abs() <= 0.02), "{offsets:?}");
        let spread = offsets.iter().copied().fold(f64::NEG_INFINITY, f64::max)
            - offsets.iter().copied().fold(f64::INFINITY, f64::min);
        assert!(spread > 0.01, "{offsets:?}");
        assert_eq!(
            offset(3).to_bits(),
            offsets[2].to_bits(),
            "the same seed, the same draw"
        );
        let (lagged, report) = Perturbation::parse("lag,clock")
            .unwrap()
            .apply(&recording, 2);
        assert_eq!(
            report.odometry_clock_offset_s.to_bits(),
            offsets[1].to_bits()
        );
        assert!(lagged.events.windows(2).all(|w| w[0].time() <= w[1].time()));
    }

    #[test]
    fn burst_stamps_what_a_stall_held_at_its_end_and_keeps_each_scans_capture_time() {
        let recording = drive(120);
        let (burst, report) = Perturbation::parse("burst").unwrap().apply(&recording, 1);
        assert!(burst.events.windows(2).all(|w| w[0].time() <= w[1].time()));
        // Between 2 and 11 stalls of 0.5–2 s in 120 s, each holding messages at 15 a second.
        assert!((2..=11).contains(&report.logger_stalls), "{report:?}");
        assert!(report.messages_restamped >= 5 * report.logger_stalls);
        // Every scan is still there, in its order, and its capture time is the recording's stamp.
        let before: Vec<Timestamp> = scans(&recording).iter().map(|s| s.time).collect();
        let after = scans(&burst);
        let captured: Vec<Timestamp> = after.iter().map(|s| report.capture_time(s.time)).collect();
        assert_eq!(captured, before);
        let moved: Vec<f64> = after
            .iter()
            .map(|s| s.time.seconds_since(report.capture_time(s.time)))
            .collect();
        assert!(moved.iter().all(|&m| (0.0..=2.0).contains(&m)), "{moved:?}");
        // A reference made at the capture times (rounded to 10 µs, as the Freiburg relations) asked at
        // the stamps.
        let rounded = |t: Timestamp| Timestamp((t.0 + 5_000) / 10_000 * 10_000);
        let relations: Vec<Relation> = before
            .windows(2)
            .map(|w| Relation {
                t1: rounded(w[0]),
                t2: rounded(w[1]),
                delta: Rigid2::identity(),
            })
            .collect();
        let at_stamps = report.relations_at_stamps(relations);
        let stamps: Vec<Timestamp> = after.iter().map(|s| s.time).collect();
        for (relation, w) in at_stamps.iter().zip(stamps.windows(2)) {
            assert_eq!((relation.t1, relation.t2), (w[0], w[1]));
        }
        // A burst: scans a few 0.5-ms steps apart (the odometry between them), taken 0.2 s apart.
        assert!(after.windows(2).any(|w| {
            w[1].time.seconds_since(w[0].time) <= 4.0 * BURST_SPACING_S
                && report
                    .capture_time(w[1].time)
                    .seconds_since(report.capture_time(w[0].time))
                    > 0.19
        }));
        // The odometry says what it said, only later.
        let poses = |r| odometry(r).iter().map(|o| o.pose).collect::<Vec<_>>();
        assert_eq!(poses(&burst), poses(&recording));
    }

    #[test]
    fn scanburst_holds_only_the_scans_and_leaves_the_odometry_on_time() {
        let recording = drive(120);
        let (burst, report) = Perturbation::parse("scanburst")
            .unwrap()
            .apply(&recording, 1);
        assert!(burst.events.windows(2).all(|w| w[0].time() <= w[1].time()));
        assert!(report.logger_stalls >= 2, "{report:?}");
        assert_eq!(report.messages_restamped, report.scan_capture_times.len());
        let odometry = |r: &Recording| -> Vec<OdometryReading> {
            r.events
                .iter()
                .filter_map(|e| match e {
                    SensorEvent::Odometry(o) => Some(o.clone()),
                    _ => None,
                })
                .collect()
        };
        assert_eq!(odometry(&burst), odometry(&recording));
        let captured: Vec<Timestamp> = scans(&burst)
            .iter()
            .map(|s| report.capture_time(s.time))
            .collect();
        let before: Vec<Timestamp> = scans(&recording).iter().map(|s| s.time).collect();
        assert_eq!(captured, before);
    }

    #[test]
    fn the_same_seed_gives_the_same_recording_and_another_seed_another() {
        let recording = drive(200);
        let p = Perturbation::parse("odom,slip,clutter,noise").unwrap();
        let (a, _) = p.apply(&recording, 7);
        let (b, _) = p.apply(&recording, 7);
        let (c, _) = p.apply(&recording, 8);
        assert_eq!(a.events, b.events);
        assert_ne!(a.events, c.events);
    }

    #[test]
    fn range_limits_cut_far_returns_to_infinity_and_sparse_halves_the_beams() {
        let recording = drive(5);
        let (short, report) = Perturbation::parse("range4").unwrap().apply(&recording, 1);
        assert!(
            scans(&short)
                .iter()
                .all(|s| s.ranges.iter().all(|r| r.is_infinite()))
        );
        assert_eq!(report.beams_cut, 25 * 181);
        let (sparse, _) = Perturbation::parse("sparse").unwrap().apply(&recording, 1);
        let s = scans(&sparse)[0];
        assert_eq!(s.ranges.len(), 91);
        assert!((s.angle_increment - 2f32.to_radians()).abs() < 1e-6);
    }

    #[test]
    fn dense_puts_a_beam_between_each_two_on_their_surface_or_the_first_side_of_an_edge() {
        let mut scan = scans(&drive(1))[0].clone();
        scan.ranges = vec![2.0, 2.1, 5.0, f32::INFINITY, 3.0];
        let increment = scan.angle_increment;
        let recording = Recording {
            events: vec![SensorEvent::Scan(scan)],
            ..drive(1)
        };
        let (dense, _) = Perturbation::parse("dense").unwrap().apply(&recording, 1);
        let s = scans(&dense)[0];
        let expected = [
            2.0,
            2.05,
            2.1,
            2.1,
            5.0,
            5.0,
            f32::INFINITY,
            f32::INFINITY,
            3.0,
        ];
        assert_eq!(s.ranges.len(), expected.len());
        for (got, want) in s.ranges.iter().zip(expected) {
            let same = if want.is_finite() {
                (got - want).abs() < 1e-6
            } else {
                got.is_infinite()
            };
            assert!(same, "{:?} against {expected:?}", s.ranges);
        }
        assert!((s.angle_increment - 0.5 * increment).abs() < 1e-9);
    }

    #[test]
    fn slow_and_late_drop_what_they_say() {
        let recording = drive(100);
        let (slow, report) = Perturbation::parse("slow").unwrap().apply(&recording, 1);
        let times: Vec<f64> = scans(&slow).iter().map(|s| s.time.as_secs_f64()).collect();
        assert!(times.windows(2).all(|w| w[1] - w[0] >= 0.7 - 1e-9));
        assert_eq!(report.scans_in, 500);
        assert_eq!(report.scans_out, 125);
        let (late, _) = Perturbation::parse("late").unwrap().apply(&recording, 1);
        let first = late.events.first().unwrap().time().as_secs_f64();
        assert!((first - 0.2 * 99.9).abs() < 0.11, "first event at {first}");
    }

    #[test]
    fn odometry_error_and_slips_are_the_sizes_they_are_said_to_be() {
        let recording = drive(500); // 499.9 m
        let (odom, _) = Perturbation::parse("odom").unwrap().apply(&recording, 3);
        let end = last_odometry(&odom);
        // 2° per 10 m over ~500 m is ~100° of heading drift, plus noise.
        let drift = end.theta().to_degrees();
        assert!((80.0..120.0).contains(&drift), "heading drift {drift}°");
        let (slipped, report) = Perturbation::parse("slip").unwrap().apply(&recording, 3);
        // One slip every 20–60 m: between 8 and 25 in 500 m.
        assert!((8..=25).contains(&report.slips), "{} slips", report.slips);
        // Each slip is reported with its stamp: 20–60 m apart is 20–60 s at 1 m/s.
        assert_eq!(report.slip_stamps_s.len(), report.slips);
        assert!(
            report
                .slip_stamps_s
                .windows(2)
                .all(|w| (19.9..=60.1).contains(&(w[1] - w[0]))),
            "{:?}",
            report.slip_stamps_s
        );
        // Between slips the odometry moves exactly as recorded.
        let steps: Vec<Rigid2> = slipped
            .events
            .iter()
            .filter_map(|e| match e {
                SensorEvent::Odometry(o) => Some(o.pose),
                _ => None,
            })
            .collect::<Vec<_>>()
            .windows(2)
            .map(|w| w[0].inverse() * w[1])
            .collect();
        let odd = steps
            .iter()
            .filter(|s| (s.translation.vector.norm() - 0.1).abs() > 1e-9 || s.theta().abs() > 1e-9)
            .count();
        assert_eq!(odd, report.slips);
        assert!(steps.iter().all(|s| s.theta().abs() < 8.01f64.to_radians()));
    }

    #[test]
    fn a_stall_repeats_the_last_pose_and_the_next_reading_carries_the_backlog() {
        let recording = drive(500); // 499.9 m at 1 m/s, odometry at 10 Hz
        let (stalled, report) = Perturbation::parse("stall").unwrap().apply(&recording, 3);
        // One stall every 20–60 m: between 8 and 25 in 500 m, each 0.4–1.0 s (4–10 readings).
        assert!(
            (8..=25).contains(&report.stalls),
            "{} stalls",
            report.stalls
        );
        assert!(
            (4 * report.stalls..=10 * report.stalls).contains(&report.stalled_readings),
            "{} readings in {} stalls",
            report.stalled_readings,
            report.stalls
        );
        let poses: Vec<Rigid2> = stalled
            .events
            .iter()
            .filter_map(|e| match e {
                SensorEvent::Odometry(o) => Some(o.pose),
                _ => None,
            })
            .collect();
        let steps: Vec<f64> = poses
            .windows(2)
            .map(|w| (w[0].inverse() * w[1]).translation.vector.norm())
            .collect();
        let frozen = steps.iter().filter(|s| **s == 0.0).count();
        assert_eq!(frozen, report.stalled_readings);
        // The cumulative pose is never lost: the end is where the recording ends.
        assert!((poses.last().unwrap().translation.x - 499.9).abs() < 1e-9);
        // A backlog step is as long as the stall it follows.
        assert!(steps.iter().all(|s| *s < 1.11), "{steps:?}");
    }

    #[test]
    fn clutter_replaces_about_its_share_of_beams_with_nearer_returns() {
        let recording = drive(100);
        let (cluttered, report) = Perturbation::parse("clutter").unwrap().apply(&recording, 5);
        let beams = 500.0 * 181.0;
        let share = report.beams_cluttered as f64 / beams;
        assert!((0.04..0.06).contains(&share), "clutter share {share}");
        assert!(
            scans(&cluttered)
                .iter()
                .all(|s| s.ranges.iter().all(|r| (0.3..=6.0).contains(r)))
        );
    }
}
