//! Decoding the few ROS 2 message types we need from their CDR payloads (see [`CdrReader`] for the
//! encoding): `sensor_msgs/msg/LaserScan`, `nav_msgs/msg/Odometry`, `sensor_msgs/msg/Imu` and
//! `tf2_msgs/msg/TFMessage`. They differ from ROS1's only in the header (no `seq`; the stamp is
//! `builtin_interfaces/Time { int32 sec; uint32 nanosec }`) and in the encoding; the values they give go
//! through the same conversions as the ROS1 reader's (`ros_messages::{laser_scan_from, planar_pose}`), so
//! the same recording gives the same events from either.

use mapping::geometry::Rigid2;
use mapping::sensor::{ImuReading, LaserScan, OdometryReading, Timestamp};

use super::cdr_reader::CdrReader;
use super::ros_messages::{DecodeError, PlanarTransform, ScanFields, laser_scan_from, planar_pose};

/// `std_msgs/msg/Header`: (stamp, frame_id).
fn header(r: &mut CdrReader<'_>) -> Result<(Timestamp, String), DecodeError> {
    let sec = r.i32("header.stamp.sec")?;
    let nanosec = r.u32("header.stamp.nanosec")?;
    let frame = r.string("header.frame_id")?;
    Ok((
        Timestamp(i64::from(sec) * 1_000_000_000 + i64::from(nanosec)),
        frame,
    ))
}

/// `geometry_msgs/msg/Pose` or `Transform` (position/translation, then the quaternion x, y, z, w).
fn planar(r: &mut CdrReader<'_>, what: &str) -> Result<Rigid2, DecodeError> {
    let x = r.f64(what)?;
    let y = r.f64(what)?;
    let _z = r.f64(what)?;
    let q = [r.f64(what)?, r.f64(what)?, r.f64(what)?, r.f64(what)?];
    planar_pose(x, y, q, what)
}

/// `sensor_msgs/msg/LaserScan` and its frame id.
pub fn laser_scan(payload: &[u8]) -> Result<(LaserScan, String), DecodeError> {
    let mut r = CdrReader::new(payload)?;
    let (time, frame) = header(&mut r)?;
    let angle_min = r.f32("angle_min")?;
    let _angle_max = r.f32("angle_max")?;
    let angle_increment = r.f32("angle_increment")?;
    let time_increment = r.f32("time_increment")?;
    let _scan_time = r.f32("scan_time")?;
    let range_min = r.f32("range_min")?;
    let range_max = r.f32("range_max")?;
    let ranges = r.f32_sequence("ranges")?;
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

/// `nav_msgs/msg/Odometry` (the pose only).
pub fn odometry(payload: &[u8]) -> Result<OdometryReading, DecodeError> {
    let mut r = CdrReader::new(payload)?;
    let (time, _frame) = header(&mut r)?;
    let _child = r.string("child_frame_id")?;
    let pose = planar(&mut r, "pose.pose")?;
    Ok(OdometryReading { time, pose })
}

/// `sensor_msgs/msg/Imu` (yaw rate only).
pub fn imu(payload: &[u8]) -> Result<ImuReading, DecodeError> {
    let mut r = CdrReader::new(payload)?;
    let (time, _frame) = header(&mut r)?;
    r.skip(8, 4 + 9, "orientation and its covariance")?;
    let _wx = r.f64("angular_velocity.x")?;
    let _wy = r.f64("angular_velocity.y")?;
    let yaw_rate = r.f64("angular_velocity.z")?;
    if !yaw_rate.is_finite() {
        return Err(DecodeError("non-finite angular_velocity.z".into()));
    }
    Ok(ImuReading { time, yaw_rate })
}

/// `tf2_msgs/msg/TFMessage`: every transform, `parent_from_child`.
pub fn tf_message(payload: &[u8]) -> Result<Vec<PlanarTransform>, DecodeError> {
    let mut r = CdrReader::new(payload)?;
    // A TransformStamped takes at least 8 (stamp) + 4 + 4 (two empty strings) + 56 (transform) bytes.
    let n = r.sequence_len(72, "transforms length")?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let (_time, parent) = header(&mut r)?;
        let child = r.string("child_frame_id")?;
        let parent_from_child = planar(&mut r, "transform")?;
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

    /// A little CDR writer for the tests: aligns relative to the body like a real serializer.
    struct Writer {
        bytes: Vec<u8>,
        big_endian: bool,
    }

    impl Writer {
        fn new(big_endian: bool) -> Self {
            Self {
                bytes: vec![0, u8::from(!big_endian), 0, 0],
                big_endian,
            }
        }
        fn align(&mut self, n: usize) {
            while !(self.bytes.len() - 4).is_multiple_of(n) {
                self.bytes.push(0);
            }
        }
        fn u32(&mut self, v: u32) {
            self.align(4);
            let b = if self.big_endian {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            };
            self.bytes.extend_from_slice(&b);
        }
        fn f32(&mut self, v: f32) {
            self.u32(v.to_bits());
        }
        fn f64(&mut self, v: f64) {
            self.align(8);
            let b = if self.big_endian {
                v.to_bits().to_be_bytes()
            } else {
                v.to_bits().to_le_bytes()
            };
            self.bytes.extend_from_slice(&b);
        }
        fn string(&mut self, s: &str) {
            self.u32(s.len() as u32 + 1);
            self.bytes.extend_from_slice(s.as_bytes());
            self.bytes.push(0);
        }
        fn header(&mut self, sec: i32, nanosec: u32, frame: &str) {
            self.u32(sec.cast_unsigned());
            self.u32(nanosec);
            self.string(frame);
        }
    }

    #[test]
    fn laser_scan_in_both_byte_orders_and_truncation_is_an_error() {
        for big_endian in [false, true] {
            let mut w = Writer::new(big_endian);
            w.header(10, 500, "laser");
            for v in [-1.5f32, 1.5, 0.5, 0.0, 0.1, 0.02, 80.0] {
                w.f32(v);
            }
            w.u32(3);
            for v in [1.0f32, f32::NAN, 81.9] {
                w.f32(v);
            }
            w.u32(0);
            let b = w.bytes;
            let (scan, frame) = laser_scan(&b).unwrap();
            assert_eq!(frame, "laser");
            assert_eq!(scan.time, Timestamp::from_sec_nsec(10, 500));
            assert_eq!(scan.angle_min.to_bits(), (-1.5f32).to_bits());
            assert_eq!(scan.angle_increment.to_bits(), 0.5f32.to_bits());
            assert_eq!(scan.range_max.to_bits(), 80.0f32.to_bits());
            assert_eq!(scan.ranges.len(), 3);
            assert!(scan.ranges[1].is_nan());
            assert_eq!(scan.ranges[2].to_bits(), 81.9f32.to_bits());
            for cut in [0, 3, 5, 20, b.len() - 9] {
                assert!(laser_scan(&b[..cut]).is_err(), "cut at {cut}");
            }
        }
    }

    #[test]
    fn odometry_and_tf_poses_are_projected_to_the_plane() {
        // A frame id of odd length makes the pose's f64s need padding: the alignment is checked.
        let yaw = 0.7f64;
        let mut w = Writer::new(false);
        w.header(3, 4, "odom");
        w.string("base_link");
        for v in [
            1.0,
            2.0,
            0.0,
            0.0,
            0.0,
            (yaw / 2.0).sin(),
            (yaw / 2.0).cos(),
        ] {
            w.f64(v);
        }
        for _ in 0..36 {
            w.f64(0.0);
        }
        let odom = odometry(&w.bytes).unwrap();
        assert_eq!(odom.time, Timestamp::from_sec_nsec(3, 4));
        assert!((odom.pose.translation.x - 1.0).abs() < 1e-12);
        assert!((odom.pose.translation.y - 2.0).abs() < 1e-12);
        assert!((odom.pose.rotation.angle() - yaw).abs() < 1e-12);

        let mut w = Writer::new(true);
        w.u32(1);
        w.header(0, 0, "base_link");
        w.string("laser");
        for v in [0.3, -0.1, 0.2, 0.0, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        let tf = tf_message(&w.bytes).unwrap();
        assert_eq!(tf.len(), 1);
        assert_eq!(tf[0].parent, "base_link");
        assert_eq!(tf[0].child, "laser");
        assert!((tf[0].parent_from_child.translation.x - 0.3).abs() < 1e-12);
        assert!(tf_message(&w.bytes[..w.bytes.len() - 1]).is_err());
    }

    #[test]
    fn imu_reads_the_yaw_rate() {
        let mut w = Writer::new(false);
        w.header(1, 0, "imu");
        for _ in 0..13 {
            w.f64(0.0);
        }
        for v in [0.1, 0.2, 0.3] {
            w.f64(v);
        }
        let imu = imu(&w.bytes).unwrap();
        assert_eq!(imu.yaw_rate.to_bits(), 0.3f64.to_bits());
        assert_eq!(imu.time, Timestamp::from_sec_nsec(1, 0));
    }
}
