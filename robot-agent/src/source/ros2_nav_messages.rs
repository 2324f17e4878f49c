//! Encoding the messages the agent sends back to the robot's navigation (CDR, see [`CdrWriter`]):
//! `nav_msgs/msg/OccupancyGrid` (the site map, as Nav2's map server publishes it on `/map`),
//! `tf2_msgs/msg/TFMessage` (the `map -> odom` transform on `/tf`) and
//! `geometry_msgs/msg/PoseWithCovarianceStamped` (the robot's global pose, as AMCL publishes it).
//! Field order and types follow the messages' ROS 2 definitions (`common_interfaces`, `geometry2`);
//! a planar pose is written with z = 0 and the rotation as the quaternion (0, 0, sin θ/2, cos θ/2).

use mapping::geometry::Rigid2;
use mapping::grid::{CellIndex, ProbabilityGrid};
use mapping::sensor::Timestamp;

use super::cdr_writer::CdrWriter;

/// `std_msgs/msg/Header`.
fn header(w: &mut CdrWriter, stamp: Timestamp, frame_id: &str) {
    time(w, stamp);
    w.string(frame_id);
}

/// `builtin_interfaces/msg/Time`: seconds (`int32`, floor) and nanoseconds (`uint32`, 0..1e9).
fn time(w: &mut CdrWriter, stamp: Timestamp) {
    let sec = stamp.0.div_euclid(1_000_000_000);
    let nanosec = stamp.0.rem_euclid(1_000_000_000);
    w.i32(i32::try_from(sec).unwrap_or(if sec < 0 { i32::MIN } else { i32::MAX }));
    w.u32(u32::try_from(nanosec).unwrap_or(0));
}

/// `geometry_msgs/msg/Pose` (or `Transform`: the same seven `float64`s) of a planar pose.
fn planar_pose(w: &mut CdrWriter, pose: &Rigid2) {
    let half = pose.rotation.angle() / 2.0;
    for v in [
        pose.translation.x,
        pose.translation.y,
        0.0,
        0.0,
        0.0,
        half.sin(),
        half.cos(),
    ] {
        w.f64(v);
    }
}

/// One cell of a `nav_msgs/msg/OccupancyGrid`: -1 unknown, else the occupancy probability in percent
/// (0 free .. 100 occupied), as Nav2's map server fills it from a `trinary`-less (`scale`) map.
fn occupancy_percent(grid: &ProbabilityGrid, cell: CellIndex) -> i8 {
    if grid.is_known(&cell) {
        (100.0 * grid.probability(&cell)).round().clamp(0.0, 100.0) as i8
    } else {
        -1
    }
}

/// `nav_msgs/msg/OccupancyGrid` of `grid` in `frame_id` (cell (0, 0) at the grid's origin, rows of
/// increasing y, as the message defines it), stamped `stamp` (also its `map_load_time`).
pub fn occupancy_grid(grid: &ProbabilityGrid, stamp: Timestamp, frame_id: &str) -> Vec<u8> {
    let limits = grid.limits();
    let (width, height) = (limits.width.max(0), limits.height.max(0));
    let mut cells = Vec::with_capacity(limits.num_cells());
    for iy in 0..height {
        for ix in 0..width {
            cells.push(occupancy_percent(grid, CellIndex::new(ix, iy)));
        }
    }
    let mut w = CdrWriter::with_capacity(cells.len() + 128);
    header(&mut w, stamp, frame_id);
    time(&mut w, stamp); // info.map_load_time
    w.f32(limits.resolution as f32);
    w.u32(width.cast_unsigned());
    w.u32(height.cast_unsigned());
    planar_pose(&mut w, &Rigid2::new(limits.origin, 0.0));
    w.i8_sequence(&cells);
    w.finish()
}

/// One `geometry_msgs/msg/TransformStamped` for [`tf_message`].
#[derive(Clone, Debug, PartialEq)]
pub struct StampedTransform {
    /// Stamp.
    pub stamp: Timestamp,
    /// Parent frame (`header.frame_id`), e.g. `map`.
    pub parent: String,
    /// Child frame (`child_frame_id`), e.g. `odom`.
    pub child: String,
    /// `parent_from_child`.
    pub parent_from_child: Rigid2,
}

/// `tf2_msgs/msg/TFMessage` of planar transforms.
pub fn tf_message(transforms: &[StampedTransform]) -> Vec<u8> {
    let mut w = CdrWriter::new();
    w.sequence_len(transforms.len());
    for t in transforms {
        header(&mut w, t.stamp, &t.parent);
        w.string(&t.child);
        planar_pose(&mut w, &t.parent_from_child);
    }
    w.finish()
}

/// `geometry_msgs/msg/PoseWithCovarianceStamped`: `frame_from_base` in `frame_id` with a diagonal
/// covariance of `sigma_xy_m²` on x and y, `sigma_yaw_rad²` on yaw, and 1e6 (unknown) on z, roll and
/// pitch (row-major 6×6 over x, y, z, roll, pitch, yaw, as the message defines it).
pub fn pose_with_covariance_stamped(
    stamp: Timestamp,
    frame_id: &str,
    frame_from_base: &Rigid2,
    sigma_xy_m: f64,
    sigma_yaw_rad: f64,
) -> Vec<u8> {
    let mut w = CdrWriter::new();
    header(&mut w, stamp, frame_id);
    planar_pose(&mut w, frame_from_base);
    let diagonal = [
        sigma_xy_m * sigma_xy_m,
        sigma_xy_m * sigma_xy_m,
        1e6,
        1e6,
        1e6,
        sigma_yaw_rad * sigma_yaw_rad,
    ];
    for (row, variance) in diagonal.iter().enumerate() {
        for col in 0..6 {
            w.f64(if row == col { *variance } else { 0.0 });
        }
    }
    w.finish()
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;
    use mapping::grid::MapLimits;
    use nalgebra::Vector2;

    use super::super::{CdrReader, ros2_messages};
    use super::*;

    #[test]
    fn occupancy_grid_reads_back_field_by_field() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(-1.0, 2.0), 3, 2));
        grid.set_probability(&CellIndex::new(0, 0), 0.9);
        grid.set_probability(&CellIndex::new(2, 1), 0.1);
        let bytes = occupancy_grid(&grid, Timestamp::from_sec_nsec(12, 5), "map");
        let mut r = CdrReader::new(&bytes).unwrap();
        assert_eq!(r.i32("sec").unwrap(), 12);
        assert_eq!(r.u32("nsec").unwrap(), 5);
        assert_eq!(r.string("frame").unwrap(), "map");
        assert_eq!(r.i32("load sec").unwrap(), 12);
        assert_eq!(r.u32("load nsec").unwrap(), 5);
        assert_eq!(r.f32("resolution").unwrap().to_bits(), 0.05f32.to_bits());
        assert_eq!(r.u32("width").unwrap(), 3);
        assert_eq!(r.u32("height").unwrap(), 2);
        let origin: Vec<f64> = (0..7).map(|_| r.f64("origin").unwrap()).collect();
        assert_eq!(origin, vec![-1.0, 2.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        assert_eq!(r.sequence_len(1, "data").unwrap(), 6);
        let data: Vec<i8> = (0..6).map(|_| r.i8("cell").unwrap()).collect();
        assert_eq!(data, vec![90, -1, -1, -1, -1, 10]);
        assert_eq!(r.remaining(), 0);
    }

    #[test]
    fn transforms_and_poses_decode_with_the_readers_of_recorded_messages() {
        let map_from_odom = rigid2(1.5, -2.0, 0.4);
        let bytes = tf_message(&[StampedTransform {
            stamp: Timestamp::from_sec_nsec(3, 0),
            parent: "map".into(),
            child: "odom".into(),
            parent_from_child: map_from_odom,
        }]);
        let decoded = ros2_messages::tf_message(&bytes).unwrap();
        assert_eq!(decoded.len(), 1);
        assert_eq!(
            (decoded[0].parent.as_str(), decoded[0].child.as_str()),
            ("map", "odom")
        );
        let got = decoded[0].parent_from_child;
        assert!((got.translation.vector - map_from_odom.translation.vector).norm() < 1e-12);
        assert!((got.rotation.angle() - 0.4).abs() < 1e-12);

        let pose = rigid2(-4.0, 7.0, -2.5);
        let bytes =
            pose_with_covariance_stamped(Timestamp::from_sec_nsec(9, 1), "map", &pose, 0.1, 0.05);
        let mut r = CdrReader::new(&bytes).unwrap();
        r.i32("sec").unwrap();
        r.u32("nsec").unwrap();
        assert_eq!(r.string("frame").unwrap(), "map");
        let p: Vec<f64> = (0..7).map(|_| r.f64("pose").unwrap()).collect();
        assert_eq!((p[0], p[1]), (-4.0, 7.0));
        assert!((2.0 * p[5].atan2(p[6]) - (-2.5)).abs() < 1e-12);
        let covariance: Vec<f64> = (0..36).map(|_| r.f64("cov").unwrap()).collect();
        assert!((covariance[0] - 0.01).abs() < 1e-15 && (covariance[35] - 0.0025).abs() < 1e-15);
        assert_eq!(r.remaining(), 0);
    }
}
