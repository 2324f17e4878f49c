//! Each GLM match judged against a reference trajectory, by the rule that decided it and where it ended:
//! how every acceptance rule does as the test it is (what it let in that was wrong, what it held back that
//! was right), on any run that has a reference — the truth, or the final trajectory of the same
//! recording's clean run for a perturbed one.
//!
//! A match says where its node lies in its submap. It is judged in the frame of the submap's node nearest
//! that place (its *anchor*), which LLO's drift inside the submap does not reach: right when the match puts
//! the node within [`MATCH_TOLERANCE`] of where the reference puts it relative to the anchor.

use std::collections::{BTreeMap, HashMap};

use serde::Serialize;

use super::PoseTolerance;
use super::relations_metric::pose_at_scan;
use crate::geometry::Rigid2;
use crate::global_slam::{GlobalSlam, MatchDecided, MatchDecision};
use crate::pose_graph::{NodeId, SubmapId};
use crate::sensor::Timestamp;

/// A match is right when it places its node within 0.5 m and 3° of the reference, relative to its anchor.
pub const MATCH_TOLERANCE: PoseTolerance = PoseTolerance {
    translation_m: 0.5,
    rotation_deg: 3.0,
};

/// Where a match ended, at the time of judging.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MatchFate {
    /// A constraint of the graph.
    InGraph,
    /// Added, then retracted (the optimized graph refused it, or a correction's probation did).
    Retracted,
    /// Never added: outvoted, or held and never confirmed.
    NeverUsed,
}

impl MatchFate {
    /// Every fate, in the order reports list them.
    pub const ALL: [Self; 3] = [Self::InGraph, Self::Retracted, Self::NeverUsed];

    /// The fate's name in reports and CSV files.
    pub fn name(self) -> &'static str {
        match self {
            Self::InGraph => "in_graph",
            Self::Retracted => "retracted",
            Self::NeverUsed => "never_used",
        }
    }
}

/// One match, where it ended, and how it compares with the reference.
#[derive(Clone, Debug, PartialEq)]
pub struct JudgedMatch {
    /// The match and the rule that decided it.
    pub decided: MatchDecided,
    /// Where it ended.
    pub fate: MatchFate,
    /// When its node's scan was taken.
    pub node_time: Timestamp,
    /// When the scan of its anchor (the submap's node nearest the match) was taken.
    pub anchor_time: Timestamp,
    /// The node's pose in the anchor's frame, as the match says.
    pub anchor_from_node: Rigid2,
    /// Translation (m) and rotation (degrees) of the match against the reference; `None` where the
    /// reference has no pose at one of the two scans (or no reference was given).
    pub error: Option<(f64, f64)>,
}

impl JudgedMatch {
    /// Whether the reference says the match is right (`None`: not judged).
    pub fn right(&self) -> Option<bool> {
        self.error.map(|(m, deg)| MATCH_TOLERANCE.accepts(m, deg))
    }
}

/// Matches of one decision and fate: how many, and how many the reference calls right and wrong.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct MatchCounts {
    /// Matches.
    pub matches: usize,
    /// Judged right.
    pub right: usize,
    /// Judged wrong.
    pub wrong: usize,
}

/// Judges each decided match of `global`'s run against `reference` (poses at the scans' stamps, as a
/// TUM trajectory holds them; `None`: where they ended only). Matches whose node or submap the map no
/// longer has are left out.
pub fn judge_matches(
    global: &GlobalSlam,
    decided: &[MatchDecided],
    reference: Option<&[(Timestamp, Rigid2)]>,
) -> Vec<JudgedMatch> {
    let mut fates: HashMap<(NodeId, SubmapId), MatchFate> = HashMap::new();
    for check in global.loop_closure_checks() {
        let fate = if check.retracted {
            MatchFate::Retracted
        } else {
            MatchFate::InGraph
        };
        fates.insert((check.closure.node, check.closure.submap), fate);
    }
    decided
        .iter()
        .filter_map(|d| {
            let node = global.nodes().get(&d.closure.node)?;
            let submap = global.submaps().get(&d.closure.submap)?;
            let place = d.closure.submap_from_node.translation.vector;
            let (anchor, submap_from_anchor) = submap
                .nodes
                .iter()
                .filter_map(|id| global.nodes().get(id))
                .map(|a| (a, submap.local_pose.inverse() * a.local_pose))
                .min_by(|(_, x), (_, y)| {
                    let dx = (x.translation.vector - place).norm();
                    let dy = (y.translation.vector - place).norm();
                    dx.total_cmp(&dy)
                })?;
            let anchor_from_node = submap_from_anchor.inverse() * d.closure.submap_from_node;
            let error = reference.and_then(|poses| {
                let truth =
                    pose_at_scan(poses, anchor.time)?.inverse() * pose_at_scan(poses, node.time)?;
                let e = anchor_from_node.inverse() * truth;
                Some((
                    e.translation.vector.norm(),
                    e.rotation.angle().abs().to_degrees(),
                ))
            });
            Some(JudgedMatch {
                decided: d.clone(),
                fate: fates
                    .get(&(d.closure.node, d.closure.submap))
                    .copied()
                    .unwrap_or(MatchFate::NeverUsed),
                node_time: node.time,
                anchor_time: anchor.time,
                anchor_from_node,
                error,
            })
        })
        .collect()
}

/// Judged matches counted by decision, then by fate, by name (every decision and fate listed, empty ones
/// included): the table `report.json` carries as `glm_matches`.
pub fn match_counts(
    judged: &[JudgedMatch],
) -> BTreeMap<&'static str, BTreeMap<&'static str, MatchCounts>> {
    let mut table: BTreeMap<&'static str, BTreeMap<&'static str, MatchCounts>> = MatchDecision::ALL
        .iter()
        .map(|d| {
            (
                d.name(),
                MatchFate::ALL
                    .iter()
                    .map(|f| (f.name(), MatchCounts::default()))
                    .collect(),
            )
        })
        .collect();
    for j in judged {
        let Some(counts) = table
            .get_mut(j.decided.decision.name())
            .and_then(|row| row.get_mut(j.fate.name()))
        else {
            continue;
        };
        counts.matches += 1;
        match j.right() {
            Some(true) => counts.right += 1,
            Some(false) => counts.wrong += 1,
            None => {}
        }
    }
    table
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;
    use crate::global_slam::{GlobalSlamEvent, straight_run, wide_closure};

    #[test]
    fn each_match_is_judged_against_the_reference_by_rule_and_fate() {
        let mut global = straight_run(30);
        // The run drove a straight line, and so did the robot: the nodes' poses are the truth.
        let truth: Vec<(Timestamp, Rigid2)> = global
            .nodes()
            .values()
            .map(|n| (n.time, n.local_pose))
            .collect();
        // Node 25 where it is (accepted at once), node 26 a metre ahead of where it is (beyond what
        // 5 m of drift explains: held for a chorus that never comes).
        let events = global.add_search_results([
            wide_closure(25, Rigid2::identity()),
            wide_closure(26, rigid2(1.0, 0.0, 0.0)),
        ]);
        let decided: Vec<MatchDecided> = events
            .into_iter()
            .filter_map(|e| match e {
                GlobalSlamEvent::MatchDecided(d) => Some(d),
                _ => None,
            })
            .collect();
        let judged = judge_matches(&global, &decided, Some(&truth));
        assert_eq!(judged.len(), 2);
        // Judged from the submap's node nearest the match, node 10 at x = 2 m.
        assert_eq!(judged[0].anchor_time, Timestamp(1_000_000_000));
        assert!((judged[0].anchor_from_node.translation.x - 3.0).abs() < 1e-9);
        assert_eq!(
            (
                judged[0].decided.decision,
                judged[0].fate,
                judged[0].right()
            ),
            (MatchDecision::Accepted, MatchFate::InGraph, Some(true))
        );
        assert_eq!(
            (
                judged[1].decided.decision,
                judged[1].fate,
                judged[1].right()
            ),
            (
                MatchDecision::HeldBeyondDrift,
                MatchFate::NeverUsed,
                Some(false)
            )
        );
        let (m, _) = judged[1].error.expect("judged");
        assert!((m - 1.0).abs() < 1e-9, "{m}");

        let counts = match_counts(&judged);
        assert_eq!(
            counts["accepted"]["in_graph"],
            MatchCounts {
                matches: 1,
                right: 1,
                wrong: 0
            }
        );
        assert_eq!(counts["held_beyond_drift"]["never_used"].wrong, 1);
        assert_eq!(counts["outvoted"]["never_used"], MatchCounts::default());
        // Without a reference, only where they ended.
        let unjudged = judge_matches(&global, &decided, None);
        assert!(unjudged.iter().all(|j| j.right().is_none()));
        assert_eq!(match_counts(&unjudged)["accepted"]["in_graph"].matches, 1);
    }
}
