//! Poses, point lists and format versions.

use mapping::geometry::{Rigid2, Rigid2Ext as _, rigid2};
use nalgebra::Point2;

use crate::{ConversionError, FORMAT_VERSION, pb};

/// The wire form of a pose.
pub fn pose_to_pb(pose: &Rigid2) -> pb::Pose2 {
    pb::Pose2 {
        x: pose.x(),
        y: pose.y(),
        theta: pose.theta(),
    }
}

/// A pose from the wire; `pose` is the (optional, message-typed) field `message.field`. Refuses a missing
/// pose and non-finite numbers.
pub fn pose_from_pb(
    pose: Option<&pb::Pose2>,
    message: &'static str,
    field: &'static str,
) -> Result<Rigid2, ConversionError> {
    let pose = pose.ok_or(ConversionError::MissingField { message, field })?;
    if !(pose.x.is_finite() && pose.y.is_finite() && pose.theta.is_finite()) {
        return Err(ConversionError::NotFinite { message, field });
    }
    Ok(rigid2(pose.x, pose.y, pose.theta))
}

/// Refuses a record whose `format_version` is not [`FORMAT_VERSION`].
pub fn check_format_version(message: &'static str, got: u32) -> Result<(), ConversionError> {
    if got == FORMAT_VERSION {
        Ok(())
    } else {
        Err(ConversionError::UnsupportedFormatVersion {
            message,
            got,
            oldest: FORMAT_VERSION,
            newest: FORMAT_VERSION,
        })
    }
}

/// Refuses a non-finite number.
pub(crate) fn check_finite(
    value: f64,
    message: &'static str,
    field: &'static str,
) -> Result<f64, ConversionError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(ConversionError::NotFinite { message, field })
    }
}

/// Points as interleaved `x, y` floats.
pub(crate) fn points_to_pb(points: &[Point2<f32>]) -> Vec<f32> {
    points.iter().flat_map(|p| [p.x, p.y]).collect()
}

/// Points from interleaved `x, y` floats: an even count of finite numbers.
/// Largest coordinate of a scan point accepted from the wire, metres from the robot. 2D LiDARs reach
/// tens of metres; a point 10¹⁰ m away makes the matchers' angular step zero and their search unbounded
/// (a fuzz finding: one such point in an upload killed the site map's worker with "capacity overflow").
pub(crate) const MAX_POINT_COORDINATE_M: f32 = 1.0e4;

pub(crate) fn points_from_pb(
    xy: &[f32],
    message: &'static str,
    field: &'static str,
) -> Result<Vec<Point2<f32>>, ConversionError> {
    if !xy.len().is_multiple_of(2) {
        return Err(ConversionError::BadSize {
            message,
            field,
            expected: xy.len() + 1,
            got: xy.len(),
        });
    }
    if xy.iter().any(|v| !v.is_finite()) {
        return Err(ConversionError::NotFinite { message, field });
    }
    if let Some(v) = xy.iter().find(|v| v.abs() > MAX_POINT_COORDINATE_M) {
        return Err(ConversionError::OutOfRange {
            message,
            field,
            value: (*v).into(),
            expected: "at most 10000 m from the robot (MAX_POINT_COORDINATE_M)",
        });
    }
    Ok(xy
        .chunks_exact(2)
        .map(|c| Point2::new(c[0], c[1]))
        .collect())
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;
    use proptest::prelude::*;

    use super::*;

    /// Fuzz finding (regression): a finite point 10¹⁰ m away was accepted and made the server's
    /// branch-and-bound search allocate without bound ("capacity overflow" in the site map's worker).
    #[test]
    fn points_too_far_away_are_refused() {
        assert!(points_from_pb(&[1.0, 2.0, 9_999.0, -9_999.0], "Node", "points_xy").is_ok());
        let err = points_from_pb(&[1.0, 2.0, 1.0e10, 0.0], "Node", "points_xy").unwrap_err();
        assert!(matches!(err, ConversionError::OutOfRange { .. }), "{err}");
        // The limit the message states is the one checked.
        assert!(
            err.to_string()
                .contains(&format!("at most {MAX_POINT_COORDINATE_M} m")),
            "{err}"
        );
    }

    proptest! {
        #[test]
        fn pose_round_trips(x in -1e4..1e4_f64, y in -1e4..1e4_f64, theta in -3.0..3.0_f64) {
            let pose = rigid2(x, y, theta);
            let back = pose_from_pb(Some(&pose_to_pb(&pose)), "Pose2", "p").unwrap();
            assert_relative_eq!(back, pose, epsilon = 1e-12);
        }

        #[test]
        fn points_round_trip(xy in proptest::collection::vec(-100.0..100.0_f32, 0..40)) {
            let xy: Vec<f32> = xy[..xy.len() / 2 * 2].to_vec();
            let points = points_from_pb(&xy, "Node", "points_xy").unwrap();
            assert_eq!(points.len() * 2, xy.len());
            assert_eq!(points_to_pb(&points), xy);
        }
    }

    #[test]
    fn bad_poses_and_points_are_named() {
        assert_eq!(
            pose_from_pb(None, "Submap", "global_pose"),
            Err(ConversionError::MissingField {
                message: "Submap",
                field: "global_pose"
            })
        );
        let inf = pb::Pose2 {
            x: 0.0,
            y: f64::INFINITY,
            theta: 0.0,
        };
        assert!(matches!(
            pose_from_pb(Some(&inf), "Submap", "global_pose"),
            Err(ConversionError::NotFinite {
                field: "global_pose",
                ..
            })
        ));
        assert!(matches!(
            points_from_pb(&[1.0, 2.0, 3.0], "Node", "points_xy"),
            Err(ConversionError::BadSize { got: 3, .. })
        ));
        assert!(matches!(
            points_from_pb(&[1.0, f32::NAN], "Node", "points_xy"),
            Err(ConversionError::NotFinite { .. })
        ));
        assert!(check_format_version("Grid", 2).is_err());
        assert!(check_format_version("Grid", 0).is_err());
        assert!(check_format_version("Grid", FORMAT_VERSION).is_ok());
    }
}
