//! Decoding the few ROS1 message types we need from their serialized bytes (little-endian, strings and
//! arrays prefixed by a u32 length). Every read is bounds-checked: a truncated message is an error, never
//! a panic.

use mapping::geometry::{Rigid2, rigid2};
use mapping::sensor::{ImuReading, LaserScan, OdometryReading, Timestamp};

/// A message decoding failure (ROS1 or CDR): what was being read and at which byte.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct DecodeError(pub String);

struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self { data, pos: 0 }
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], DecodeError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.data.len())
            .ok_or_else(|| {
                DecodeError(format!(
                    "truncated at byte {} of {} reading {what}",
                    self.pos,
                    self.data.len()
                ))
            })?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u32(&mut self, what: &str) -> Result<u32, DecodeError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn f32(&mut self, what: &str) -> Result<f32, DecodeError> {
        Ok(f32::from_bits(self.u32(what)?))
    }

    fn f64(&mut self, what: &str) -> Result<f64, DecodeError> {
        let b = self.take(8, what)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(f64::from_le_bytes(a))
    }

    fn string(&mut self, what: &str) -> Result<String, DecodeError> {
        let n = self.u32(what)? as usize;
        Ok(String::from_utf8_lossy(self.take(n, what)?).into_owned())
    }

    fn skip_f64s(&mut self, n: usize, what: &str) -> Result<(), DecodeError> {
        self.take(8 * n, what).map(|_| ())
    }

    /// `std_msgs/Header`: (stamp, frame_id).
    fn header(&mut self) -> Result<(Timestamp, String), DecodeError> {
        let _seq = self.u32("header.seq")?;
        let sec = self.u32("header.stamp.sec")?;
        let nsec = self.u32("header.stamp.nsec")?;
        let frame = self.string("header.frame_id")?;
        Ok((Timestamp::from_sec_nsec(sec, nsec), frame))
    }

    /// `geometry_msgs/Pose` or `Transform` (position/translation then quaternion) projected to the plane.
    fn planar_pose(&mut self, what: &str) -> Result<Rigid2, DecodeError> {
        let x = self.f64(what)?;
        let y = self.f64(what)?;
        let _z = self.f64(what)?;
        let (qx, qy, qz, qw) = (
            self.f64(what)?,
            self.f64(what)?,
            self.f64(what)?,
            self.f64(what)?,
        );
        planar_pose(x, y, [qx, qy, qz, qw], what)
    }
}

/// A 3-D position and quaternion `[x, y, z, w]` projected to the plane (yaw about z); ROS1 and ROS 2
/// readers share it so both give the same pose from the same values.
pub(super) fn planar_pose(x: f64, y: f64, q: [f64; 4], what: &str) -> Result<Rigid2, DecodeError> {
    let yaw = mapping::geometry::yaw_from_quaternion(q);
    if !(x.is_finite() && y.is_finite() && yaw.is_finite()) {
        return Err(DecodeError(format!("non-finite {what}")));
    }
    Ok(rigid2(x, y, yaw))
}

/// The raw fields of a `sensor_msgs/LaserScan` (ROS1 or ROS 2) that evermap uses.
pub(super) struct ScanFields {
    pub time: Timestamp,
    pub angle_min: f32,
    pub angle_increment: f32,
    pub time_increment: f32,
    pub range_min: f32,
    pub range_max: f32,
    pub ranges: Vec<f32>,
}

/// Checks the scan geometry and replaces a non-finite `time_increment` or `range_min` by 0; ROS1 and
/// ROS 2 readers share it so both give the same scan from the same values.
pub(super) fn laser_scan_from(f: ScanFields) -> Result<LaserScan, DecodeError> {
    if !(f.angle_min.is_finite() && f.angle_increment.is_finite() && f.range_max.is_finite()) {
        return Err(DecodeError(
            "non-finite scan geometry (angle_min, angle_increment or range_max)".into(),
        ));
    }
    Ok(LaserScan {
        time: f.time,
        angle_min: f.angle_min,
        angle_increment: f.angle_increment,
        time_increment: if f.time_increment.is_finite() {
            f.time_increment
        } else {
            0.0
        },
        range_min: if f.range_min.is_finite() {
            f.range_min
        } else {
            0.0
        },
        range_max: f.range_max,
        ranges: f.ranges,
    })
}

/// `sensor_msgs/LaserScan` and its frame id.
pub fn laser_scan(data: &[u8]) -> Result<(LaserScan, String), DecodeError> {
    let mut c = Cursor::new(data);
    let (time, frame) = c.header()?;
    let angle_min = c.f32("angle_min")?;
    let _angle_max = c.f32("angle_max")?;
    let angle_increment = c.f32("angle_increment")?;
    let time_increment = c.f32("time_increment")?;
    let _scan_time = c.f32("scan_time")?;
    let range_min = c.f32("range_min")?;
    let range_max = c.f32("range_max")?;
    let n = c.u32("ranges length")? as usize;
    let bytes = c.take(4 * n, "ranges")?;
    let ranges: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let scan = laser_scan_from(ScanFields {
        time,
        angle_min,
        angle_increment,
        time_increment,
        range_min,
        range_max,
        ranges,
    })?;
    Ok((scan, frame))
}

/// `nav_msgs/Odometry`.
pub fn odometry(data: &[u8]) -> Result<OdometryReading, DecodeError> {
    let mut c = Cursor::new(data);
    let (time, _frame) = c.header()?;
    let _child = c.string("child_frame_id")?;
    let pose = c.planar_pose("pose.pose")?;
    Ok(OdometryReading { time, pose })
}

/// `sensor_msgs/Imu` (yaw rate only).
pub fn imu(data: &[u8]) -> Result<ImuReading, DecodeError> {
    let mut c = Cursor::new(data);
    let (time, _frame) = c.header()?;
    c.skip_f64s(4 + 9, "orientation")?;
    let _wx = c.f64("angular_velocity")?;
    let _wy = c.f64("angular_velocity")?;
    let yaw_rate = c.f64("angular_velocity")?;
    if !yaw_rate.is_finite() {
        return Err(DecodeError("non-finite angular_velocity.z".into()));
    }
    Ok(ImuReading { time, yaw_rate })
}

/// One planar transform of a `tf2_msgs/TFMessage`: `parent_from_child`.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanarTransform {
    /// Parent frame id.
    pub parent: String,
    /// Child frame id.
    pub child: String,
    /// `parent_from_child`.
    pub parent_from_child: Rigid2,
}

/// `tf2_msgs/TFMessage` (or `tf/tfMessage`, the same layout).
pub fn tf_message(data: &[u8]) -> Result<Vec<PlanarTransform>, DecodeError> {
    let mut c = Cursor::new(data);
    let n = c.u32("transforms length")? as usize;
    let mut out = Vec::with_capacity(n.min(64));
    for _ in 0..n {
        let (_time, parent) = c.header()?;
        let child = c.string("child_frame_id")?;
        let parent_from_child = c.planar_pose("transform")?;
        out.push(PlanarTransform {
            parent,
            child,
            parent_from_child,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(bytes: &mut Vec<u8>, sec: u32, nsec: u32, frame: &str) {
        bytes.extend_from_slice(&7u32.to_le_bytes());
        bytes.extend_from_slice(&sec.to_le_bytes());
        bytes.extend_from_slice(&nsec.to_le_bytes());
        bytes.extend_from_slice(&(frame.len() as u32).to_le_bytes());
        bytes.extend_from_slice(frame.as_bytes());
    }

    #[test]
    fn laser_scan_round_trip_and_truncation_is_an_error() {
        let mut b = Vec::new();
        header(&mut b, 10, 500, "laser");
        for v in [-1.5f32, 1.5, 0.5, 0.0, 0.1, 0.02, 80.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&3u32.to_le_bytes());
        for v in [1.0f32, f32::NAN, 81.9] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&0u32.to_le_bytes());
        let (scan, frame) = laser_scan(&b).unwrap();
        assert_eq!(frame, "laser");
        assert_eq!(scan.time, Timestamp::from_sec_nsec(10, 500));
        assert_eq!(scan.ranges.len(), 3);
        assert!(scan.ranges[1].is_nan());
        for cut in [0, 5, 20, b.len() - 9] {
            assert!(laser_scan(&b[..cut]).is_err(), "cut at {cut}");
        }
    }
}
