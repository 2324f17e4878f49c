//! Linearisation of relative-pose constraints, in the optimizer's parametrisation: each pose is
//! `(x, y, θ)` in the world frame, perturbed additively.
//!
//! The error and Jacobians are the optimizer's own (`pose_graph::constraint`): for a constraint `i → j`
//! with measurement `Z`, `A = R(−(θi + θz))` and `u = A (tj − ti)`,
//!
//! ```text
//! e = [ u − R(θz)ᵀ tz ,  wrap(θj − θi − θz) ]
//! ∂e/∂xi = [ −A  (u_y, −u_x)ᵀ ]      ∂e/∂xj = [ A  0 ]
//!          [  0        −1     ]               [ 0  1 ]
//! ```
//!
//! `∂e/∂xj` is a rotation (determinant 1), which the Chow–Liu derivation relies on.

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

use crate::geometry::{Rigid2, Rigid2Ext as _};
use crate::pose_graph::{PreparedMeasurement, RobustLoss};

/// The error `e` of measurement `from_from_to` at `(world_from_from, world_from_to)` and its Jacobians
/// with respect to the `from` and `to` poses.
pub(crate) fn linearize(
    from_from_to: &Rigid2,
    world_from_from: &Rigid2,
    world_from_to: &Rigid2,
) -> (Vector3<f64>, Matrix3<f64>, Matrix3<f64>) {
    PreparedMeasurement::from_parts(from_from_to, Matrix3::identity(), RobustLoss::Trivial)
        .linearize(&world_from_from.to_xytheta(), &world_from_to.to_xytheta())
}

/// A constraint linearised at the current estimate: `½ (e + Ja δa + Jb δb)ᵀ Ω (e + Ja δa + Jb δb)`,
/// with `Ω` already scaled by the robust weight. `a`, `b` index 3×3 blocks of a dense system.
#[derive(Clone, Debug)]
pub(crate) struct LinearFactor {
    pub a: usize,
    pub b: usize,
    pub e: Vector3<f64>,
    pub ja: Matrix3<f64>,
    pub jb: Matrix3<f64>,
    pub omega: Matrix3<f64>,
}

impl LinearFactor {
    /// Adds `JᵀΩJ` to `information` and `JᵀΩe` to `gradient` (when given), skipping a block index
    /// `None` (a variable held fixed, or dropped for the gauge).
    pub(crate) fn accumulate(
        &self,
        block_of: impl Fn(usize) -> Option<usize>,
        information: &mut DMatrix<f64>,
        gradient: Option<&mut DVector<f64>>,
    ) {
        let blocks = [(block_of(self.a), self.ja), (block_of(self.b), self.jb)];
        for (row, jr) in &blocks {
            let Some(row) = row else { continue };
            let left = jr.transpose() * self.omega;
            for (col, jc) in &blocks {
                let Some(col) = col else { continue };
                let block = left * jc;
                let mut view = information.fixed_view_mut::<3, 3>(3 * row, 3 * col);
                view += block;
            }
        }
        if let Some(gradient) = gradient {
            for (row, jr) in &blocks {
                let Some(row) = row else { continue };
                let g = jr.transpose() * (self.omega * self.e);
                let mut view = gradient.fixed_rows_mut::<3>(3 * row);
                view += g;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;

    use super::*;
    use crate::geometry::rigid2;
    use crate::pose_graph::{Constraint, ConstraintKind, NodeId, RobustLoss, VariableId};

    #[test]
    fn error_matches_constraint_and_jacobians_match_differences() {
        let node = |index| {
            VariableId::Node(NodeId {
                trajectory: 0,
                index,
            })
        };
        let cases = [
            (
                rigid2(0.3, -1.2, 0.4),
                rigid2(2.0, 0.5, -2.9),
                rigid2(1.1, 0.7, 2.8),
            ),
            (
                rigid2(-5.0, 3.0, 3.1),
                rigid2(-4.0, 2.0, -3.1),
                rigid2(0.9, -0.2, 0.05),
            ),
            (
                rigid2(10.0, 0.0, -1.5),
                rigid2(10.5, 1.0, 1.5),
                rigid2(-0.4, 0.3, -3.0),
            ),
        ];
        assert!(cases.len() >= 3);
        for (xi, xj, z) in cases {
            let constraint = Constraint {
                kind: ConstraintKind::NodeToNode,
                from: node(0),
                to: node(1),
                from_from_to: z,
                information: Matrix3::identity(),
                loss: RobustLoss::Trivial,
            };
            let (e, ji, jj) = linearize(&z, &xi, &xj);
            assert_relative_eq!(e, constraint.error(&xi, &xj), epsilon = 1e-12);
            assert!(e.norm() > 0.1);
            let h = 1e-6;
            for k in 0..3 {
                let mut step = Vector3::zeros();
                step[k] = h;
                let moved = |x: &Rigid2, s: f64| Rigid2::from_xytheta(&(x.to_xytheta() + s * step));
                let di = (constraint.error(&moved(&xi, 1.0), &xj)
                    - constraint.error(&moved(&xi, -1.0), &xj))
                    / (2.0 * h);
                let dj = (constraint.error(&xi, &moved(&xj, 1.0))
                    - constraint.error(&xi, &moved(&xj, -1.0)))
                    / (2.0 * h);
                assert_relative_eq!(ji.column(k).into_owned(), di, epsilon = 1e-7);
                assert_relative_eq!(jj.column(k).into_owned(), dj, epsilon = 1e-7);
            }
        }
    }
}
