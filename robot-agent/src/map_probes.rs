//! The site map as it stood at a given moment of a multi-session run: where the map held an earlier
//! session's scan when the robot estimated a later scan. A relation between the two is then judged
//! against the map the robot was placed on (see `mapping::metrics::judge_placements`), not against a
//! map smoothed after the fact.

use std::collections::BTreeMap;

use mapping::geometry::Rigid2;
use mapping::io::relations::Relation;
use mapping::metrics::{RelationError, pose_at, relation_error};
use mapping::pose_graph::NodeId;
use mapping::sensor::Timestamp;

use crate::lifelong_run::ScanAnchor;

/// Asks where the map held the scan at `earlier` (a scan of a session that has ended) at the moment the
/// robot estimated its pose at `later`: right after the map took in the node that `later`'s estimate
/// derives from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapProbe {
    /// A scan of an earlier session.
    pub earlier: Timestamp,
    /// A scan of a later session.
    pub later: Timestamp,
}

/// The relations whose two stamps fall in different sessions (`boundaries`: each session's start time),
/// with the probe each asks: where the map held its earlier scan when the robot estimated its later one.
pub fn cross_session_probes(
    relations: &[Relation],
    boundaries: &[Timestamp],
) -> (Vec<Relation>, Vec<MapProbe>) {
    let session_of = |t: Timestamp| boundaries.partition_point(|b| *b <= t);
    relations
        .iter()
        .filter(|r| session_of(r.t1) != session_of(r.t2))
        .map(|r| {
            let (earlier, later) = if session_of(r.t1) < session_of(r.t2) {
                (r.t1, r.t2)
            } else {
                (r.t2, r.t1)
            };
            (r.clone(), MapProbe { earlier, later })
        })
        .unzip()
}

/// The relations that score the map a multi-session run leaves: those within one session, and those
/// between two sessions that are both in the map (`in_map[k]`: session `k`, which starts at
/// `boundaries[k]`, ended placed and committed). A relation touching a session dropped at its end (never
/// placed, or its placement never committed) is left out, and counted: that session's scans float in a
/// frame nothing ties to the site, so its error says nothing of the map (a refusal, not an error).
pub fn relations_in_the_map(
    relations: &[Relation],
    boundaries: &[Timestamp],
    in_map: &[bool],
) -> (Vec<Relation>, usize) {
    let session_of = |t: Timestamp| boundaries.partition_point(|b| *b <= t).saturating_sub(1);
    let kept_session = |k: usize| in_map.get(k).copied().unwrap_or(false);
    let (kept, left_out): (Vec<&Relation>, Vec<&Relation>) = relations.iter().partition(|r| {
        let (a, b) = (session_of(r.t1), session_of(r.t2));
        a == b || (kept_session(a) && kept_session(b))
    });
    (kept.into_iter().cloned().collect(), left_out.len())
}

/// Each relation's error as the robot lived it: its later scan's estimate at the time (`online`,
/// time-ordered `map_from_base`) against `answers`, the map's pose of its earlier scan at that moment
/// (the run's answers to `probes`). Relations without either pose are left out.
pub fn relation_errors_at_the_time(
    relations: &[Relation],
    probes: &[MapProbe],
    answers: &[Option<Rigid2>],
    online: &[(Timestamp, Rigid2)],
) -> Vec<RelationError> {
    relations
        .iter()
        .zip(probes)
        .zip(answers)
        .filter_map(|((relation, probe), earlier)| {
            let earlier = (*earlier)?;
            let later = pose_at(online, probe.later)?;
            Some(if probe.earlier == relation.t1 {
                relation_error(relation, &earlier, &later)
            } else {
                relation_error(relation, &later, &earlier)
            })
        })
        .collect()
}

/// Answers [`MapProbe`]s as a run goes: the map's worker calls [`Self::answer_before`] before it takes
/// in each node and before a session ends, and [`Self::add_ended_session`] after.
#[derive(Debug, Default)]
pub(crate) struct MapProbes {
    probes: Vec<MapProbe>,
    /// Probe indices by `later`.
    order: Vec<usize>,
    next: usize,
    answers: Vec<Option<Rigid2>>,
    /// The scans of the sessions that have ended, in time order, and their nodes' local poses.
    past_scans: Vec<ScanAnchor>,
    past_node_local: BTreeMap<NodeId, Rigid2>,
}

impl MapProbes {
    pub(crate) fn new(probes: &[MapProbe]) -> Self {
        let mut order: Vec<usize> = (0..probes.len()).collect();
        order.sort_by_key(|&k| probes[k].later);
        Self {
            probes: probes.to_vec(),
            order,
            answers: vec![None; probes.len()],
            ..Self::default()
        }
    }

    /// Answers, from the map as it is now (`node_pose`: a node's current global pose), every probe
    /// whose `later` scan comes before `before`.
    pub(crate) fn answer_before(
        &mut self,
        before: Timestamp,
        node_pose: impl Fn(NodeId) -> Option<Rigid2>,
    ) {
        while let Some(&k) = self.order.get(self.next) {
            let probe = self.probes[k];
            if probe.later >= before {
                break;
            }
            self.answers[k] = self.earlier_pose(probe.earlier, &node_pose);
            self.next += 1;
        }
    }

    /// Where the map holds the ended sessions' scan at `t` now (nearest scan within 0.1 s, or
    /// interpolated, as the relations metric takes it).
    fn earlier_pose(
        &self,
        t: Timestamp,
        node_pose: &impl Fn(NodeId) -> Option<Rigid2>,
    ) -> Option<Rigid2> {
        let i = self.past_scans.partition_point(|a| a.time < t);
        let near: Vec<(Timestamp, Rigid2)> = [i.checked_sub(1), Some(i)]
            .into_iter()
            .flatten()
            .filter_map(|k| self.past_scans.get(k))
            .filter_map(|a| {
                let node = a.node?;
                let global = node_pose(node)?;
                let local = self.past_node_local.get(&node)?;
                Some((a.time, global * local.inverse() * a.local_pose))
            })
            .collect();
        pose_at(&near, t)
    }

    /// Adds an ended session's scans (time-ordered, after every earlier session's) and its nodes' local
    /// poses.
    pub(crate) fn add_ended_session(
        &mut self,
        scans: &[ScanAnchor],
        node_local: &BTreeMap<NodeId, Rigid2>,
    ) {
        self.past_scans.extend_from_slice(scans);
        self.past_node_local
            .extend(node_local.iter().map(|(id, pose)| (*id, *pose)));
    }

    /// Every probe's answer, in the probes' order (`None`: the earlier scan had no pose in the map then,
    /// or the run ended first).
    pub(crate) fn into_answers(self) -> Vec<Option<Rigid2>> {
        self.answers
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    fn s(secs: f64) -> Timestamp {
        Timestamp::from_secs_f64(secs)
    }

    #[test]
    fn relations_touching_a_dropped_session_are_left_out_and_counted() {
        let relation = |t1: f64, t2: f64| Relation {
            t1: s(t1),
            t2: s(t2),
            delta: Rigid2::identity(),
        };
        // Sessions start at 0, 10 and 20 s; the second was dropped.
        let boundaries = [s(0.0), s(10.0), s(20.0)];
        let relations = [
            relation(1.0, 2.0),   // within session 0
            relation(11.0, 12.0), // within the dropped session: self-consistent, kept
            relation(1.0, 21.0),  // between two sessions in the map
            relation(2.0, 12.0),  // to the dropped session
            relation(12.0, 22.0), // from the dropped session
        ];
        let (kept, left_out) = relations_in_the_map(&relations, &boundaries, &[true, false, true]);
        let stamps: Vec<_> = kept.iter().map(|r| (r.t1, r.t2)).collect();
        assert_eq!(
            stamps,
            vec![(s(1.0), s(2.0)), (s(11.0), s(12.0)), (s(1.0), s(21.0))]
        );
        assert_eq!(left_out, 2);
        let (kept, left_out) = relations_in_the_map(&relations, &boundaries, &[true, true, true]);
        assert_eq!((kept.len(), left_out), (5, 0));
    }

    #[test]
    fn a_probe_is_answered_from_the_map_as_it_stood_before_its_later_scan() {
        let node = NodeId {
            trajectory: 0,
            index: 0,
        };
        let mut probes = MapProbes::new(&[
            MapProbe {
                earlier: s(1.0),
                later: s(20.0),
            },
            MapProbe {
                earlier: s(1.0),
                later: s(10.0),
            },
        ]);
        // Session 0: one node at its local origin, a scan 1 m further along it.
        probes.add_ended_session(
            &[ScanAnchor {
                time: s(1.0),
                local_pose: rigid2(1.0, 0.0, 0.0),
                node: Some(node),
            }],
            &BTreeMap::from([(node, Rigid2::identity())]),
        );
        // At 10 s the map holds the node at x = 5; by 20 s an optimization moved it to x = 6.
        probes.answer_before(s(15.0), |_| Some(rigid2(5.0, 0.0, 0.0)));
        probes.answer_before(s(25.0), |_| Some(rigid2(6.0, 0.0, 0.0)));
        let answers = probes.into_answers();
        assert_eq!(answers[1].map(|p| p.translation.vector.x), Some(6.0));
        assert_eq!(answers[0].map(|p| p.translation.vector.x), Some(7.0));
    }
}
