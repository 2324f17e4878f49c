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

fn flaser(fields: &[&str]) -> Result<Parsed, String> {
    let n: usize = fields
        .get(1)
        .and_then(|f| f.parse().ok())
        .ok_or("FLASER: missing beam count")?;
    if fields.len() < 2 + n + 9 {
        return Err(format!(
            "FLASER: {} fields, expected {} for {n} beams",
            fields.len(),
            2 + n + 9
        ));
    }
    let ranges = numbers(&fields[2..2 + n], "FLASER range")?
        .into_iter()
        .map(|r| r as f32)
        .collect();
    let p = numbers(&fields[2 + n..2 + n + 7], "FLASER pose")?;
    let increment = if n > 1 {
        std::f64::consts::PI / (n - 1) as f64
    } else {
        0.0
    };
    Ok(Parsed {
        scan: LaserScan {
            time: Timestamp::from_secs_f64(p[6]),
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
    let head = numbers(
        fields.get(1..8).ok_or("ROBOTLASER1: too short")?,
        "ROBOTLASER1 header",
    )?;
    let n: usize = fields
        .get(8)
        .and_then(|f| f.parse().ok())
        .ok_or("ROBOTLASER1: missing beam count")?;
    let ranges: Vec<f32> = numbers(
        fields.get(9..9 + n).ok_or("ROBOTLASER1: too few ranges")?,
        "range",
    )?
    .into_iter()
    .map(|r| r as f32)
    .collect();
    let m: usize = fields
        .get(9 + n)
        .and_then(|f| f.parse().ok())
        .ok_or("ROBOTLASER1: missing remission count")?;
    let rest = numbers(
        fields
            .get(10 + n + m..10 + n + m + 12)
            .ok_or("ROBOTLASER1: too short")?,
        "pose",
    )?;
    Ok(Parsed {
        scan: LaserScan {
            time: Timestamp::from_secs_f64(rest[11]),
            angle_min: head[1] as f32,
            angle_increment: head[3] as f32,
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
    let p = numbers(fields.get(1..8).ok_or("ODOM: too short")?, "ODOM")?;
    Ok(OdometryReading {
        time: Timestamp::from_secs_f64(p[6]),
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
