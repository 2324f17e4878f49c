//! The site checkpoint record (`site_checkpoint.proto`): a site's whole map state at a log position,
//! encoded so that every number comes back with the same bits (see the `.proto` file for why poses and
//! information matrices are not encoded as elsewhere on the wire).
//!
//! Decoding reads every `format_version` from [`OLDEST_CHECKPOINT_FORMAT_VERSION`] to
//! [`CHECKPOINT_FORMAT_VERSION`] (an older one migrated as the constants' docs say) and refuses any
//! other with an error naming the version found ([`ConversionError::UnsupportedFormatVersion`]): the
//! caller stops, and never guesses at the layout. What decodes is checked field by field here and for
//! consistency by `LifelongMap::from_state`.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use mapping::geometry::Rigid2;
use mapping::global_slam::{
    Acceptance, BendGrowth, ClosureState, CorrectionProbation, FixedRatioSampler, GlobalSlamState,
    LoopClosure, NodeRecord, SearchJob, SearchWindow, SubmapBend, SubmapRecord,
};
use mapping::lifelong::{
    LifelongError, LifelongMap, LifelongMapState, LifelongOptions, SessionProgress,
};
use mapping::pose_graph::{Constraint, ConstraintId, NodeId, PoseGraph, SubmapId, VariableId};
use mapping::sensor::Timestamp;
use nalgebra::{Complex, Matrix3, Translation2, UnitComplex};

use crate::convert::constraint::{
    kind_from_pb, kind_to_pb, loss_from_pb, loss_to_pb, variable_in, variable_to_pb,
};
use crate::convert::{check_finite, points_from_pb, points_to_pb};
use crate::upload_batch::{fitted_nodes_from_pb, fitted_nodes_to_pb};
use crate::{ConversionError, ErrorSource, grid_from_pb, grid_to_pb, pb};

mod site_server_state;

pub use site_server_state::{
    PublishedSubmapState, RobotPrior, SessionStartCounts, SiteServerState, SiteSessionState,
};
use site_server_state::{site_from_pb, site_to_pb};

/// The `format_version` of the checkpoints this build writes, the newest it reads. Bump it with every
/// change of `site_checkpoint.proto` or of what the state means (a field of `GlobalSlamState` or
/// `LifelongMapState` added, removed or reinterpreted), and say here how the version before it is read.
///
/// Version 2: the server's part of the site ([`SiteServerState`], field 6) added and required.
/// Version 3: `GlobalSlamState.recovery_path` (the heading doubt of LLO recoveries) added. A version-2
/// checkpoint reads as version 3 with no recovery since any trajectory's last loop closure (the build
/// that wrote it kept none): the doubt starts at each trajectory's next recovery.
/// Version 4: `GlobalSlamState.placement_fits` (the nodes that fitted each search's placement) and
/// `SiteSessionState.prior_fitted` (those of a robot's prior) added. A version-2 or -3 checkpoint reads
/// with none (the build that wrote it kept none): its trajectories' nodes are treated as those of a
/// placement given without a search.
pub const CHECKPOINT_FORMAT_VERSION: u32 = 4;

/// The oldest `format_version` this build reads. A server upgraded across a format change must restore
/// the sites it holds, whose log before their checkpoint compaction deleted: raise it only with a
/// migration that reads the versions it leaves behind. Version 1 (no server part) is refused.
pub const OLDEST_CHECKPOINT_FORMAT_VERSION: u32 = 2;

/// Refuses a checkpoint `format_version` this build does not read, naming it and the versions it reads.
pub fn check_checkpoint_format_version(got: u32) -> Result<(), ConversionError> {
    if (OLDEST_CHECKPOINT_FORMAT_VERSION..=CHECKPOINT_FORMAT_VERSION).contains(&got) {
        Ok(())
    } else {
        Err(ConversionError::UnsupportedFormatVersion {
            message: "SiteCheckpoint",
            got,
            oldest: OLDEST_CHECKPOINT_FORMAT_VERSION,
            newest: CHECKPOINT_FORMAT_VERSION,
        })
    }
}

/// A site's map state and the log position it covers.
#[derive(Clone, Debug, PartialEq)]
pub struct SiteCheckpoint {
    /// The last site log index whose entry the state includes: replay resumes after it.
    pub log_index: u64,
    /// The site map version after that entry.
    pub map_version: u64,
    /// The lifelong map's state.
    pub map: LifelongMapState,
    /// [`options_fingerprint`] of the options the map ran with.
    pub options_fingerprint: u32,
    /// The server's part of the site (sessions, versions, counters).
    pub site: SiteServerState,
}

/// A fingerprint of `options` (CRC-32 of their `Debug` form: every field, names and values, in order),
/// kept with a checkpoint to tell whether it is restored under the options it ran with. Any change of
/// the options or of their struct changes it.
pub fn options_fingerprint(options: &LifelongOptions) -> u32 {
    crc32fast::hash(format!("{options:?}").as_bytes())
}

impl SiteCheckpoint {
    /// The checkpoint of `map` after the site log entry `log_index`, at map version `map_version`, with
    /// an empty server part (the server sets [`Self::site`]).
    pub fn of(map: &LifelongMap, log_index: u64, map_version: u64) -> Self {
        Self {
            log_index,
            map_version,
            map: map.to_state(),
            options_fingerprint: options_fingerprint(map.options()),
            site: SiteServerState::default(),
        }
    }

    /// The map this checkpoint holds, under `options`: those the site is configured with now. They need
    /// not be the ones it ran with (a newer build adds an option, an operator retunes one): the state is
    /// kept as it stands and the options govern what comes after it, as they would have had they been
    /// changed while the site ran ([`Self::written_under_other_options`] tells the caller to say so).
    /// Refused only if the options are invalid or the state contradicts itself.
    pub fn restore(self, options: LifelongOptions) -> Result<LifelongMap, LifelongError> {
        LifelongMap::from_state(options, self.map)
    }

    /// Whether the checkpoint was written under other options than `options` (by fingerprint).
    pub fn written_under_other_options(&self, options: &LifelongOptions) -> bool {
        options_fingerprint(options) != self.options_fingerprint
    }
}

impl From<&SiteCheckpoint> for pb::SiteCheckpoint {
    fn from(c: &SiteCheckpoint) -> Self {
        Self {
            format_version: CHECKPOINT_FORMAT_VERSION,
            log_index: c.log_index,
            map_version: c.map_version,
            map: Some(map_to_pb(&c.map)),
            options_fingerprint: c.options_fingerprint,
            site: Some(site_to_pb(&c.site)),
        }
    }
}

impl TryFrom<&pb::SiteCheckpoint> for SiteCheckpoint {
    type Error = ConversionError;

    /// Checks the format version first (nothing else is read from a checkpoint of a version this build
    /// does not read), then every field. Versions 2 and 3 need no conversion: the fields versions 3 and 4
    /// added (`GlobalSlamState.recovery_path`, `GlobalSlamState.placement_fits`,
    /// `SiteSessionState.prior_fitted`) decode empty from them.
    fn try_from(c: &pb::SiteCheckpoint) -> Result<Self, ConversionError> {
        const M: &str = "SiteCheckpoint";
        check_checkpoint_format_version(c.format_version)?;
        Ok(Self {
            log_index: c.log_index,
            map_version: c.map_version,
            map: map_from_pb(required(c.map.as_ref(), M, "map")?)?,
            options_fingerprint: c.options_fingerprint,
            site: site_from_pb(required(c.site.as_ref(), M, "site")?)?,
        })
    }
}

fn required<'a, T>(
    value: Option<&'a T>,
    message: &'static str,
    field: &'static str,
) -> Result<&'a T, ConversionError> {
    value.ok_or(ConversionError::MissingField { message, field })
}

fn to_usize(
    value: u64,
    message: &'static str,
    field: &'static str,
) -> Result<usize, ConversionError> {
    usize::try_from(value).map_err(|_| ConversionError::OutOfRange {
        message,
        field,
        value: value.into(),
        expected: "a count this machine's usize holds",
    })
}

fn node_in(
    id: Option<&pb::NodeId>,
    message: &'static str,
    field: &'static str,
) -> Result<NodeId, ConversionError> {
    required(id, message, field).map(|id| (*id).into())
}

fn submap_in(
    id: Option<&pb::SubmapId>,
    message: &'static str,
    field: &'static str,
) -> Result<SubmapId, ConversionError> {
    required(id, message, field).map(|id| (*id).into())
}

/// `pose` exactly as stored: translation and the rotation's unit complex number (see `ExactPose2`).
pub fn pose_to_exact(pose: &Rigid2) -> pb::ExactPose2 {
    pb::ExactPose2 {
        x: Some(pose.translation.vector.x),
        y: Some(pose.translation.vector.y),
        cos: Some(pose.rotation.re),
        sin: Some(pose.rotation.im),
    }
}

/// A pose from its exact form: finite numbers, and a rotation of unit norm (to 1e-6; kept as stored).
/// `message` and `field` name it in the error.
///
/// # Errors
/// [`ConversionError`] for a missing pose or component, a number that is not finite, or a rotation
/// that is not of unit norm.
pub fn pose_from_exact(
    pose: Option<&pb::ExactPose2>,
    message: &'static str,
    field: &'static str,
) -> Result<Rigid2, ConversionError> {
    let p = required(pose, message, field)?;
    let [Some(x), Some(y), Some(cos), Some(sin)] = [p.x, p.y, p.cos, p.sin] else {
        return Err(ConversionError::MissingField { message, field });
    };
    for v in [x, y, cos, sin] {
        check_finite(v, message, field)?;
    }
    let norm = cos.hypot(sin);
    if (norm - 1.0).abs() > 1e-6 {
        return Err(ConversionError::OutOfRange {
            message,
            field,
            value: norm.into(),
            expected: "a rotation (cos, sin) of norm 1 (to 1e-6)",
        });
    }
    Ok(Rigid2::from_parts(
        Translation2::new(x, y),
        UnitComplex::new_unchecked(Complex::new(cos, sin)),
    ))
}

fn matrix_to_pb(m: &Matrix3<f64>) -> Vec<f64> {
    (0..3)
        .flat_map(|r| (0..3).map(move |c| m[(r, c)]))
        .collect()
}

fn matrix_from_pb(
    values: &[f64],
    message: &'static str,
    field: &'static str,
) -> Result<Matrix3<f64>, ConversionError> {
    if values.len() != 9 {
        return Err(ConversionError::BadSize {
            message,
            field,
            expected: 9,
            got: values.len(),
        });
    }
    for v in values {
        check_finite(*v, message, field)?;
    }
    Ok(Matrix3::from_row_slice(values))
}

fn constraint_to_pb(c: &Constraint) -> pb::ExactConstraint {
    let (loss, loss_scale) = loss_to_pb(c.loss);
    pb::ExactConstraint {
        kind: kind_to_pb(c.kind).into(),
        from: Some(variable_to_pb(c.from)),
        to: Some(variable_to_pb(c.to)),
        from_from_to: Some(pose_to_exact(&c.from_from_to)),
        information: matrix_to_pb(&c.information),
        loss: loss.into(),
        loss_scale,
    }
}

fn constraint_from_pb(c: &pb::ExactConstraint) -> Result<Constraint, ConversionError> {
    const M: &str = "ExactConstraint";
    Ok(Constraint {
        kind: kind_from_pb(c.kind, M)?,
        from: variable_in(c.from.as_ref(), M, "from")?,
        to: variable_in(c.to.as_ref(), M, "to")?,
        from_from_to: pose_from_exact(c.from_from_to.as_ref(), M, "from_from_to")?,
        information: matrix_from_pb(&c.information, M, "information")?,
        loss: loss_from_pb(c.loss, c.loss_scale, M)?,
    })
}

fn closure_to_pb(c: &LoopClosure) -> pb::LoopClosureState {
    pb::LoopClosureState {
        submap: Some(c.submap.into()),
        node: Some(c.node.into()),
        submap_from_node: Some(pose_to_exact(&c.submap_from_node)),
        score: c.score,
        runner_up_score: c.runner_up_score,
        information: c.information.as_ref().map(matrix_to_pb).unwrap_or_default(),
    }
}

fn closure_from_pb(c: Option<&pb::LoopClosureState>) -> Result<LoopClosure, ConversionError> {
    const M: &str = "LoopClosureState";
    let c = required(c, M, "closure")?;
    Ok(LoopClosure {
        submap: submap_in(c.submap.as_ref(), M, "submap")?,
        node: node_in(c.node.as_ref(), M, "node")?,
        submap_from_node: pose_from_exact(c.submap_from_node.as_ref(), M, "submap_from_node")?,
        score: c.score,
        runner_up_score: c.runner_up_score,
        information: if c.information.is_empty() {
            None
        } else {
            Some(matrix_from_pb(&c.information, M, "information")?)
        },
    })
}

fn acceptance_to_pb(a: &Acceptance) -> pb::AcceptanceState {
    pb::AcceptanceState {
        innovation_translation_m: a.innovation_translation_m,
        innovation_rotation_rad: a.innovation_rotation_rad,
        confirmed_by_agreement: a.confirmed_by_agreement,
    }
}

fn acceptance_from_pb(a: Option<&pb::AcceptanceState>) -> Result<Acceptance, ConversionError> {
    let a = required(a, "AcceptanceState", "acceptance")?;
    Ok(Acceptance {
        innovation_translation_m: a.innovation_translation_m,
        innovation_rotation_rad: a.innovation_rotation_rad,
        confirmed_by_agreement: a.confirmed_by_agreement,
    })
}

fn pending_to_pb(pending: &[(LoopClosure, Acceptance)]) -> Vec<pb::PendingClosure> {
    pending
        .iter()
        .map(|(c, a)| pb::PendingClosure {
            closure: Some(closure_to_pb(c)),
            acceptance: Some(acceptance_to_pb(a)),
        })
        .collect()
}

fn pending_from_pb(
    pending: &[pb::PendingClosure],
) -> Result<Vec<(LoopClosure, Acceptance)>, ConversionError> {
    pending
        .iter()
        .map(|p| {
            Ok((
                closure_from_pb(p.closure.as_ref())?,
                acceptance_from_pb(p.acceptance.as_ref())?,
            ))
        })
        .collect()
}

fn graph_to_pb(graph: &PoseGraph) -> pb::PoseGraphState {
    pb::PoseGraphState {
        variables: graph
            .variables()
            .map(|(id, pose, fixed)| pb::GraphVariable {
                id: Some(variable_to_pb(id)),
                pose: Some(pose_to_exact(&pose)),
                fixed,
            })
            .collect(),
        constraints: graph
            .constraints()
            .map(|(id, c)| pb::GraphConstraint {
                id: id.0,
                constraint: Some(constraint_to_pb(c)),
            })
            .collect(),
        next_constraint: graph.next_constraint_id().0,
    }
}

fn graph_from_pb(graph: Option<&pb::PoseGraphState>) -> Result<PoseGraph, ConversionError> {
    const M: &str = "PoseGraphState";
    let graph = required(graph, M, "graph")?;
    let variables = graph
        .variables
        .iter()
        .map(|v| {
            Ok((
                variable_in(v.id.as_ref(), "GraphVariable", "id")?,
                pose_from_exact(v.pose.as_ref(), "GraphVariable", "pose")?,
                v.fixed,
            ))
        })
        .collect::<Result<Vec<_>, ConversionError>>()?;
    let constraints = graph
        .constraints
        .iter()
        .map(|c| {
            let constraint = required(c.constraint.as_ref(), "GraphConstraint", "constraint")?;
            Ok((ConstraintId(c.id), constraint_from_pb(constraint)?))
        })
        .collect::<Result<Vec<_>, ConversionError>>()?;
    PoseGraph::from_parts(variables, constraints, ConstraintId(graph.next_constraint)).map_err(
        |e| ConversionError::Invalid {
            message: M,
            field: "graph",
            source: ErrorSource::new(e),
        },
    )
}

fn global_to_pb(g: &GlobalSlamState) -> pb::GlobalSlamState {
    pb::GlobalSlamState {
        graph: Some(graph_to_pb(&g.graph)),
        nodes: g
            .nodes
            .iter()
            .map(|(id, r)| pb::NodeRecordState {
                id: Some((*id).into()),
                time_ns: r.time.0,
                local_pose: Some(pose_to_exact(&r.local_pose)),
                points: points_to_pb(&r.points),
                submaps: r.submaps.iter().map(|s| (*s).into()).collect(),
                path_m: r.path_m,
            })
            .collect(),
        submaps: g
            .submaps
            .iter()
            .map(|(id, r)| pb::SubmapRecordState {
                id: Some((*id).into()),
                local_pose: Some(pose_to_exact(&r.local_pose)),
                grid: r.grid.as_deref().map(grid_to_pb),
                nodes: r.nodes.iter().map(|n| (*n).into()).collect(),
            })
            .collect(),
        samplers: g
            .samplers
            .iter()
            .map(|(id, s)| {
                let (pulses, samples) = s.counts();
                pb::SamplerState {
                    submap: Some((*id).into()),
                    ratio: s.ratio(),
                    pulses,
                    samples,
                }
            })
            .collect(),
        global_from_local: g
            .global_from_local
            .iter()
            .map(|(t, pose)| pb::TrajectoryPose {
                trajectory: *t,
                pose: Some(pose_to_exact(pose)),
            })
            .collect(),
        last_node: g
            .last_node
            .iter()
            .map(|(t, node)| pb::TrajectoryNode {
                trajectory: *t,
                node: Some((*node).into()),
            })
            .collect(),
        pending_jobs: g
            .pending_jobs
            .iter()
            .map(|j| pb::SearchJobState {
                submap: Some(j.submap.into()),
                node: Some(j.node.into()),
                submap_from_node_estimate: j.submap_from_node_estimate.as_ref().map(pose_to_exact),
                window: j.window.map(|w| pb::SearchWindowState {
                    linear_m: w.linear_m,
                    angular_rad: w.angular_rad,
                }),
            })
            .collect(),
        nodes_since_optimization: g.nodes_since_optimization as u64,
        accepted_loop_closures: g
            .accepted_loop_closures
            .iter()
            .zip(&g.acceptances)
            .zip(&g.closure_states)
            .map(|((c, a), state)| pb::AcceptedClosure {
                closure: Some(closure_to_pb(c)),
                acceptance: Some(acceptance_to_pb(a)),
                state: Some(match state {
                    ClosureState::InGraph(id) => pb::accepted_closure::State::InGraph(id.0),
                    ClosureState::Retracted(c) => {
                        pb::accepted_closure::State::Retracted(constraint_to_pb(c))
                    }
                    ClosureState::Gone => pb::accepted_closure::State::Gone(true),
                }),
            })
            .collect(),
        loop_closures_accepted: g.loop_closures_accepted as u64,
        searches_queued: g.searches_queued as u64,
        unanchored: g.unanchored.iter().copied().collect(),
        matched_elsewhere: g.matched_elsewhere.iter().copied().collect(),
        last_loop_path: trajectory_paths_to_pb(&g.last_loop_path),
        recovery_path: trajectory_paths_to_pb(&g.recovery_path),
        placement_fits: g
            .placement_fits
            .iter()
            .map(|(&trajectory, &nodes)| pb::PlacementFit {
                trajectory,
                nodes: Some(fitted_nodes_to_pb(nodes)),
            })
            .collect(),
        closures_beyond_drift: g.closures_beyond_drift as u64,
        pending_beyond_drift: pending_to_pb(&g.pending_beyond_drift),
        closures_outvoted: g.closures_outvoted as u64,
        pending_unconfirmed: pending_to_pb(&g.pending_unconfirmed),
        settled: g.settled.iter().copied().collect(),
        new_constraints_from: g.new_constraints_from.0,
        changed: g.changed.iter().map(|v| variable_to_pb(*v)).collect(),
        correction_probations: g
            .correction_probations
            .iter()
            .map(probation_to_pb)
            .collect(),
        submap_bends: g.submap_bends.iter().map(bend_to_pb).collect(),
    }
}

fn closure_refs_to_pb(closures: &[(NodeId, SubmapId)]) -> Vec<pb::ClosureRef> {
    closures
        .iter()
        .map(|(node, submap)| pb::ClosureRef {
            node: Some((*node).into()),
            submap: Some((*submap).into()),
        })
        .collect()
}

fn closure_refs_from_pb(
    closures: &[pb::ClosureRef],
) -> Result<Vec<(NodeId, SubmapId)>, ConversionError> {
    closures
        .iter()
        .map(|c| {
            Ok((
                node_in(c.node.as_ref(), "ClosureRef", "node")?,
                submap_in(c.submap.as_ref(), "ClosureRef", "submap")?,
            ))
        })
        .collect()
}

fn bend_to_pb(b: &SubmapBend) -> pb::SubmapBendState {
    pb::SubmapBendState {
        closures: closure_refs_to_pb(&b.closures),
        submaps: b.submaps.iter().map(|s| (*s).into()).collect(),
        growth_translation_per_m: b.growth.translation_per_m,
        growth_rotation_per_m: b.growth.rotation_per_m,
    }
}

fn bend_from_pb(b: &pb::SubmapBendState) -> Result<SubmapBend, ConversionError> {
    Ok(SubmapBend {
        closures: closure_refs_from_pb(&b.closures)?,
        submaps: b
            .submaps
            .iter()
            .map(|s| submap_in(Some(s), "SubmapBendState", "submaps"))
            .collect::<Result<Vec<_>, ConversionError>>()?,
        growth: BendGrowth {
            translation_per_m: b.growth_translation_per_m,
            rotation_per_m: b.growth_rotation_per_m,
        },
    })
}

fn probation_to_pb(p: &CorrectionProbation) -> pb::CorrectionProbationState {
    pb::CorrectionProbationState {
        closures: closure_refs_to_pb(&p.closures),
        newest: Some(closure_to_pb(&p.newest)),
        after_node: p.after_node,
        old_submaps_to: p.old_submaps_to,
        agreeing: p.agreeing.iter().map(|n| (*n).into()).collect(),
        disagreeing: p.disagreeing.iter().map(|n| (*n).into()).collect(),
        nodes_judging: p.nodes_judging as u64,
        kept: p.kept,
    }
}

fn probation_from_pb(
    p: &pb::CorrectionProbationState,
) -> Result<CorrectionProbation, ConversionError> {
    const M: &str = "CorrectionProbationState";
    let nodes = |ids: &[pb::NodeId], field| {
        ids.iter()
            .map(|id| node_in(Some(id), M, field))
            .collect::<Result<BTreeSet<NodeId>, ConversionError>>()
    };
    Ok(CorrectionProbation {
        closures: closure_refs_from_pb(&p.closures)?,
        newest: closure_from_pb(p.newest.as_ref())?,
        after_node: p.after_node,
        old_submaps_to: p.old_submaps_to,
        agreeing: nodes(&p.agreeing, "agreeing")?,
        disagreeing: nodes(&p.disagreeing, "disagreeing")?,
        nodes_judging: to_usize(p.nodes_judging, M, "nodes_judging")?,
        kept: p.kept,
    })
}

fn global_from_pb(g: Option<&pb::GlobalSlamState>) -> Result<GlobalSlamState, ConversionError> {
    const M: &str = "GlobalSlamState";
    let g = required(g, "LifelongMapState", "global")?;
    let nodes = g
        .nodes
        .iter()
        .map(|r| {
            const N: &str = "NodeRecordState";
            Ok((
                node_in(r.id.as_ref(), N, "id")?,
                NodeRecord {
                    time: Timestamp(r.time_ns),
                    local_pose: pose_from_exact(r.local_pose.as_ref(), N, "local_pose")?,
                    points: Arc::new(points_from_pb(&r.points, N, "points")?),
                    submaps: r.submaps.iter().map(|s| (*s).into()).collect(),
                    path_m: check_finite(r.path_m, N, "path_m")?,
                },
            ))
        })
        .collect::<Result<BTreeMap<_, _>, ConversionError>>()?;
    let submaps = g
        .submaps
        .iter()
        .map(|r| {
            const S: &str = "SubmapRecordState";
            Ok((
                submap_in(r.id.as_ref(), S, "id")?,
                SubmapRecord {
                    local_pose: pose_from_exact(r.local_pose.as_ref(), S, "local_pose")?,
                    grid: r.grid.as_ref().map(grid_from_pb).transpose()?.map(Arc::new),
                    nodes: r.nodes.iter().map(|n| (*n).into()).collect(),
                },
            ))
        })
        .collect::<Result<BTreeMap<_, _>, ConversionError>>()?;
    let samplers = g
        .samplers
        .iter()
        .map(|s| {
            Ok((
                submap_in(s.submap.as_ref(), "SamplerState", "submap")?,
                FixedRatioSampler::from_counts(s.ratio, s.pulses, s.samples),
            ))
        })
        .collect::<Result<BTreeMap<_, _>, ConversionError>>()?;
    let global_from_local = g
        .global_from_local
        .iter()
        .map(|t| {
            Ok((
                t.trajectory,
                pose_from_exact(t.pose.as_ref(), "TrajectoryPose", "pose")?,
            ))
        })
        .collect::<Result<BTreeMap<_, _>, ConversionError>>()?;
    let last_node = g
        .last_node
        .iter()
        .map(|t| {
            Ok((
                t.trajectory,
                node_in(t.node.as_ref(), "TrajectoryNode", "node")?,
            ))
        })
        .collect::<Result<BTreeMap<_, _>, ConversionError>>()?;
    let pending_jobs = g
        .pending_jobs
        .iter()
        .map(|j| {
            const J: &str = "SearchJobState";
            let node = node_in(j.node.as_ref(), J, "node")?;
            Ok(SearchJob {
                submap: submap_in(j.submap.as_ref(), J, "submap")?,
                node,
                // The node's own points: `GlobalSlam::from_state` shares them again.
                points: nodes
                    .get(&node)
                    .map(|r| Arc::clone(&r.points))
                    .unwrap_or_default(),
                submap_from_node_estimate: j
                    .submap_from_node_estimate
                    .as_ref()
                    .map(|p| pose_from_exact(Some(p), J, "submap_from_node_estimate"))
                    .transpose()?,
                window: j.window.map(|w| SearchWindow {
                    linear_m: w.linear_m,
                    angular_rad: w.angular_rad,
                }),
            })
        })
        .collect::<Result<Vec<_>, ConversionError>>()?;
    let mut accepted_loop_closures = Vec::with_capacity(g.accepted_loop_closures.len());
    let mut acceptances = Vec::with_capacity(g.accepted_loop_closures.len());
    let mut closure_states = Vec::with_capacity(g.accepted_loop_closures.len());
    for a in &g.accepted_loop_closures {
        accepted_loop_closures.push(closure_from_pb(a.closure.as_ref())?);
        acceptances.push(acceptance_from_pb(a.acceptance.as_ref())?);
        closure_states.push(match &a.state {
            Some(pb::accepted_closure::State::InGraph(id)) => {
                ClosureState::InGraph(ConstraintId(*id))
            }
            Some(pb::accepted_closure::State::Retracted(c)) => {
                ClosureState::Retracted(constraint_from_pb(c)?)
            }
            Some(pb::accepted_closure::State::Gone(_)) => ClosureState::Gone,
            None => {
                return Err(ConversionError::MissingField {
                    message: "AcceptedClosure",
                    field: "state",
                });
            }
        });
    }
    let last_loop_path = trajectory_paths_from_pb(&g.last_loop_path)?;
    let recovery_path = trajectory_paths_from_pb(&g.recovery_path)?;
    let placement_fits = g
        .placement_fits
        .iter()
        .map(|f| {
            let nodes = f.nodes.ok_or(ConversionError::MissingField {
                message: "PlacementFit",
                field: "nodes",
            })?;
            Ok((f.trajectory, fitted_nodes_from_pb(nodes, "PlacementFit")?))
        })
        .collect::<Result<BTreeMap<u32, (u32, u32)>, ConversionError>>()?;
    Ok(GlobalSlamState {
        graph: graph_from_pb(g.graph.as_ref())?,
        nodes,
        submaps,
        samplers,
        global_from_local,
        last_node,
        pending_jobs,
        nodes_since_optimization: to_usize(
            g.nodes_since_optimization,
            M,
            "nodes_since_optimization",
        )?,
        accepted_loop_closures,
        loop_closures_accepted: to_usize(g.loop_closures_accepted, M, "loop_closures_accepted")?,
        acceptances,
        closure_states,
        searches_queued: to_usize(g.searches_queued, M, "searches_queued")?,
        unanchored: g.unanchored.iter().copied().collect(),
        matched_elsewhere: g.matched_elsewhere.iter().copied().collect(),
        last_loop_path,
        recovery_path,
        placement_fits,
        closures_beyond_drift: to_usize(g.closures_beyond_drift, M, "closures_beyond_drift")?,
        pending_beyond_drift: pending_from_pb(&g.pending_beyond_drift)?,
        closures_outvoted: to_usize(g.closures_outvoted, M, "closures_outvoted")?,
        pending_unconfirmed: pending_from_pb(&g.pending_unconfirmed)?,
        settled: g.settled.iter().copied().collect(),
        new_constraints_from: ConstraintId(g.new_constraints_from),
        changed: g
            .changed
            .iter()
            .map(|v| variable_in(Some(v), M, "changed"))
            .collect::<Result<BTreeSet<VariableId>, ConversionError>>()?,
        correction_probations: g
            .correction_probations
            .iter()
            .map(probation_from_pb)
            .collect::<Result<Vec<_>, ConversionError>>()?,
        submap_bends: g
            .submap_bends
            .iter()
            .map(bend_from_pb)
            .collect::<Result<Vec<_>, ConversionError>>()?,
    })
}

fn map_to_pb(m: &LifelongMapState) -> pb::LifelongMapState {
    pb::LifelongMapState {
        global: Some(global_to_pb(&m.global)),
        sessions: m
            .sessions
            .iter()
            .map(|(id, s)| pb::SessionProgress {
                session: *id,
                order: s.order as u64,
                finished: s.finished,
            })
            .collect(),
        base: m.base,
        probation: m.probation.iter().copied().collect(),
        trimmed_total: m.trimmed_total as u64,
        dropped_total: m.dropped_total as u64,
        sparsifications_since_optimization: m.sparsifications_since_optimization as u64,
    }
}

fn map_from_pb(m: &pb::LifelongMapState) -> Result<LifelongMapState, ConversionError> {
    const M: &str = "LifelongMapState";
    Ok(LifelongMapState {
        global: global_from_pb(m.global.as_ref())?,
        sessions: m
            .sessions
            .iter()
            .map(|s| {
                Ok((
                    s.session,
                    SessionProgress {
                        order: to_usize(s.order, "SessionProgress", "order")?,
                        finished: s.finished,
                    },
                ))
            })
            .collect::<Result<BTreeMap<_, _>, ConversionError>>()?,
        base: m.base,
        probation: m.probation.iter().copied().collect(),
        trimmed_total: to_usize(m.trimmed_total, M, "trimmed_total")?,
        dropped_total: to_usize(m.dropped_total, M, "dropped_total")?,
        sparsifications_since_optimization: to_usize(
            m.sparsifications_since_optimization,
            M,
            "sparsifications_since_optimization",
        )?,
    })
}

#[cfg(test)]
mod tests;

fn trajectory_paths_to_pb(paths: &BTreeMap<u32, f64>) -> Vec<pb::TrajectoryPath> {
    paths
        .iter()
        .map(|(t, path_m)| pb::TrajectoryPath {
            trajectory: *t,
            path_m: *path_m,
        })
        .collect()
}

fn trajectory_paths_from_pb(
    paths: &[pb::TrajectoryPath],
) -> Result<BTreeMap<u32, f64>, ConversionError> {
    paths
        .iter()
        .map(|t| {
            Ok((
                t.trajectory,
                check_finite(t.path_m, "TrajectoryPath", "path_m")?,
            ))
        })
        .collect()
}
