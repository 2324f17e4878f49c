//! What a session start decided, kept as the scores read it: every shell that runs a
//! [`SessionStart`](crate::lifelong::SessionStart) records its decisions here, in one way.

use super::Placement;
use crate::geometry::Rigid2;
use crate::lifelong::SessionStartEvent;
use crate::sensor::Timestamp;

/// The decisions of one session's start that [`score_session`](super::score_session) reads, recorded
/// as they come ([`Self::record`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StartRecord {
    /// Every placement the robot acted on, in order: each [`SessionStartEvent::Placed`] (tentative, on
    /// probation), decided at the node that placed it.
    pub placements: Vec<Placement>,
    /// The placement the session committed to ([`SessionStartEvent::Committed`]'s), decided at the node
    /// whose match committed it; `None` while it has not committed.
    pub committed: Option<Placement>,
    /// Per whole-map search, in order (a [`SessionStartEvent::Placed`] or
    /// [`SessionStartEvent::Refused`]): where its best candidate put the node it was made at (`None`
    /// without a candidate).
    pub search_bests: Vec<Option<Placement>>,
    /// Whether a placement was revoked.
    pub revoked: bool,
}

impl StartRecord {
    /// Records one decision, made when the session's latest node is the last of `node_times` (the scan
    /// time of each node, in node order); `local_pose(node)` is a node's `local_from_tracking`.
    pub fn record(
        &mut self,
        event: &SessionStartEvent,
        node_times: &[Timestamp],
        local_pose: &dyn Fn(usize) -> Option<Rigid2>,
    ) {
        let at = |global_from_local: &Rigid2, node: usize| {
            Some(Placement {
                decided_at: *node_times.last()?,
                time: *node_times.get(node)?,
                map_from_base: global_from_local * local_pose(node)?,
            })
        };
        match event {
            SessionStartEvent::Placed(placement) => {
                let placed = at(&placement.global_from_local, placement.node);
                self.placements.extend(placed);
                self.search_bests.push(placed);
            }
            SessionStartEvent::Refused { node, best, .. } => {
                self.search_bests
                    .push(best.and_then(|best| at(&best, *node)));
            }
            SessionStartEvent::Committed { placement, .. } => {
                self.committed = at(&placement.global_from_local, placement.node);
            }
            SessionStartEvent::Revoked { .. } => self.revoked = true,
            SessionStartEvent::DockChecked { .. } | SessionStartEvent::GaveUp { .. } => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;
    use crate::lifelong::{RelocalizationOutcome, RevokeReason, StartPlacement};

    fn t(seconds: f64) -> Timestamp {
        Timestamp::from_secs_f64(seconds)
    }

    fn placement(node: usize, x: f64) -> StartPlacement {
        StartPlacement {
            global_from_local: rigid2(x, 0.0, 0.0),
            node,
            fitted_from: None,
            score: None,
            weakest_z: None,
            fit: None,
        }
    }

    #[test]
    fn decisions_are_kept_as_the_scores_read_them() {
        let local = |node: usize| (node < 3).then(|| rigid2(node as f64, 0.0, 0.0));
        let mut record = StartRecord::default();
        record.record(
            &SessionStartEvent::Refused {
                node: 0,
                outcome: RelocalizationOutcome::NotFound,
                weakest_z: None,
                best: None,
                fit: None,
            },
            &[t(1.0)],
            &local,
        );
        let times = [t(1.0), t(2.0)];
        record.record(
            &SessionStartEvent::Placed(placement(1, 10.0)),
            &times,
            &local,
        );
        let times = [t(1.0), t(2.0), t(3.0)];
        record.record(
            &SessionStartEvent::Committed {
                placement: placement(1, 10.0),
                node: 2,
            },
            &times,
            &local,
        );
        let placed = Placement {
            decided_at: t(2.0),
            time: t(2.0),
            map_from_base: rigid2(11.0, 0.0, 0.0),
        };
        assert_eq!(record.placements, vec![placed]);
        assert_eq!(record.search_bests, vec![None, Some(placed)]);
        // Committed at the node whose match confirmed it; the placement's own node is the one placed.
        assert_eq!(
            record.committed,
            Some(Placement {
                decided_at: t(3.0),
                ..placed
            })
        );
        assert!(!record.revoked);
        record.record(
            &SessionStartEvent::Revoked {
                placement: placement(1, 10.0),
                reason: RevokeReason::Rival,
                node: 2,
            },
            &times,
            &local,
        );
        assert!(record.revoked);
    }
}
