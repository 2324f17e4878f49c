//! Acting on a session start's decisions: the placement in the map, and what the session's
//! summary and record note of them.

use std::collections::BTreeMap;

use mapping::geometry::{Rigid2, Rigid2Ext as _};
use mapping::lifelong::{LifelongMap, RelocalizationOutcome, SessionStartEvent};
use mapping::pose_graph::NodeId;
use mapping::sensor::Timestamp;

use super::{DockCheckFigures, SearchFigures, SessionRecord, SessionSummary, SessionsError};

/// Acts on the session start's `decisions` for `session` (`first_search`: they come from its first
/// whole-map search): places it in the map on probation, commits or revokes its placement, and notes
/// what happened in its summary and record.
#[allow(clippy::too_many_arguments)]
pub(super) fn act_on_start(
    map: &mut LifelongMap,
    session: u32,
    first_search: bool,
    decisions: &[SessionStartEvent],
    node_times: &[Timestamp],
    node_local: &BTreeMap<NodeId, Rigid2>,
    mut summary: Option<&mut SessionSummary>,
    mut record: Option<&mut SessionRecord>,
    priors: &mut BTreeMap<u32, (Rigid2, Rigid2)>,
) -> Result<(), SessionsError> {
    let local = |node: usize| {
        node_local.get(&NodeId {
            trajectory: session,
            index: u32::try_from(node).ok()?,
        })
    };
    let mut from_dock = false;
    for decision in decisions {
        map.apply_start_decision(session, decision)?;
        if let Some(record) = record.as_deref_mut() {
            record
                .start
                .record(decision, node_times, &|node| local(node).copied());
        }
        match decision {
            SessionStartEvent::DockChecked {
                agreed,
                fit,
                weakest_z,
                ..
            } => {
                from_dock = *agreed;
                if let Some(summary) = summary.as_deref_mut() {
                    summary.dock_check = Some(DockCheckFigures {
                        agreed: *agreed,
                        fit: *fit,
                        weakest_z: *weakest_z,
                    });
                }
            }
            SessionStartEvent::Refused {
                node,
                outcome,
                weakest_z,
                fit,
                ..
            } => {
                if let Some(summary) = summary.as_deref_mut() {
                    summary.searches.push(SearchFigures {
                        node: *node,
                        outcome: match outcome {
                            RelocalizationOutcome::Ambiguous { .. } => "ambiguous",
                            RelocalizationOutcome::NotFound => "not_found",
                            RelocalizationOutcome::Found(_) => "revoked_again",
                        },
                        weakest_z: *weakest_z,
                        fit: *fit,
                        best_error_m: None,
                    });
                    // The first search's refusal, for the report.
                    if first_search {
                        match *outcome {
                            RelocalizationOutcome::Ambiguous {
                                score,
                                runner_up_score,
                                runner_up_from_best,
                            } => {
                                summary.relocalization_refused = Some("ambiguous".into());
                                summary.relocalization_ambiguity = Some([score, runner_up_score]);
                                summary.relocalization_runner_up_from_best =
                                    Some(runner_up_from_best);
                            }
                            RelocalizationOutcome::NotFound => {
                                summary.relocalization_refused = Some("not_found".into());
                            }
                            RelocalizationOutcome::Found(_) => {
                                summary.relocalization_refused = Some("revoked_before".into());
                            }
                        }
                    }
                }
            }
            SessionStartEvent::Placed(placement) => {
                if let Some(summary) = summary.as_deref_mut() {
                    summary.searches.push(SearchFigures {
                        node: placement.node,
                        outcome: "placed",
                        weakest_z: placement.weakest_z,
                        fit: placement.fit,
                        best_error_m: None,
                    });
                    if first_search {
                        summary.relocalized = true;
                    } else if from_dock {
                        summary.placed_at_time = node_times.get(placement.node).copied();
                    } else {
                        summary.placed_by_retry_at_node = Some(placement.node);
                        summary.placed_at_time = node_times.get(placement.node).copied();
                    }
                    summary.relocalization_score = placement.score;
                    if let Some(first_local) = local(0) {
                        let pose = placement.global_from_local * first_local;
                        priors.insert(session, (placement.global_from_local, *first_local));
                        summary.relocalized_first_pose = Some([
                            pose.translation.vector.x,
                            pose.translation.vector.y,
                            pose.theta(),
                        ]);
                    }
                }
            }
            SessionStartEvent::Committed { node, .. } => {
                if let Some(summary) = summary.as_deref_mut() {
                    summary.committed_at_node = Some(*node);
                }
            }
            SessionStartEvent::Revoked { reason, .. } => {
                priors.remove(&session);
                if let Some(summary) = summary.as_deref_mut() {
                    summary.revoked.push(reason.as_str().into());
                }
            }
            SessionStartEvent::GaveUp { .. } => {}
        }
    }
    Ok(())
}
