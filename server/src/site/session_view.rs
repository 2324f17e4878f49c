//! What an operator sees of one session: its robot, where it stands in the session start (searching, on
//! probation, committed, dropped), and its trajectory in the site frame.

use mapping::geometry::Rigid2;
use serde::Serialize;

/// Where a session stands in the session start (`mapping::lifelong::SessionStart`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PlacementState {
    /// Opened; no node has arrived yet.
    Waiting,
    /// The site's first session: the map's frame.
    Base,
    /// Not placed in the map (no prior, or its placement revoked): the server is searching for it.
    Searching,
    /// Placed tentatively (on probation): its submaps are not published yet.
    Probation,
    /// Placed and committed: its submaps are part of the map.
    Committed,
    /// Ended unplaced or on probation: it added nothing to the map.
    Dropped,
}

/// One session of a site.
#[derive(Clone, Debug, PartialEq)]
pub struct SessionView {
    /// The session's uuid.
    pub session: String,
    /// Its robot.
    pub robot_id: String,
    /// Its trajectory in the site map (the order sessions were opened in).
    pub trajectory: u32,
    /// Whether it has ended.
    pub closed: bool,
    /// Nodes received.
    pub nodes: u64,
    /// Its placement state.
    pub state: PlacementState,
    /// The robot relocalized the session's start itself and sent it as a prior.
    pub prior_from_robot: bool,
    /// The robot's prior was revoked by disagreeing matches (the server searched for it instead).
    pub robot_prior_revoked: bool,
    /// `global_from_local` of the session while it is placed (committed, on probation or the base).
    pub global_from_local: Option<Rigid2>,
    /// Node poses still in the map (`global_from_tracking`), in node order, while the session is placed
    /// (an unplaced session's poses are in a frame nothing ties to the site). At most
    /// [`SessionView::MAX_TRAJECTORY_POINTS`], evenly thinned, the last node always included.
    pub trajectory_poses: Vec<Rigid2>,
    /// The last node's pose while the session is placed: where the robot is (or was when it ended).
    pub latest_pose: Option<Rigid2>,
}

impl SessionView {
    /// Most trajectory points sent per session.
    pub const MAX_TRAJECTORY_POINTS: usize = 2000;
}

/// Thins `poses` to at most `max` (≥ 2) evenly spaced ones, keeping the first and the last.
pub fn thin_poses(poses: Vec<Rigid2>, max: usize) -> Vec<Rigid2> {
    let max = max.max(2);
    if poses.len() <= max {
        return poses;
    }
    let last = poses.len() - 1;
    (0..max)
        .filter_map(|k| poses.get(k * last / (max - 1)).copied())
        .collect()
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    #[test]
    fn thinning_keeps_both_ends_and_the_bound() {
        let poses: Vec<Rigid2> = (0..1001).map(|i| rigid2(f64::from(i), 0.0, 0.0)).collect();
        let thin = thin_poses(poses.clone(), 10);
        assert_eq!(thin.len(), 10);
        assert_eq!(thin[0], poses[0]);
        assert_eq!(thin[9], poses[1000]);
        assert_eq!(thin_poses(poses[..5].to_vec(), 10).len(), 5);
    }
}
