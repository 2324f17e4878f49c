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
    /// Closures checked.
    pub checked: usize,
    /// Those the optimized graph holds.
    pub held: usize,
    /// `held / checked` (1 when nothing was checked).
    pub precision: f64,
}

/// The share of `checks` the optimized graph holds.
pub fn loop_closure_precision(checks: &[LoopClosureCheck]) -> LoopClosurePrecision {
    let held = checks.iter().filter(|c| c.holds()).count();
    LoopClosurePrecision {
        checked: checks.len(),
        held,
        precision: if checks.is_empty() {
            1.0
        } else {
            held as f64 / checks.len() as f64
        },
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
}
