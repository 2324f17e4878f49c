//! How well the optimized graph agrees with each accepted loop closure: the measure of loop-closure
//! precision of Hess et al., "Real-Time Loop Closure in 2D LIDAR SLAM" (ICRA 2016, Table IV): a closure
//! counts as true when the final optimization violates it by less than 20 cm and 1°.

use serde::Serialize;

use super::{Acceptance, LoopClosure};

/// A loop closure counts as true when its residual after optimization is below this translation (m) …
pub const TRUE_CLOSURE_TRANSLATION_M: f64 = 0.20;
/// … and this rotation (radians, 1°).
pub const TRUE_CLOSURE_ROTATION_RAD: f64 = std::f64::consts::PI / 180.0;

/// One accepted loop closure against the optimized poses.
#[derive(Clone, Debug, PartialEq)]
pub struct LoopClosureCheck {
    /// The closure as accepted.
    pub closure: LoopClosure,
    /// How it was accepted.
    pub acceptance: Acceptance,
    /// Translation (m) of `measured⁻¹ · optimized` for the node in the submap's frame.
    pub residual_translation_m: f64,
    /// Absolute rotation (rad) of that residual.
    pub residual_rotation_rad: f64,
    /// Whether the back end removed it from the graph because the optimized graph refused it (see
    /// `GlobalSlamOptions::loop_closure_retraction_chi2`).
    pub retracted: bool,
}

impl LoopClosureCheck {
    /// Whether the optimized graph holds the closure within [`TRUE_CLOSURE_TRANSLATION_M`] and
    /// [`TRUE_CLOSURE_ROTATION_RAD`].
    pub fn holds(&self) -> bool {
        self.residual_translation_m < TRUE_CLOSURE_TRANSLATION_M
            && self.residual_rotation_rad < TRUE_CLOSURE_ROTATION_RAD
    }
}

/// Summary of [`LoopClosureCheck`]s.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct LoopClosurePrecision {
    /// Closures checked that are in the graph (not retracted).
    pub checked: usize,
    /// Those the optimized graph holds.
    pub held: usize,
    /// `held / checked` (1 when nothing was checked): the precision of the closures the map is made of.
    pub precision: f64,
    /// Closures the back end retracted (not in `checked`).
    pub retracted: usize,
    /// The share of every match GLM accepted, retracted ones included, that the optimized graph holds
    /// (1 when there were none): how good the matching is, whatever the back end made of it.
    pub precision_as_matched: f64,
}

/// The share of `checks` the optimized graph holds.
///
/// What it cannot see: it measures agreement with the final optimization, not with the world. A map
/// pulled consistently wrong (a wing rotated by closures that all agree with each other) holds every
/// closure it is made of and scores 1. Only ground truth (`metrics::relations_error`'s `torn` and
/// largest errors) shows such a tear.
pub fn loop_closure_precision(checks: &[LoopClosureCheck]) -> LoopClosurePrecision {
    let ratio = |held: usize, of: usize| {
        if of == 0 {
            1.0
        } else {
            held as f64 / of as f64
        }
    };
    let retracted = checks.iter().filter(|c| c.retracted).count();
    let checked = checks.len() - retracted;
    let held = checks.iter().filter(|c| !c.retracted && c.holds()).count();
    LoopClosurePrecision {
        checked,
        held,
        precision: ratio(held, checked),
        retracted,
        precision_as_matched: ratio(checks.iter().filter(|c| c.holds()).count(), checks.len()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;
    use crate::pose_graph::{NodeId, SubmapId};

    fn check(t: f64, r: f64) -> LoopClosureCheck {
        LoopClosureCheck {
            closure: LoopClosure {
                submap: SubmapId {
                    trajectory: 0,
                    index: 0,
                },
                node: NodeId {
                    trajectory: 0,
                    index: 0,
                },
                submap_from_node: rigid2(0.0, 0.0, 0.0),
                score: 0.7,
                runner_up_score: None,
                information: None,
            },
            acceptance: Acceptance::default(),
            residual_translation_m: t,
            residual_rotation_rad: r,
            retracted: false,
        }
    }

    #[test]
    fn precision_counts_closures_within_both_bounds() {
        let checks = [
            check(0.05, 0.001),
            check(0.25, 0.001), // too far
            check(0.05, 0.02),  // turned more than 1°
            check(0.19, 0.017),
        ];
        let p = loop_closure_precision(&checks);
        assert_eq!((p.checked, p.held), (4, 2));
        assert!((p.precision - 0.5).abs() < 1e-12);
        assert!((loop_closure_precision(&[]).precision - 1.0).abs() < 1e-12);
    }

    #[test]
    fn retracted_closures_leave_the_map_precision_but_not_the_matched_one() {
        let retracted = |t| LoopClosureCheck {
            retracted: true,
            ..check(t, 0.001)
        };
        let p = loop_closure_precision(&[check(0.05, 0.001), retracted(0.9), retracted(0.1)]);
        assert_eq!((p.checked, p.held, p.retracted), (1, 1, 2));
        assert!((p.precision - 1.0).abs() < 1e-12);
        assert!((p.precision_as_matched - 2.0 / 3.0).abs() < 1e-12);
    }
}
