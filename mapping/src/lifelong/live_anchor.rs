//! [`LiveAnchor`]: the pose a placed robot navigates on, between optimizations.
//!
//! A session's nodes are placed in the map by its `global_from_local`, which the pose graph re-derives only
//! when it optimizes (every `optimize_every_n_nodes` nodes, or when matches confirm a correction). Between
//! optimizations LLO's drift since then goes straight into the robot's pose, although GLM keeps matching
//! its nodes against the map. The anchor fuses each node's best accepted match against the map into the
//! session's `global_from_local` (the paper's agents localize so), and takes the graph's own once it
//! optimizes. Right after a session's start in the map this halves what the robot's estimate is off at the
//! time on ACES and MIT CSAIL cut into sessions (docs/BENCHMARK-HISTORY.md, "Session 70").
//!
//! The fusion is an extended Kalman filter on the error of the robot's pose, a right perturbation
//! `(x, y, θ)` in the robot's frame: LLO's motion carries it along and adds drift in proportion to the
//! path since the last match, and each match is a measurement with the σ a loop closure enters the graph
//! with. A single match pins the node's position well but its heading only to about half a degree, which a
//! lever of tens of metres turns into decimetres: the filter takes a match's heading only as far as the
//! drift since the last one makes it news (docs/BENCHMARK-HISTORY.md, "Session 71").

use nalgebra::{Matrix3, Vector3};

use crate::geometry::{Rigid2, se2_exp, se2_log};
use crate::global_slam::ConstraintBuilderOptions;

/// The noise model of a [`LiveAnchor`]: how far a match is off, and how fast LLO drifts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LiveAnchorNoise {
    /// σ of a match's translation (m).
    pub match_translation_sigma: f64,
    /// σ of a match's rotation (rad).
    pub match_rotation_sigma: f64,
    /// σ of LLO's translation drift per metre of path since the last match (m/m).
    pub drift_translation_per_m: f64,
    /// σ of LLO's heading drift per metre of path since the last match (rad/m).
    pub drift_rotation_per_m: f64,
}

impl LiveAnchorNoise {
    /// GLM's own model: a match as precise as the loop closure it adds to the graph
    /// (`loop_closure_*_sigma`), LLO drifting as fast as GLM's search windows grow with the path
    /// (`linear_window_growth`, `angular_window_growth`).
    pub fn from_constraint_builder(options: &ConstraintBuilderOptions) -> Self {
        Self {
            match_translation_sigma: options.loop_closure_translation_sigma,
            match_rotation_sigma: options.loop_closure_rotation_sigma,
            drift_translation_per_m: options.linear_window_growth,
            drift_rotation_per_m: options.angular_window_growth,
        }
    }

    /// A match's covariance, in the node's frame.
    fn match_covariance(&self) -> Matrix3<f64> {
        pose_covariance(
            self.match_translation_sigma.powi(2),
            self.match_rotation_sigma.powi(2),
        )
    }

    /// The drift LLO adds as its path since the last match grows from `from` to `to` metres: drift grows
    /// in proportion to the path (a heading bias, a scale error), as GLM's windows do, so its variance
    /// grows with the path's square.
    fn drift_covariance(&self, from: f64, to: f64) -> Matrix3<f64> {
        let grown = to.powi(2) - from.powi(2);
        pose_covariance(
            self.drift_translation_per_m.powi(2) * grown,
            self.drift_rotation_per_m.powi(2) * grown,
        )
    }
}

/// A covariance over `(x, y, θ)` with `translation` variance (m²) on each axis and `rotation` variance (rad²).
fn pose_covariance(translation: f64, rotation: f64) -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(translation, translation, rotation))
}

/// σ of a placement the matches have not yet spoken on (m): nothing a match says is unlikely.
const UNKNOWN_TRANSLATION_SIGMA: f64 = 100.0;
/// … (rad).
const UNKNOWN_ROTATION_SIGMA: f64 = 10.0;

/// A session's `global_from_local` as the robot has it (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LiveAnchor {
    global_from_local: Rigid2,
    noise: LiveAnchorNoise,
    /// The local pose (LLO's frame) the covariance is expressed at; `None` before the first node.
    at: Option<Rigid2>,
    /// Covariance of the robot's pose error at `at`, a right perturbation `(x, y, θ)` in its frame.
    covariance: Matrix3<f64>,
    /// LLO's path since the last match (m).
    path_since_match: f64,
}

/// The adjoint of `pose` on SE(2) right perturbations: `pose · exp(δ) = exp(Ad · δ) · pose`.
fn adjoint(pose: &Rigid2) -> Matrix3<f64> {
    let (c, s) = (pose.rotation.cos_angle(), pose.rotation.sin_angle());
    let t = pose.translation.vector;
    Matrix3::new(c, -s, t.y, s, c, -t.x, 0.0, 0.0, 1.0)
}

/// `covariance` of a perturbation at a pose, seen at that pose composed with `motion`.
fn carried(covariance: &Matrix3<f64>, motion: &Rigid2) -> Matrix3<f64> {
    let a = adjoint(&motion.inverse());
    a * covariance * a.transpose()
}

impl LiveAnchor {
    /// Anchored at `global_from_local` (the graph's, after an optimization), trusted as much as one match.
    pub fn new(global_from_local: Rigid2, noise: LiveAnchorNoise) -> Self {
        Self {
            global_from_local,
            noise,
            at: None,
            covariance: noise.match_covariance(),
            path_since_match: 0.0,
        }
    }

    /// Anchored at a session start's placement, which the first match overrules (a placement is only as
    /// good as the start search's grid; the matches that follow it are refined).
    pub fn placed(global_from_local: Rigid2, noise: LiveAnchorNoise) -> Self {
        Self {
            covariance: pose_covariance(
                UNKNOWN_TRANSLATION_SIGMA.powi(2),
                UNKNOWN_ROTATION_SIGMA.powi(2),
            ),
            ..Self::new(global_from_local, noise)
        }
    }

    /// The session's `global_from_local` as the robot has it.
    pub fn global_from_local(&self) -> Rigid2 {
        self.global_from_local
    }

    /// Where the robot is at `local_pose` (LLO's frame).
    pub fn pose(&self, local_pose: &Rigid2) -> Rigid2 {
        self.global_from_local * local_pose
    }

    /// LLO moved the robot to `local_pose`: its error grows with the path since the last match.
    pub fn advance(&mut self, local_pose: &Rigid2) {
        if let Some(at) = self.at {
            let motion = at.inverse() * local_pose;
            let path = self.path_since_match + motion.translation.vector.norm();
            self.covariance = carried(&self.covariance, &motion)
                + self.noise.drift_covariance(self.path_since_match, path);
            self.path_since_match = path;
        }
        self.at = Some(*local_pose);
    }

    /// Fuses a match of the node at `local_pose` (LLO's frame): the node is at `submap_from_node` in the
    /// submap whose pose in the map is `global_from_submap`, with `information` over the error in the
    /// node's frame (the constraint the match adds to the graph, [`LoopClosure::information`]: a match in
    /// a corridor hardly pins the position along it), or the noise model's σ where it is `None`.
    ///
    /// [`LoopClosure::information`]: crate::global_slam::LoopClosure::information
    pub fn anchor_on_match(
        &mut self,
        global_from_submap: &Rigid2,
        submap_from_node: &Rigid2,
        local_pose: &Rigid2,
        information: Option<&Matrix3<f64>>,
    ) {
        let at = *self.at.get_or_insert(*local_pose);
        let to_node = at.inverse() * local_pose;
        let prior = carried(&self.covariance, &to_node);
        let estimate = self.global_from_local * local_pose;
        let measured = global_from_submap * submap_from_node;
        let innovation = se2_log(&(estimate.inverse() * measured));
        let measurement = information
            .and_then(|information| information.try_inverse())
            .unwrap_or_else(|| self.noise.match_covariance());
        let Some(inverse) = (prior + measurement).try_inverse() else {
            return;
        };
        let gain = prior * inverse;
        let corrected = estimate * se2_exp(&(gain * innovation));
        self.global_from_local = corrected * local_pose.inverse();
        let posterior = (Matrix3::identity() - gain) * prior;
        self.covariance = carried(&posterior, &to_node.inverse());
        self.path_since_match = 0.0;
    }
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;

    use super::*;
    use crate::geometry::{Rigid2Ext as _, rigid2};

    fn noise() -> LiveAnchorNoise {
        LiveAnchorNoise::from_constraint_builder(&ConstraintBuilderOptions::default())
    }

    #[test]
    fn after_a_long_drive_a_match_moves_the_robot_to_where_it_puts_the_node() {
        let mut anchor = LiveAnchor::new(rigid2(1.0, 0.0, 0.0), noise());
        anchor.advance(&rigid2(0.0, 0.0, 0.0));
        let node = rigid2(200.0, 0.0, 0.0);
        anchor.advance(&node);
        assert_relative_eq!(anchor.pose(&node).translation.x, 201.0);
        // The map says the node is 0.3 m farther and turned 0.1 rad: LLO drifted over 200 m.
        let submap = rigid2(0.0, 1.0, 0.0);
        let submap_from_node = rigid2(201.3, -1.0, 0.1);
        anchor.anchor_on_match(&submap, &submap_from_node, &node, None);
        let at_node = anchor.pose(&node);
        assert_relative_eq!(at_node.translation.x, 201.3, epsilon = 1e-3);
        assert_relative_eq!(at_node.translation.y, 0.0, epsilon = 1e-3);
        assert_relative_eq!(at_node.theta(), 0.1, epsilon = 1e-3);
        // One metre on in LLO's frame is one metre on along the corrected heading.
        let later = anchor.pose(&rigid2(201.0, 0.0, 0.0));
        assert_relative_eq!(later.translation.x, 201.3 + 0.1f64.cos(), epsilon = 1e-2);
        assert_relative_eq!(later.translation.y, 0.1f64.sin(), epsilon = 1e-2);
    }

    #[test]
    fn a_match_off_in_heading_turns_a_well_matched_robot_only_a_little_until_others_agree() {
        let mut anchor = LiveAnchor::new(Rigid2::identity(), noise());
        let mut node = Rigid2::identity();
        anchor.advance(&node);
        // Matched every metre for 20 m, each match agreeing with the anchor.
        for i in 1..=20 {
            node = rigid2(f64::from(i), 0.0, 0.0);
            anchor.advance(&node);
            anchor.anchor_on_match(&Rigid2::identity(), &node, &node, None);
        }
        assert_relative_eq!(
            anchor.global_from_local(),
            Rigid2::identity(),
            epsilon = 1e-12
        );
        // A match 1° off in heading, right where the node is: the heading moves a fraction of that, and a
        // point 20 m ahead far less than 20 m × 1°.
        let one_degree = 1f64.to_radians();
        let turned_node = rigid2(20.0, 0.0, one_degree);
        anchor.anchor_on_match(&Rigid2::identity(), &turned_node, &node, None);
        let turned = anchor.pose(&node).theta();
        assert!(turned > 0.0 && turned < 0.5 * one_degree, "{turned}");
        let ahead = anchor.pose(&rigid2(40.0, 0.0, 0.0));
        assert!(ahead.translation.y.abs() < 0.5 * 20.0 * one_degree);
        // Matches that keep saying so win in the end.
        for _ in 0..200 {
            anchor.anchor_on_match(&Rigid2::identity(), &turned_node, &node, None);
        }
        assert_relative_eq!(anchor.pose(&node).theta(), one_degree, epsilon = 1e-3);
    }

    #[test]
    fn a_match_in_a_corridor_moves_the_robot_across_it_not_along_it() {
        let mut anchor = LiveAnchor::new(Rigid2::identity(), noise());
        anchor.advance(&Rigid2::identity());
        let node = rigid2(2.0, 0.0, 0.0);
        anchor.advance(&node);
        // A corridor along the robot's x: the match pins y 10× better than x (σ 0.03 m against 0.3 m).
        let information = Matrix3::from_diagonal(&Vector3::new(
            1.0 / 0.3f64.powi(2),
            1.0 / 0.03f64.powi(2),
            1.0 / 0.01f64.powi(2),
        ));
        anchor.anchor_on_match(
            &Rigid2::identity(),
            &rigid2(2.3, 0.05, 0.0),
            &node,
            Some(&information),
        );
        let moved = anchor.pose(&node).translation.vector - node.translation.vector;
        assert!(moved.x.abs() < 0.05, "{moved:?}");
        assert!(moved.y > 0.025, "{moved:?}");
    }

    #[test]
    fn the_error_carried_by_a_turn_in_place_keeps_its_size() {
        let mut anchor = LiveAnchor::new(Rigid2::identity(), noise());
        anchor.advance(&Rigid2::identity());
        let before = anchor.covariance;
        anchor.advance(&rigid2(0.0, 0.0, 1.0));
        assert_relative_eq!(anchor.covariance.trace(), before.trace(), epsilon = 1e-12);
    }
}
