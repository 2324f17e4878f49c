//! One upload from a robot: a numbered batch of LLO output for one session.

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;
use mapping::local_slam::LloNode;
use mapping::pose_graph::SubmapId;
use mapping::sensor::Timestamp;
use nalgebra::Point2;

use crate::convert::{points_from_pb, points_to_pb};
use crate::{
    ConversionError, FORMAT_VERSION, check_format_version, grid_from_pb, grid_to_pb, pb,
    pose_from_pb, pose_to_pb,
};

/// LLO inserted a node.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeAdded {
    /// When the node's scan was taken.
    pub time: Timestamp,
    /// `local_from_tracking`.
    pub local_pose: Rigid2,
    /// Voxel-filtered hits in the tracking frame (m).
    pub points: Vec<Point2<f32>>,
    /// `(index, local_from_submap)` of each submap the node was inserted into.
    pub insertion_submaps: Vec<(u32, Rigid2)>,
    /// See `mapping::local_slam::TrajectoryNodeData::recovered`.
    pub recovered: bool,
}

impl NodeAdded {
    /// The node as global SLAM takes it, with the submaps its insertion finished (`(index, grid)`, the
    /// `SubmapFinished` items after it).
    pub fn to_llo_node(&self, finished_submaps: Vec<(usize, ProbabilityGrid)>) -> LloNode {
        LloNode {
            time: self.time,
            local_pose: self.local_pose,
            points: self.points.clone(),
            insertion_submaps: self
                .insertion_submaps
                .iter()
                .map(|(index, pose)| (*index as usize, *pose))
                .collect(),
            finished_submaps,
            recovered: self.recovered,
        }
    }
}

/// One item of an [`UploadBatch`].
#[derive(Clone, Debug, PartialEq)]
pub enum UploadItem {
    /// A new node.
    NodeAdded(NodeAdded),
    /// A submap finished by the node just before it in the batch.
    SubmapFinished {
        /// Submap index within the session's trajectory.
        index: u32,
        /// The grid, in the session's local frame.
        grid: ProbabilityGrid,
    },
    /// Where the session's local frame is believed to sit in the site frame.
    SessionStartPrior {
        /// `global_from_local`.
        global_from_local: Rigid2,
        /// The robot runs GLM and sends [`UploadItem::GlobalMatch`] items: the server searches only
        /// within the session.
        glm_on_robot: bool,
        /// The prior is the robot's dock placement: where its last session ended, checked against the
        /// site map by the session's first nodes (see [`UploadItem::DockPlacementKept`]).
        at_dock: bool,
        /// The first and last index of the session's nodes whose scans the robot's search fitted to the
        /// site map at this placement (`None`: a prior given without such a search).
        fitted: Option<(u32, u32)>,
    },
    /// GLM on the robot: the node before it (after that node's `SubmapFinished` items) matched a global
    /// submap of the site.
    GlobalMatch {
        /// The global submap.
        submap: SubmapId,
        /// The node's measured pose in the submap's frame.
        submap_from_node: Rigid2,
        /// Branch-and-bound score in `[0, 1]`.
        score: f32,
    },
    /// The robot's dock placement ([`UploadItem::SessionStartPrior`] with `at_dock`), still on probation
    /// at the session's end, stands: no match disputed it and no rival of its check fits the route
    /// decisively better (`mapping::lifelong::SessionStart::finish`), so the session is committed there
    /// instead of being dropped. Sent once, before [`UploadItem::SessionEnd`].
    DockPlacementKept,
    /// The session ended.
    SessionEnd,
}

/// A batch of one session's LLO output, numbered by `seq` (1, 2, 3, ... per session).
#[derive(Clone, Debug, PartialEq)]
pub struct UploadBatch {
    /// The site.
    pub site: String,
    /// The uploading robot.
    pub robot_id: String,
    /// The session (chosen by the robot).
    pub session_uuid: String,
    /// Sequence number within the session, from 1.
    pub seq: u64,
    /// The items, in the order LLO produced them.
    pub items: Vec<UploadItem>,
}

impl UploadBatch {
    /// Whether the batch carries its session's end.
    pub fn ends_session(&self) -> bool {
        self.items
            .iter()
            .any(|item| matches!(item, UploadItem::SessionEnd))
    }
}

impl From<&UploadItem> for pb::UploadItem {
    fn from(item: &UploadItem) -> Self {
        use pb::upload_item::Item;
        let item = match item {
            UploadItem::NodeAdded(node) => Item::NodeAdded(pb::NodeAdded {
                time_ns: node.time.0,
                local_pose: Some(pose_to_pb(&node.local_pose)),
                points_xy: points_to_pb(&node.points),
                insertion_submaps: node
                    .insertion_submaps
                    .iter()
                    .map(|(index, pose)| pb::SubmapInsertion {
                        index: *index,
                        local_pose: Some(pose_to_pb(pose)),
                    })
                    .collect(),
                recovered: node.recovered,
            }),
            UploadItem::SubmapFinished { index, grid } => {
                Item::SubmapFinished(pb::SubmapFinished {
                    index: *index,
                    grid: Some(grid_to_pb(grid)),
                })
            }
            UploadItem::SessionStartPrior {
                global_from_local,
                glm_on_robot,
                at_dock,
                fitted,
            } => Item::SessionStartPrior(pb::SessionStartPrior {
                global_from_local: Some(pose_to_pb(global_from_local)),
                glm_on_robot: *glm_on_robot,
                at_dock: *at_dock,
                fitted: fitted.map(fitted_nodes_to_pb),
            }),
            UploadItem::GlobalMatch {
                submap,
                submap_from_node,
                score,
            } => Item::GlobalMatch(pb::GlobalMatch {
                submap: Some((*submap).into()),
                submap_from_node: Some(pose_to_pb(submap_from_node)),
                score: *score,
            }),
            UploadItem::DockPlacementKept => Item::DockPlacementKept(pb::DockPlacementKept {}),
            UploadItem::SessionEnd => Item::SessionEnd(pb::SessionEnd {}),
        };
        Self { item: Some(item) }
    }
}

impl TryFrom<&pb::UploadItem> for UploadItem {
    type Error = ConversionError;

    fn try_from(item: &pb::UploadItem) -> Result<Self, ConversionError> {
        use pb::upload_item::Item;
        match &item.item {
            Some(Item::NodeAdded(node)) => {
                const M: &str = "NodeAdded";
                if node.insertion_submaps.is_empty() {
                    return Err(ConversionError::BadSize {
                        message: M,
                        field: "insertion_submaps",
                        expected: 1,
                        got: 0,
                    });
                }
                let insertion_submaps = node
                    .insertion_submaps
                    .iter()
                    .map(|s| {
                        Ok((
                            s.index,
                            pose_from_pb(s.local_pose.as_ref(), "SubmapInsertion", "local_pose")?,
                        ))
                    })
                    .collect::<Result<_, ConversionError>>()?;
                Ok(Self::NodeAdded(NodeAdded {
                    time: Timestamp(node.time_ns),
                    local_pose: pose_from_pb(node.local_pose.as_ref(), M, "local_pose")?,
                    points: points_from_pb(&node.points_xy, M, "points_xy")?,
                    insertion_submaps,
                    recovered: node.recovered,
                }))
            }
            Some(Item::SubmapFinished(submap)) => Ok(Self::SubmapFinished {
                index: submap.index,
                grid: grid_from_pb(submap.grid.as_ref().ok_or(ConversionError::MissingField {
                    message: "SubmapFinished",
                    field: "grid",
                })?)?,
            }),
            Some(Item::SessionStartPrior(prior)) => Ok(Self::SessionStartPrior {
                global_from_local: pose_from_pb(
                    prior.global_from_local.as_ref(),
                    "SessionStartPrior",
                    "global_from_local",
                )?,
                glm_on_robot: prior.glm_on_robot,
                at_dock: prior.at_dock,
                fitted: prior
                    .fitted
                    .map(|f| fitted_nodes_from_pb(f, "SessionStartPrior"))
                    .transpose()?,
            }),
            Some(Item::GlobalMatch(m)) => {
                const M: &str = "GlobalMatch";
                let submap = m.submap.ok_or(ConversionError::MissingField {
                    message: M,
                    field: "submap",
                })?;
                if !(m.score.is_finite() && (0.0..=1.0).contains(&m.score)) {
                    return Err(ConversionError::OutOfRange {
                        message: M,
                        field: "score",
                        value: m.score.into(),
                        expected: "in [0, 1]",
                    });
                }
                Ok(Self::GlobalMatch {
                    submap: submap.into(),
                    submap_from_node: pose_from_pb(
                        m.submap_from_node.as_ref(),
                        M,
                        "submap_from_node",
                    )?,
                    score: m.score,
                })
            }
            Some(Item::DockPlacementKept(_)) => Ok(Self::DockPlacementKept),
            Some(Item::SessionEnd(_)) => Ok(Self::SessionEnd),
            None => Err(ConversionError::MissingField {
                message: "UploadItem",
                field: "item",
            }),
        }
    }
}

impl From<&UploadBatch> for pb::UploadBatch {
    fn from(batch: &UploadBatch) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            site: batch.site.clone(),
            robot_id: batch.robot_id.clone(),
            session_uuid: batch.session_uuid.clone(),
            seq: batch.seq,
            items: batch.items.iter().map(pb::UploadItem::from).collect(),
        }
    }
}

fn non_empty(value: &str, field: &'static str) -> Result<String, ConversionError> {
    if value.is_empty() {
        Err(ConversionError::MissingField {
            message: "UploadBatch",
            field,
        })
    } else {
        Ok(value.to_owned())
    }
}

impl TryFrom<&pb::UploadBatch> for UploadBatch {
    type Error = ConversionError;

    /// Checks the version, the names, `seq ≥ 1`, at least one item, every item, that each
    /// `SubmapFinished` follows a `NodeAdded` (or another `SubmapFinished`) of the same batch, and that each
    /// `GlobalMatch` follows a `NodeAdded`, `SubmapFinished` or `GlobalMatch`.
    fn try_from(batch: &pb::UploadBatch) -> Result<Self, ConversionError> {
        const M: &str = "UploadBatch";
        check_format_version(M, batch.format_version)?;
        if batch.seq == 0 {
            return Err(ConversionError::OutOfRange {
                message: M,
                field: "seq",
                value: 0_u64.into(),
                expected: "at least 1 (sequence numbers start at 1)",
            });
        }
        if batch.items.is_empty() {
            return Err(ConversionError::BadSize {
                message: M,
                field: "items",
                expected: 1,
                got: 0,
            });
        }
        let items = batch
            .items
            .iter()
            .map(UploadItem::try_from)
            .collect::<Result<Vec<_>, _>>()?;
        for (i, item) in items.iter().enumerate() {
            let follows_node = i > 0
                && matches!(
                    items[i - 1],
                    UploadItem::NodeAdded(_) | UploadItem::SubmapFinished { .. }
                );
            if matches!(item, UploadItem::SubmapFinished { .. }) && !follows_node {
                return Err(ConversionError::Misplaced {
                    message: M,
                    field: "items",
                    index: i,
                    rule: "SubmapFinished must follow the NodeAdded that finished it",
                });
            }
            let follows_node_items = i > 0
                && matches!(
                    items[i - 1],
                    UploadItem::NodeAdded(_)
                        | UploadItem::SubmapFinished { .. }
                        | UploadItem::GlobalMatch { .. }
                );
            if matches!(item, UploadItem::GlobalMatch { .. }) && !follows_node_items {
                return Err(ConversionError::Misplaced {
                    message: M,
                    field: "items",
                    index: i,
                    rule: "GlobalMatch must follow the NodeAdded it matched",
                });
            }
        }
        Ok(Self {
            site: non_empty(&batch.site, "site")?,
            robot_id: non_empty(&batch.robot_id, "robot_id")?,
            session_uuid: non_empty(&batch.session_uuid, "session_uuid")?,
            seq: batch.seq,
            items,
        })
    }
}

/// `(first, last)` node indices as a [`pb::FittedNodes`].
pub(crate) fn fitted_nodes_to_pb((first, last): (u32, u32)) -> pb::FittedNodes {
    pb::FittedNodes { first, last }
}

/// A [`pb::FittedNodes`] as `(first, last)`; refused when `first` is past `last` (`message` names where
/// it was read).
pub(crate) fn fitted_nodes_from_pb(
    fitted: pb::FittedNodes,
    message: &'static str,
) -> Result<(u32, u32), ConversionError> {
    if fitted.first > fitted.last {
        return Err(ConversionError::OutOfRange {
            message,
            field: "fitted.first",
            value: crate::FieldValue::Unsigned(fitted.first.into()),
            expected: "at most fitted.last",
        });
    }
    Ok((fitted.first, fitted.last))
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;
    use mapping::grid::{CellIndex, MapLimits};
    use nalgebra::Vector2;

    use super::*;

    pub(crate) fn sample_batch() -> UploadBatch {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(1.0, 2.0), 8, 6));
        grid.set_probability(&CellIndex::new(3, 4), 0.75);
        UploadBatch {
            site: "store-7".into(),
            robot_id: "r1".into(),
            session_uuid: "c0ffee".into(),
            seq: 4,
            items: vec![
                UploadItem::SessionStartPrior {
                    global_from_local: rigid2(1.0, 2.0, 0.5),
                    glm_on_robot: true,
                    at_dock: true,
                    fitted: Some((0, 9)),
                },
                UploadItem::NodeAdded(NodeAdded {
                    time: Timestamp(42),
                    local_pose: rigid2(0.25, 0.5, 0.125),
                    points: vec![Point2::new(1.0, 2.0)],
                    insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0)), (1, rigid2(0.5, 0.0, 0.0))],
                    recovered: true,
                }),
                UploadItem::SubmapFinished { index: 0, grid },
                UploadItem::GlobalMatch {
                    submap: SubmapId {
                        trajectory: 3,
                        index: 9,
                    },
                    submap_from_node: rigid2(0.5, -0.25, 0.0625),
                    score: 0.75,
                },
                UploadItem::DockPlacementKept,
                UploadItem::SessionEnd,
            ],
        }
    }

    /// Poses go through (x, y, θ), so compare after one trip.
    fn normalized(batch: &UploadBatch) -> UploadBatch {
        UploadBatch::try_from(&pb::UploadBatch::from(batch)).unwrap()
    }

    #[test]
    fn batches_round_trip() {
        let batch = sample_batch();
        let once = normalized(&batch);
        assert_eq!(once.items.len(), 6);
        assert!(matches!(
            once.items[3],
            UploadItem::GlobalMatch { score: 0.75, .. }
        ));
        assert_eq!(normalized(&once), once);
        let UploadItem::SubmapFinished { grid, .. } = &once.items[2] else {
            panic!("item 2 is not a submap");
        };
        let UploadItem::SubmapFinished { grid: original, .. } = &batch.items[2] else {
            unreachable!();
        };
        assert_eq!(grid, original);
    }

    #[test]
    fn malformed_batches_are_refused() {
        let good = pb::UploadBatch::from(&sample_batch());
        let mut zero = good.clone();
        zero.seq = 0;
        assert!(UploadBatch::try_from(&zero).is_err());
        let mut empty = good.clone();
        empty.items.clear();
        assert!(UploadBatch::try_from(&empty).is_err());
        let mut no_site = good.clone();
        no_site.site.clear();
        assert_eq!(
            UploadBatch::try_from(&no_site).unwrap_err(),
            ConversionError::MissingField {
                message: "UploadBatch",
                field: "site"
            }
        );
        let mut orphan = good.clone();
        orphan.items.swap(1, 2);
        assert!(matches!(
            UploadBatch::try_from(&orphan),
            Err(ConversionError::Misplaced { field: "items", .. })
        ));
        // A match with no node before it, and a match scored outside [0, 1].
        let mut stray = good.clone();
        stray.items.swap(0, 3);
        assert!(matches!(
            UploadBatch::try_from(&stray),
            Err(ConversionError::Misplaced { field: "items", .. })
        ));
        let mut overscored = good.clone();
        if let Some(pb::upload_item::Item::GlobalMatch(m)) = &mut overscored.items[3].item {
            m.score = 1.5;
        }
        assert!(matches!(
            UploadBatch::try_from(&overscored),
            Err(ConversionError::OutOfRange { field: "score", .. })
        ));
        let mut nan = good.clone();
        if let Some(pb::upload_item::Item::NodeAdded(node)) = &mut nan.items[1].item {
            node.local_pose = Some(pb::Pose2 {
                x: f64::NAN,
                y: 0.0,
                theta: 0.0,
            });
        }
        assert!(matches!(
            UploadBatch::try_from(&nan),
            Err(ConversionError::NotFinite {
                message: "NodeAdded",
                field: "local_pose"
            })
        ));
        // A prior's fitted nodes must run forward.
        let mut reversed = good.clone();
        if let Some(pb::upload_item::Item::SessionStartPrior(prior)) = &mut reversed.items[0].item {
            prior.fitted = Some(pb::FittedNodes { first: 10, last: 9 });
        }
        assert!(matches!(
            UploadBatch::try_from(&reversed),
            Err(ConversionError::OutOfRange {
                message: "SessionStartPrior",
                field: "fitted.first",
                ..
            })
        ));
        let mut blank = good;
        blank.items[3].item = None;
        assert!(UploadBatch::try_from(&blank).is_err());
    }
}
