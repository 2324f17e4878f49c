//! CARMEN log reading: `FLASER`, `ROBOTLASER1` and `ODOM` lines; other lines are counted and skipped.
//!
//! Scan geometry follows the conversion used for the benchmark bags (so a `.clf` and its bag give the
//! same events): 180° field of view starting at −π/2 with `n − 1` intervals, `range_min` 0.1 m,
//! `range_max` 80 m (CARMEN writes 81.91 m for "no return"). Odometry comes from `ODOM` lines when the
//! log has any, otherwise from the robot-pose triple of each `FLASER` line.

use std::io::BufRead;
use std::path::Path;

use mapping::geometry::{Rigid2, rigid2};
use mapping::sensor::{LaserScan, OdometryReading, SensorEvent, Timestamp};

use super::SourceError;
use super::recording::{ReadReport, Recording};

const RANGE_MIN: f32 = 0.1;
const RANGE_MAX: f32 = 80.0;

struct Parsed {
    scan: LaserScan,
    laser_pose: Rigid2,
    robot_pose: Rigid2,
}

fn numbers(fields: &[&str], what: &str) -> Result<Vec<f64>, String> {
    fields
        .iter()
        .map(|f| {
            f.parse::<f64>()
                .map_err(|_| format!("{what}: {f:?} is not a number"))
        })
        .collect()
}

/// Latest time accepted, seconds: ROS1's (u32 seconds since the epoch), so that differences of stamps
/// never overflow `Timestamp`'s i64 nanoseconds.
const MAX_TIME_S: f64 = 4_294_967_296.0;

/// A log time (seconds since the epoch) as a stamp, if it is in `0..MAX_TIME_S`.
fn time(seconds: f64, what: &str) -> Result<Timestamp, String> {
    if (0.0..MAX_TIME_S).contains(&seconds) {
        Ok(Timestamp::from_secs_f64(seconds))
    } else {
        Err(format!(
            "{what}: time {seconds} s is outside 0..{MAX_TIME_S} s"
        ))
    }
}

fn is_finite(pose: &Rigid2) -> bool {
    pose.translation.vector.iter().all(|v| v.is_finite())
        && pose.rotation.re.is_finite()
        && pose.rotation.im.is_finite()
}

/// `numbers`, refusing NaN and infinities (poses, times and scan geometry; ranges may be NaN).
fn finite_numbers(fields: &[&str], what: &str) -> Result<Vec<f64>, String> {
    let values = numbers(fields, what)?;
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(format!("{what}: {:?} is not a finite number", fields[i])),
        None => Ok(values),
    }
}

fn flaser(fields: &[&str]) -> Result<Parsed, String> {
    let n: usize = fields
        .get(1)
        .and_then(|f| f.parse().ok())
        .ok_or("FLASER: missing beam count")?;
    // A beam count larger than the line is refused before any index arithmetic (no overflow).
    if n > fields.len() || fields.len() < 2 + n + 9 {
        return Err(format!(
            "FLASER: {} fields, expected {} for {n} beams",
            fields.len(),
            n.saturating_add(2 + 9)
        ));
    }
    let ranges = numbers(&fields[2..2 + n], "FLASER range")?
        .into_iter()
        .map(|r| r as f32)
        .collect();
    let p = finite_numbers(&fields[2 + n..2 + n + 7], "FLASER pose")?;
    let increment = if n > 1 {
        std::f64::consts::PI / (n - 1) as f64
    } else {
        0.0
    };
    Ok(Parsed {
        scan: LaserScan {
            time: time(p[6], "FLASER")?,
            angle_min: -std::f32::consts::FRAC_PI_2,
            angle_increment: increment as f32,
            time_increment: 0.0,
            range_min: RANGE_MIN,
            range_max: RANGE_MAX,
            ranges,
        },
        laser_pose: rigid2(p[0], p[1], p[2]),
        robot_pose: rigid2(p[3], p[4], p[5]),
    })
}

fn robotlaser1(fields: &[&str]) -> Result<Parsed, String> {
    // ROBOTLASER1 type start_angle fov angular_res max_range accuracy remission_mode n r1..rn
    //   m rem1..remm laser_x laser_y laser_th robot_x robot_y robot_th tv rv fwd side turn ipc_ts host ts
    let head = finite_numbers(
        fields.get(1..8).ok_or("ROBOTLASER1: too short")?,
        "ROBOTLASER1 header",
    )?;
    // Counts larger than the line are refused before any index arithmetic (no overflow).
    let count = |at: usize, what: &str| -> Result<usize, String> {
        fields
            .get(at)
            .and_then(|f| f.parse::<usize>().ok())
            .filter(|&c| c <= fields.len())
            .ok_or_else(|| format!("ROBOTLASER1: missing or impossible {what}"))
    };
    let n = count(8, "beam count")?;
    let ranges: Vec<f32> = numbers(
        fields.get(9..9 + n).ok_or("ROBOTLASER1: too few ranges")?,
        "range",
    )?
    .into_iter()
    .map(|r| r as f32)
    .collect();
    let m = count(9 + n, "remission count")?;
    let rest = finite_numbers(
        fields
            .get(10 + n + m..10 + n + m + 12)
            .ok_or("ROBOTLASER1: too short")?,
        "pose",
    )?;
    let (angle_min, angle_increment) = (head[1] as f32, head[3] as f32);
    if !(angle_min.is_finite() && angle_increment.is_finite()) {
        return Err("ROBOTLASER1: start angle or angular resolution out of range".into());
    }
    Ok(Parsed {
        scan: LaserScan {
            time: time(rest[11], "ROBOTLASER1")?,
            angle_min,
            angle_increment,
            time_increment: 0.0,
            range_min: RANGE_MIN,
            range_max: (head[4] as f32).min(RANGE_MAX),
            ranges,
        },
        laser_pose: rigid2(rest[0], rest[1], rest[2]),
        robot_pose: rigid2(rest[3], rest[4], rest[5]),
    })
}

fn odom(fields: &[&str]) -> Result<OdometryReading, String> {
    let p = finite_numbers(fields.get(1..8).ok_or("ODOM: too short")?, "ODOM")?;
    Ok(OdometryReading {
        time: time(p[6], "ODOM")?,
        pose: rigid2(p[0], p[1], p[2]),
    })
}

/// Reads a CARMEN log.
pub fn read(input: impl BufRead, path: &Path) -> Result<Recording, SourceError> {
    let mut report = ReadReport::default();
    let mut events = Vec::new();
    let mut odometry_lines = Vec::new();
    let mut flaser_odometry = Vec::new();
    let mut base_from_laser = None;
    for (number, line) in input.lines().enumerate() {
        let line = line.map_err(|source| SourceError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let fields: Vec<&str> = line.split_whitespace().collect();
        let Some(&tag) = fields.first() else { continue };
        let parsed = match tag {
            "FLASER" => flaser(&fields).map(Some),
            "ROBOTLASER1" => robotlaser1(&fields).map(Some),
            "ODOM" => match odom(&fields) {
                Ok(o) => {
                    odometry_lines.push(SensorEvent::Odometry(o));
                    Ok(None)
                }
                Err(e) => Err(e),
            },
            _ => {
                if !tag.starts_with('#') {
                    report.skipped_other += 1;
                }
                Ok(None)
            }
        };
        // Finite poses can still compose to infinity (|x| near f64::MAX): such a line is malformed too.
        let parsed = parsed.and_then(|p| match p {
            Some(p) if !is_finite(&(p.robot_pose.inverse() * p.laser_pose)) => {
                Err("laser pose relative to the robot is not finite".to_owned())
            }
            other => Ok(other),
        });
        match parsed {
            Ok(Some(p)) => {
                base_from_laser.get_or_insert(p.robot_pose.inverse() * p.laser_pose);
                flaser_odometry.push(SensorEvent::Odometry(OdometryReading {
                    time: p.scan.time,
                    pose: p.robot_pose,
                }));
                events.push(SensorEvent::Scan(p.scan));
            }
            Ok(None) => {}
            Err(e) => {
                report.skipped_malformed += 1;
                report.problem(format!("line {}: {e}", number + 1));
            }
        }
    }
    if events.is_empty() && report.skipped_malformed > 0 {
        return Err(SourceError::Malformed {
            path: path.display().to_string(),
            format: "CARMEN log",
            source: None,
            what: format!(
                "no readable laser line; first problem: {}",
                report.problems.join("; ")
            ),
        });
    }
    events.extend(if odometry_lines.is_empty() {
        flaser_odometry
    } else {
        odometry_lines
    });
    report.extrinsic_source = if base_from_laser.is_some() {
        "first laser line's laser and robot poses".into()
    } else {
        "no laser lines: identity".into()
    };
    Ok(Recording::from_unsorted(
        events,
        base_from_laser.unwrap_or_else(Rigid2::identity),
        report,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_text(text: &str) -> Result<Recording, SourceError> {
        read(text.as_bytes(), Path::new("test.clf"))
    }

    const GOOD: &str = "FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 100.5 host 100.5\n";

    #[test]
    fn reads_a_flaser_line() {
        let recording = read_text(GOOD).unwrap();
        assert_eq!(recording.report.scans, 1);
        assert_eq!(recording.report.odometry, 1);
    }

    /// Fuzz finding (regression): a beam count near `usize::MAX` overflowed the field arithmetic (a panic
    /// in debug builds, an out-of-range slice in release).
    #[test]
    fn impossible_beam_counts_are_malformed_lines() {
        for line in [
            "FLASER 18446744073709551615 1.0 2.0\n",
            "FLASER 18446744073709551606 1.0 2.0\n",
            "ROBOTLASER1 0 -1.5 3.1 0.78 80 0.01 0 18446744073709551615 1.0\n",
            "ROBOTLASER1 0 -1.5 3.1 0.78 80 0.01 0 1 1.0 18446744073709551615 0.5\n",
        ] {
            let text = format!("{GOOD}{line}");
            let recording = read_text(&text).unwrap();
            assert_eq!(recording.report.skipped_malformed, 1, "{line}");
            assert_eq!(recording.report.scans, 1, "{line}");
        }
    }

    /// Fuzz finding (regression): `nan`, `inf`, angles beyond f32 and poses that compose to infinity
    /// were accepted as poses, times and scan geometry, so non-finite odometry and extrinsics reached LLO;
    /// times beyond i64 nanoseconds saturated (and their differences overflowed).
    #[test]
    fn non_finite_poses_and_geometry_are_malformed_lines() {
        for line in [
            "FLASER 3 1.0 2.0 3.0 nan 0.2 0.3 0.1 0.2 0.3 100.5 host 100.5\n",
            "FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 inf 0.3 100.5 host 100.5\n",
            "FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 -inf host 100.5\n",
            "FLASER 3 1.0 2.0 3.0 1e308 0 0 -1e308 0 0 100.5 host 100.5\n",
            "ODOM 1.0 nan 0.3 0 0 0 100.6\n",
            "ROBOTLASER1 0 nan 3.1 0.78 80 0.01 0 1 1.0 0 0 0 0 0 0 0 0 0 0 0 0 1.0\n",
            "ROBOTLASER1 0 1e308 3.1 0.78 80 0.01 0 1 1.0 0 0 0 0 0 0 0 0 0 0 0 0 1.0\n",
            "ODOM 1.0 2.0 0.3 0 0 0 1e300\n",
            "ODOM 1.0 2.0 0.3 0 0 0 -5\n",
        ] {
            let text = format!("{GOOD}{line}");
            let recording = read_text(&text).unwrap();
            assert_eq!(recording.report.skipped_malformed, 1, "{line}");
            let finite = recording.events.iter().all(|e| match e {
                SensorEvent::Odometry(o) => is_finite(&o.pose),
                SensorEvent::Scan(s) => s.angle_min.is_finite() && s.angle_increment.is_finite(),
                SensorEvent::Imu(_) => true,
            });
            assert!(finite, "{line}");
            assert!(is_finite(&recording.base_from_laser), "{line}");
        }
    }
}
