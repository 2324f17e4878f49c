//! Trajectory nodes.

use mapping::geometry::Rigid2;
use mapping::pose_graph::NodeId;
use mapping::sensor::Timestamp;
use nalgebra::Point2;

use crate::convert::{points_from_pb, points_to_pb};
use crate::{ConversionError, FORMAT_VERSION, check_format_version, pb, pose_from_pb, pose_to_pb};

/// A trajectory node as it travels on the wire.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeSnapshot {
    /// The node.
    pub id: NodeId,
    /// When its scan was taken.
    pub time: Timestamp,
    /// `local_from_tracking`.
    pub local_pose: Rigid2,
    /// Voxel-filtered hits in the tracking frame (m).
    pub points: Vec<Point2<f32>>,
}

impl From<&NodeSnapshot> for pb::Node {
    fn from(node: &NodeSnapshot) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            id: Some(node.id.into()),
            time_ns: node.time.0,
            local_pose: Some(pose_to_pb(&node.local_pose)),
            points_xy: points_to_pb(&node.points),
        }
    }
}

impl TryFrom<&pb::Node> for NodeSnapshot {
    type Error = ConversionError;

    fn try_from(node: &pb::Node) -> Result<Self, ConversionError> {
        const M: &str = "Node";
        check_format_version(M, node.format_version)?;
        Ok(Self {
            id: node
                .id
                .ok_or(ConversionError::MissingField {
                    message: M,
                    field: "id",
                })?
                .into(),
            time: Timestamp(node.time_ns),
            local_pose: pose_from_pb(node.local_pose.as_ref(), M, "local_pose")?,
            points: points_from_pb(&node.points_xy, M, "points_xy")?,
        })
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    #[test]
    fn nodes_round_trip_and_need_an_id() {
        let node = NodeSnapshot {
            id: NodeId {
                trajectory: 3,
                index: 9,
            },
            time: Timestamp(1_234_567_890),
            local_pose: rigid2(0.5, 0.25, -1.0),
            points: vec![Point2::new(1.0, 2.0), Point2::new(-3.5, 0.125)],
        };
        let wire = pb::Node::from(&node);
        let back = NodeSnapshot::try_from(&wire).unwrap();
        assert_eq!(
            (back.id, back.time, &back.points),
            (node.id, node.time, &node.points)
        );
        approx::assert_relative_eq!(back.local_pose, node.local_pose, epsilon = 1e-12);
        let mut no_id = wire;
        no_id.id = None;
        assert!(NodeSnapshot::try_from(&no_id).is_err());
    }
}
