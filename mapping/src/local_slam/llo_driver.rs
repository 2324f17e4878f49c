//! LLO fed one sensor event at a time: the step every shell runs, written once.
//!
//! Odometry and IMU readings go to the pose extrapolator. A scan is converted into range data
//! ([`LaserScan::to_range_data`](crate::sensor::LaserScan::to_range_data)), moved from the laser frame
//! into the tracking frame by `base_from_laser`, and matched by the [`LocalTrajectoryBuilder`]. The
//! caller gets an [`LloEvent`] back and keeps its own bookkeeping (counts, nodes, uploads). The driver
//! also estimates the odometry clock's offset against the scanner's from what it matches
//! ([`OdometryClock`], reported, not applied). No I/O.

use super::{
    InsertionResult, LocalTrajectoryBuilder, LocalTrajectoryBuilderOptions, MatchingResult,
};
use crate::geometry::Rigid2;
use crate::sensor::{OdometryClock, RangeConversionOptions, RangeData, RangeStats, SensorEvent};

/// What LLO made of one sensor event.
#[derive(Clone, Debug)]
#[expect(
    clippy::large_enum_variant,
    reason = "one per sensor event, taken apart by the caller at once"
)]
pub enum LloEvent {
    /// An odometry or IMU reading went to the pose extrapolator.
    ReadingAdded,
    /// The scan was dropped: too few hits, or older than the last pose.
    ScanDropped {
        /// What became of its beams.
        stats: RangeStats,
    },
    /// The scan was matched; `result.insertion` is present when it became a node.
    ScanMatched {
        /// LLO's result.
        result: MatchingResult,
        /// The scan in the tracking frame.
        range_data: RangeData,
        /// What became of its beams.
        stats: RangeStats,
    },
}

impl LloEvent {
    /// A matched scan that became a node: its result (with `insertion` taken out) and the insertion;
    /// `None` for every other event.
    pub fn into_node(self) -> Option<(MatchingResult, InsertionResult)> {
        match self {
            Self::ScanMatched { mut result, .. } => {
                let insertion = result.insertion.take()?;
                Some((result, insertion))
            }
            Self::ReadingAdded | Self::ScanDropped { .. } => None,
        }
    }
}

/// LLO for one trajectory, fed [`SensorEvent`]s: a [`LocalTrajectoryBuilder`] and the range conversion
/// of its scans.
#[derive(Debug)]
pub struct LloDriver {
    builder: LocalTrajectoryBuilder,
    range_conversion: RangeConversionOptions,
    odometry_clock: OdometryClock,
}

impl LloDriver {
    /// A driver with no submaps yet; scans are converted with `options.range_conversion`.
    pub fn new(options: LocalTrajectoryBuilderOptions) -> Self {
        Self {
            range_conversion: options.range_conversion.clone(),
            builder: LocalTrajectoryBuilder::new(options),
            odometry_clock: OdometryClock::default(),
        }
    }

    /// The builder (its active submaps, its rejections).
    pub fn builder(&self) -> &LocalTrajectoryBuilder {
        &self.builder
    }

    /// The odometry clock's offset against the scanner's, as estimated from the scans matched so far.
    pub fn odometry_clock(&self) -> &OdometryClock {
        &self.odometry_clock
    }

    /// Hands one event to LLO. `base_from_laser`, the laser's mounting pose, moves a scan into the
    /// tracking frame; readings ignore it.
    pub fn add_event(&mut self, event: &SensorEvent, base_from_laser: &Rigid2) -> LloEvent {
        match event {
            SensorEvent::Odometry(reading) => {
                self.builder.add_odometry(reading);
                self.odometry_clock.add_odometry(reading);
                LloEvent::ReadingAdded
            }
            SensorEvent::Imu(reading) => {
                self.builder.add_imu(reading);
                LloEvent::ReadingAdded
            }
            SensorEvent::Scan(scan) => {
                let (range_data, stats) = scan.to_range_data(&self.range_conversion);
                let range_data = range_data.transformed(base_from_laser);
                match self.builder.add_range_data(scan.time, &range_data) {
                    Some(result) => {
                        self.odometry_clock
                            .scan_matched(result.time, &result.local_pose);
                        LloEvent::ScanMatched {
                            result,
                            range_data,
                            stats,
                        }
                    }
                    None => LloEvent::ScanDropped { stats },
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point2, Vector2};
    use simulator::RayCaster;

    use super::*;
    use crate::geometry::rigid2;
    use crate::local_slam::test_support::room;
    use crate::sensor::{ImuReading, LaserScan, OdometryReading, Timestamp};

    /// A 181-beam 180° scan (30 m) from `world_from_laser`, in the laser frame.
    fn scan(room: &RayCaster, time: Timestamp, world_from_laser: &Rigid2) -> LaserScan {
        let origin = Point2::from(world_from_laser.translation.vector);
        let increment = 1f32.to_radians();
        let angle_min = -90f32.to_radians();
        let ranges = (0..181_u16)
            .map(|k| {
                let angle = f64::from(angle_min + f32::from(k) * increment);
                let direction = world_from_laser.rotation * Vector2::new(angle.cos(), angle.sin());
                room.cast(&origin, &direction, 30.0)
                    .map_or(f32::INFINITY, |r| r as f32)
            })
            .collect();
        LaserScan {
            time,
            angle_min,
            angle_increment: increment,
            time_increment: 0.0,
            range_min: 0.1,
            range_max: 30.0,
            ranges,
        }
    }

    /// The robot drives 5 cm and turns 1° per 0.1 s from (2, 3), with odometry, IMU and a scan each step.
    fn drive(base_from_laser: &Rigid2) -> Vec<SensorEvent> {
        let room = room();
        (0..30_i32)
            .flat_map(|k| {
                let time = Timestamp(1_000_000_000 + i64::from(k) * 100_000_000);
                let world_from_base =
                    rigid2(2.0 + 0.05 * f64::from(k), 3.0, f64::from(k).to_radians());
                [
                    SensorEvent::Odometry(OdometryReading {
                        time,
                        pose: world_from_base,
                    }),
                    SensorEvent::Imu(ImuReading {
                        time,
                        yaw_rate: 10f64.to_radians(),
                    }),
                    SensorEvent::Scan(scan(&room, time, &(world_from_base * base_from_laser))),
                ]
            })
            .collect()
    }

    #[test]
    fn the_driver_does_what_the_hand_written_loop_did() {
        let options = LocalTrajectoryBuilderOptions::default();
        let base_from_laser = rigid2(0.2, -0.1, 0.05);
        let mut driver = LloDriver::new(options.clone());
        let mut builder = LocalTrajectoryBuilder::new(options.clone());
        let mut nodes = 0;
        for event in drive(&base_from_laser) {
            let got = driver.add_event(&event, &base_from_laser);
            match (&event, got) {
                (SensorEvent::Odometry(o), LloEvent::ReadingAdded) => builder.add_odometry(o),
                (SensorEvent::Imu(i), LloEvent::ReadingAdded) => builder.add_imu(i),
                (
                    SensorEvent::Scan(scan),
                    LloEvent::ScanMatched {
                        result,
                        range_data,
                        stats,
                    },
                ) => {
                    let (expected, expected_stats) = scan.to_range_data(&options.range_conversion);
                    let expected = expected.transformed(&base_from_laser);
                    let matched = builder.add_range_data(scan.time, &expected).unwrap();
                    assert_eq!((range_data, stats), (expected, expected_stats));
                    assert_eq!(result.time, matched.time);
                    assert_eq!(result.local_pose, matched.local_pose);
                    assert_eq!(result.branch, matched.branch);
                    assert_eq!(result.insertion.is_some(), matched.insertion.is_some());
                    nodes += usize::from(result.insertion.is_some());
                }
                (event, got) => panic!("{event:?} gave {got:?}"),
            }
        }
        assert!(nodes >= 4, "{nodes} nodes: the run compares too little");
        assert_eq!(driver.builder().num_rejected(), builder.num_rejected());
    }

    #[test]
    fn a_scan_with_too_few_hits_is_dropped_with_its_beam_counts() {
        let mut driver = LloDriver::new(LocalTrajectoryBuilderOptions::default());
        let identity = Rigid2::identity();
        let mut scan = scan(&room(), Timestamp(1_000_000_000), &rigid2(2.0, 3.0, 0.0));
        scan.ranges.fill(f32::NAN);
        match driver.add_event(&SensorEvent::Scan(scan), &identity) {
            LloEvent::ScanDropped { stats } => assert_eq!(
                stats,
                RangeStats {
                    nan: 181,
                    ..RangeStats::default()
                }
            ),
            other => panic!("expected a dropped scan, got {other:?}"),
        }
        assert_eq!(driver.builder().num_rejected(), 1);
    }
}
