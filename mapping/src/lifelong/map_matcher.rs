//! GLM on the robot: matches one session's nodes against the site's global submaps (the robot's cached
//! copy) near where the session's current `global_from_local` puts them, as the paper's agents do, so the
//! server only adds the accepted node-to-submap constraints instead of searching for them.
//!
//! The searches are [`ConstraintBuilder`]'s (branch and bound in the loop-closure window, least-squares
//! refinement, the same minimum score and sampling ratio as the server's GLM). After each node, the best
//! accepted match is fused into the session's `global_from_local` ([`LiveAnchor`], as `sessions` anchors
//! the robot's pose on the map's matches), so the estimate follows the map rather than LLO's drift since the
//! session-start relocalization.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use nalgebra::{Matrix3, Point2};

use crate::geometry::Rigid2;
use crate::global_slam::{
    ConstraintBuilder, ConstraintBuilderOptions, FixedRatioSampler, GlobalSlamOptionsError,
    SearchJob,
};
use crate::grid::ProbabilityGrid;
use crate::pose_graph::{NodeId, SubmapId};

use super::{LiveAnchor, LiveAnchorNoise};

/// One accepted match of a node against a global submap.
#[derive(Clone, Debug, PartialEq)]
pub struct MapMatch {
    /// The global submap.
    pub submap: SubmapId,
    /// The node's measured pose in the submap's frame.
    pub submap_from_node: Rigid2,
    /// Branch-and-bound score.
    pub score: f32,
    /// Information over the error in the node's frame ([`crate::global_slam::LoopClosure::information`]).
    pub information: Option<Matrix3<f64>>,
}

/// A global submap as the robot knows it.
#[derive(Clone, Debug)]
pub struct GlobalSubmap<'a> {
    /// The submap.
    pub id: SubmapId,
    /// `global_from_submap`, the site map's current estimate.
    pub global_pose: Rigid2,
    /// `local_from_submap` in the frame its grid is drawn in (its session's LLO frame).
    pub local_pose: Rigid2,
    /// The grid.
    pub grid: &'a Arc<ProbabilityGrid>,
}

struct Known {
    global_pose: Rigid2,
    grid: Arc<ProbabilityGrid>,
    sampler: FixedRatioSampler,
}

/// GLM for one session on the robot. See the module docs.
pub struct MapMatcher {
    builder: ConstraintBuilder,
    submaps: BTreeMap<SubmapId, Known>,
    anchor: LiveAnchor,
    nodes: u32,
    searches: u64,
}

impl MapMatcher {
    /// A matcher with no submaps yet, for a session placed at `global_from_local` (its start prior).
    pub fn new(
        options: ConstraintBuilderOptions,
        global_from_local: Rigid2,
    ) -> Result<Self, GlobalSlamOptionsError> {
        options.validate()?;
        let noise = LiveAnchorNoise::from_constraint_builder(&options);
        Ok(Self {
            builder: ConstraintBuilder::new(options),
            submaps: BTreeMap::new(),
            anchor: LiveAnchor::placed(global_from_local, noise),
            nodes: 0,
            searches: 0,
        })
    }

    /// Makes the matcher's submaps exactly `submaps`: precomputes the new ones (the costly part), forgets
    /// those gone (trimmed), and takes the current global poses of the rest. A submap whose grid changed
    /// (a new revision) is precomputed again.
    pub fn sync_submaps<'a>(&mut self, submaps: impl IntoIterator<Item = GlobalSubmap<'a>>) {
        let mut seen = BTreeSet::new();
        for submap in submaps {
            seen.insert(submap.id);
            match self.submaps.get_mut(&submap.id) {
                Some(known) if Arc::ptr_eq(&known.grid, submap.grid) => {
                    known.global_pose = submap.global_pose;
                }
                _ => {
                    self.builder.add_finished_submap(
                        submap.id,
                        submap.local_pose,
                        Arc::clone(submap.grid),
                    );
                    self.submaps.insert(
                        submap.id,
                        Known {
                            global_pose: submap.global_pose,
                            grid: Arc::clone(submap.grid),
                            sampler: FixedRatioSampler::new(self.builder.options().sampling_ratio),
                        },
                    );
                }
            }
        }
        let gone: Vec<SubmapId> = self
            .submaps
            .keys()
            .filter(|id| !seen.contains(id))
            .copied()
            .collect();
        for id in gone {
            self.submaps.remove(&id);
            self.builder.remove_submap(id);
        }
    }

    /// The session's current `global_from_local`.
    pub fn global_from_local(&self) -> Rigid2 {
        self.anchor.global_from_local()
    }

    /// Submaps known.
    pub fn num_submaps(&self) -> usize {
        self.submaps.len()
    }

    /// Searches run so far.
    pub fn searches(&self) -> u64 {
        self.searches
    }

    /// Matches the session's next node (`local_from_tracking`, its filtered points in the tracking frame)
    /// against the known submaps within the loop-closure distance of its estimate, each sampled at the
    /// configured ratio. Returns the accepted matches, best first, and fuses the best into the session's anchor.
    pub fn match_node(
        &mut self,
        local_pose: &Rigid2,
        points: &Arc<Vec<Point2<f32>>>,
    ) -> Vec<MapMatch> {
        let node = NodeId {
            trajectory: u32::MAX,
            index: self.nodes,
        };
        self.nodes += 1;
        self.anchor.advance(local_pose);
        let global_node = self.anchor.pose(local_pose);
        let max_distance = self.builder.options().max_constraint_distance;
        let mut jobs = Vec::new();
        for (id, known) in &mut self.submaps {
            let submap_from_node = known.global_pose.inverse() * global_node;
            if submap_from_node.translation.vector.norm() > max_distance || !known.sampler.pulse() {
                continue;
            }
            jobs.push(SearchJob {
                submap: *id,
                node,
                points: Arc::clone(points),
                submap_from_node_estimate: Some(submap_from_node),
                window: None,
            });
        }
        self.searches += jobs.len() as u64;
        let mut matches: Vec<MapMatch> = jobs
            .iter()
            .filter_map(|job| self.builder.run(job))
            .map(|closure| MapMatch {
                submap: closure.submap,
                submap_from_node: closure.submap_from_node,
                score: closure.score,
                information: closure.information,
            })
            .collect();
        matches.sort_by(|a, b| b.score.total_cmp(&a.score));
        if let Some(best) = matches.first()
            && let Some(known) = self.submaps.get(&best.submap)
        {
            self.anchor.anchor_on_match(
                &known.global_pose,
                &best.submap_from_node,
                local_pose,
                best.information.as_ref(),
            );
        }
        matches
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;

    use super::*;
    use crate::geometry::{Rigid2Ext as _, rigid2};
    use crate::grid::{CellIndex, MapLimits};

    /// A 10 m × 6 m room with an L-shaped display, 10 cm walls, free elsewhere, in the submap's local frame.
    fn room() -> Arc<ProbabilityGrid> {
        let r = 0.05;
        let mut grid = ProbabilityGrid::new(MapLimits::new(r, Vector2::new(-1.0, -1.0), 240, 160));
        for iy in 0..160 {
            for ix in 0..240 {
                let (x, y) = (
                    -1.0 + (f64::from(ix) + 0.5) * r,
                    -1.0 + (f64::from(iy) + 0.5) * r,
                );
                // Walls two cells thick: a flat top wider than that lets a scan-led refinement wander
                // across it.
                let near = |a: f64, b: f64| (a - b).abs() < 0.03;
                let inside = |v: f64, lo: f64, hi: f64| v > lo - 0.1 && v < hi + 0.1;
                let wall = ((near(x, 0.0) || near(x, 10.0)) && inside(y, 0.0, 6.0))
                    || ((near(y, 0.0) || near(y, 6.0)) && inside(x, 0.0, 10.0));
                // An L-shaped display breaks the room's symmetry.
                let display =
                    (near(y, 1.5) && inside(x, 5.7, 6.3)) || (near(x, 5.7) && inside(y, 1.5, 2.5));
                let p = if wall || display { 0.9 } else { 0.1 };
                grid.set_probability(&CellIndex::new(ix, iy), p);
            }
        }
        Arc::new(grid)
    }

    /// Points on the room's walls and display seen from `pose` (room frame), in the tracking frame.
    fn scan(pose: &Rigid2) -> Arc<Vec<Point2<f32>>> {
        let mut points = Vec::new();
        for i in 0..200 {
            let t = f64::from(i) / 200.0;
            for p in [
                Vector2::new(10.0 * t, 0.0),
                Vector2::new(10.0 * t, 6.0),
                Vector2::new(0.0, 6.0 * t),
                Vector2::new(10.0, 6.0 * t),
                Vector2::new(5.7 + 0.6 * t, 1.5),
                Vector2::new(5.7, 1.5 + t),
            ] {
                let local = pose.inverse() * nalgebra::Point2::from(p);
                points.push(Point2::new(local.x as f32, local.y as f32));
            }
        }
        Arc::new(points)
    }

    fn options() -> ConstraintBuilderOptions {
        ConstraintBuilderOptions {
            sampling_ratio: 1.0,
            ..ConstraintBuilderOptions::default()
        }
    }

    #[test]
    fn a_drifted_estimate_is_matched_to_the_truth_and_the_session_re_anchored() {
        let grid = room();
        // The submap: drawn in a session frame that sits at (20, -3, 0.3) in the site frame.
        let id = SubmapId {
            trajectory: 0,
            index: 0,
        };
        let site_from_session0 = rigid2(20.0, -3.0, 0.3);
        let local_pose = rigid2(1.0, 1.0, 0.0);
        let global_pose = site_from_session0 * local_pose;
        // This session's true frame, and a prior off by 0.25 m and 3°.
        let truth = rigid2(18.0, 1.0, -0.4);
        let prior = truth * rigid2(0.2, -0.15, 3f64.to_radians());
        let mut matcher = MapMatcher::new(options(), prior).unwrap();
        matcher.sync_submaps([GlobalSubmap {
            id,
            global_pose,
            local_pose,
            grid: &grid,
        }]);
        let room_pose = rigid2(3.0, 3.0, 0.2); // the robot in the room (session-0 local frame)
        let site_pose = site_from_session0 * room_pose;
        let local_node = truth.inverse() * site_pose;
        let found = matcher.match_node(&local_node, &scan(&room_pose));
        assert_eq!(found.len(), 1, "{found:?}");
        let expected = global_pose.inverse() * site_pose;
        let error = found[0].submap_from_node.inverse() * expected;
        assert!(
            error.translation.vector.norm() < 0.05 && error.theta().abs() < 0.02,
            "{error:?}"
        );
        // Re-anchored: the session's frame now puts the node where the map says it is (the prior put it
        // 0.13 m and 3° off).
        let before = (prior * local_node).inverse() * site_pose;
        let after = (matcher.global_from_local() * local_node).inverse() * site_pose;
        assert!(before.translation.vector.norm() > 0.1 && before.theta().abs() > 0.05);
        assert!(
            after.translation.vector.norm() < 0.05 && after.theta().abs() < 0.02,
            "re-anchored: {after:?}"
        );
        // Out of reach (beyond max_constraint_distance): no search.
        let far = matcher.match_node(&rigid2(500.0, 0.0, 0.0), &scan(&room_pose));
        assert!(far.is_empty());
        assert_eq!(matcher.searches(), 1);
        // A trimmed submap is forgotten.
        matcher.sync_submaps([]);
        assert_eq!(matcher.num_submaps(), 0);
        assert!(
            matcher
                .match_node(&local_node, &scan(&room_pose))
                .is_empty()
        );
    }
}
