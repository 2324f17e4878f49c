//! Constraints (relative-pose measurements) between pose-graph variables, their error and robust losses.
//!
//! Error convention (g2o's): for a constraint `i → j` with measurement `Z = i_from_j` and estimates
//! `Xi = world_from_i`, `Xj = world_from_j`,
//!
//! ```text
//! e = [ translation of Z⁻¹ · Xi⁻¹ · Xj ,  wrap(θj − θi − θz) ]      χ² = eᵀ Ω e
//! ```
//!
//! With the additive parametrisation `x = (x, y, θ)` in the world frame, `A = R(−(θi + θz))` and
//! `u = A (tj − ti)`, the Jacobians are
//!
//! ```text
//! ∂e/∂xi = [ −A  (u_y, −u_x)ᵀ ]      ∂e/∂xj = [ A  0 ]
//!          [  0        −1     ]               [ 0  1 ]
//! ```

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::ids::VariableId;
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};

/// Where a constraint comes from. The optimizer treats all kinds alike; trimming and sparsification use it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ConstraintKind {
    /// A node matched against a submap of its own trajectory, while the submap was being built.
    NodeToSubmapIntra,
    /// A node matched against a submap by loop closure (possibly of another trajectory).
    NodeToSubmapInter,
    /// Relative motion between consecutive nodes from odometry.
    Odometry,
    /// Any other node-to-node measurement (e.g. imported from a g2o file, or made by sparsification).
    NodeToNode,
    /// A submap-to-submap measurement (e.g. made by sparsification).
    SubmapToSubmap,
}

/// A robust loss `ρ(s)` applied to the squared Mahalanobis norm `s = eᵀΩe` of one constraint.
///
/// The cost of a constraint is `ρ(s)`; for [`RobustLoss::Trivial`] it is `s`, the χ² term.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum RobustLoss {
    /// `ρ(s) = s`: plain least squares.
    Trivial,
    /// Huber: quadratic for `√s ≤ delta`, linear beyond: `ρ(s) = 2·delta·√s − delta²`.
    Huber {
        /// Threshold on the Mahalanobis distance `√s` (unitless, in standard deviations), > 0.
        delta: f64,
    },
    /// Cauchy: `ρ(s) = scale² · ln(1 + s / scale²)`.
    Cauchy {
        /// Scale on the Mahalanobis distance `√s` (unitless, in standard deviations), > 0.
        scale: f64,
    },
    /// Dynamic covariance scaling (Agarwal et al., ICRA 2013): the constraint's information is scaled by
    /// `w = min(1, 2Φ / (Φ + s))²`, which is the weight of `ρ(s) = s` for `s ≤ Φ` and
    /// `ρ(s) = 3Φ − 4Φ² / (Φ + s)` beyond. Redescending and bounded by `3Φ`: a constraint far from the
    /// rest of the graph (a false loop closure) costs at most `3Φ` and pulls with a weight falling as
    /// `1/s²`, where Huber's pull never fades. Quadratic below `Φ`, so a graph whose constraints all fit
    /// within `Φ` keeps its least-squares optimum.
    Dcs {
        /// `Φ`, on the squared Mahalanobis norm `s` (unitless), > 0.
        phi: f64,
    },
    /// Truncated least squares: `ρ(s) = min(s, threshold)`, weight 1 up to the threshold and exactly 0
    /// beyond. The least-squares term of a constraint that fits, a constant for one that does not: a
    /// rejected constraint keeps no pull at all (DCS's `(2Φ/s)²` never reaches 0), and a graph whose
    /// constraints all lie within the threshold at its least-squares optimum keeps that optimum exactly.
    /// Not differentiable at the threshold and flat beyond it, so it needs a start near the answer
    /// (see [`super::RobustOptimizer`]).
    TruncatedLeastSquares {
        /// The threshold `c̄²`, on the squared Mahalanobis norm `s` (unitless), > 0.
        threshold: f64,
    },
}

impl RobustLoss {
    /// The loss `ρ(s)` of a squared Mahalanobis norm `s ≥ 0`.
    pub fn rho(&self, s: f64) -> f64 {
        match *self {
            Self::Trivial => s,
            Self::Huber { delta } => {
                if s <= delta * delta {
                    s
                } else {
                    2.0 * delta * s.sqrt() - delta * delta
                }
            }
            Self::Cauchy { scale } => {
                let c2 = scale * scale;
                c2 * (s / c2).ln_1p()
            }
            Self::Dcs { phi } => {
                if s <= phi {
                    s
                } else {
                    3.0 * phi - 4.0 * phi * phi / (phi + s)
                }
            }
            Self::TruncatedLeastSquares { threshold } => s.min(threshold),
        }
    }

    /// The derivative `ρ'(s)`: the iteratively-reweighted-least-squares weight of the constraint.
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            Self::Trivial => 1.0,
            Self::Huber { delta } => {
                if s <= delta * delta {
                    1.0
                } else {
                    delta / s.sqrt()
                }
            }
            Self::Cauchy { scale } => 1.0 / (1.0 + s / (scale * scale)),
            Self::Dcs { phi } => {
                if s <= phi {
                    1.0
                } else {
                    let scale = 2.0 * phi / (phi + s);
                    scale * scale
                }
            }
            Self::TruncatedLeastSquares { threshold } => {
                if s <= threshold {
                    1.0
                } else {
                    0.0
                }
            }
        }
    }

    /// Whether the parameters are usable (finite and positive).
    pub fn is_valid(&self) -> bool {
        match *self {
            Self::Trivial => true,
            Self::Huber { delta: p }
            | Self::Cauchy { scale: p }
            | Self::Dcs { phi: p }
            | Self::TruncatedLeastSquares { threshold: p } => p.is_finite() && p > 0.0,
        }
    }
}

/// A measured relative pose between two variables, with its information matrix and robust loss.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Constraint {
    /// Where the measurement comes from.
    pub kind: ConstraintKind,
    /// The variable the measurement is expressed in.
    pub from: VariableId,
    /// The measured variable.
    pub to: VariableId,
    /// The measurement `from_from_to` (metres, radians).
    pub from_from_to: Rigid2,
    /// Information (inverse covariance) over the `(x, y, θ)` error; symmetric positive semi-definite,
    /// units 1/m², 1/(m·rad), 1/rad².
    pub information: Matrix3<f64>,
    /// The robust loss applied to `eᵀΩe`.
    pub loss: RobustLoss,
}

impl Constraint {
    /// The error `e` (see the module docs) for estimates `world_from_from` and `world_from_to`.
    pub fn error(&self, world_from_from: &Rigid2, world_from_to: &Rigid2) -> Vector3<f64> {
        let delta = self.from_from_to.inverse() * world_from_from.inverse() * world_from_to;
        Vector3::new(
            delta.translation.vector.x,
            delta.translation.vector.y,
            normalize_angle(
                world_from_to.theta() - world_from_from.theta() - self.from_from_to.theta(),
            ),
        )
    }

    /// The χ² term `eᵀΩe` (robust loss ignored).
    pub fn chi2(&self, world_from_from: &Rigid2, world_from_to: &Rigid2) -> f64 {
        let e = self.error(world_from_from, world_from_to);
        e.dot(&(self.information * e))
    }

    /// The robust cost `ρ(eᵀΩe)`.
    pub fn cost(&self, world_from_from: &Rigid2, world_from_to: &Rigid2) -> f64 {
        self.loss.rho(self.chi2(world_from_from, world_from_to))
    }
}

/// A constraint's measurement in the form the optimizer's inner loop wants.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PreparedMeasurement {
    /// `Rzᵀ · tz`.
    pub rotated_translation: Vector2<f64>,
    /// `θz` in radians.
    pub theta: f64,
    /// Ω.
    pub information: Matrix3<f64>,
    /// ρ.
    pub loss: RobustLoss,
}

impl PreparedMeasurement {
    pub(crate) fn new(constraint: &Constraint) -> Self {
        Self::from_parts(
            &constraint.from_from_to,
            constraint.information,
            constraint.loss,
        )
    }

    /// From a measurement `from_from_to`, its information and loss.
    pub(crate) fn from_parts(z: &Rigid2, information: Matrix3<f64>, loss: RobustLoss) -> Self {
        Self {
            rotated_translation: z.rotation.inverse() * z.translation.vector,
            theta: z.theta(),
            information,
            loss,
        }
    }

    /// The error `e` for `xi = (x, y, θ)` and `xj`.
    #[inline]
    pub(crate) fn error(&self, xi: &Vector3<f64>, xj: &Vector3<f64>) -> Vector3<f64> {
        let (s, c) = (-(xi.z + self.theta)).sin_cos();
        let dx = xj.x - xi.x;
        let dy = xj.y - xi.y;
        Vector3::new(
            c * dx - s * dy - self.rotated_translation.x,
            s * dx + c * dy - self.rotated_translation.y,
            normalize_angle(xj.z - xi.z - self.theta),
        )
    }

    /// The error and the Jacobians `∂e/∂xi`, `∂e/∂xj`.
    #[inline]
    pub(crate) fn linearize(
        &self,
        xi: &Vector3<f64>,
        xj: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>, Matrix3<f64>) {
        let (s, c) = (-(xi.z + self.theta)).sin_cos();
        let dx = xj.x - xi.x;
        let dy = xj.y - xi.y;
        let u = Vector2::new(c * dx - s * dy, s * dx + c * dy);
        let et = u - self.rotated_translation;
        let e = Vector3::new(et.x, et.y, normalize_angle(xj.z - xi.z - self.theta));
        #[rustfmt::skip]
        let ji = Matrix3::new(
            -c,  s,  u.y,
            -s, -c, -u.x,
            0.0, 0.0, -1.0,
        );
        #[rustfmt::skip]
        let jj = Matrix3::new(
            c,  -s, 0.0,
            s,   c, 0.0,
            0.0, 0.0, 1.0,
        );
        (e, ji, jj)
    }
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;

    use super::*;
    use crate::geometry::rigid2;
    use crate::pose_graph::ids::NodeId;

    fn constraint(z: Rigid2, information: Matrix3<f64>) -> Constraint {
        Constraint {
            kind: ConstraintKind::NodeToNode,
            from: VariableId::Node(NodeId {
                trajectory: 0,
                index: 0,
            }),
            to: VariableId::Node(NodeId {
                trajectory: 0,
                index: 1,
            }),
            from_from_to: z,
            information,
            loss: RobustLoss::Trivial,
        }
    }

    fn cases() -> Vec<(Vector3<f64>, Vector3<f64>, Rigid2)> {
        vec![
            (
                Vector3::new(0.3, -1.2, 0.4),
                Vector3::new(2.0, 0.5, -2.9),
                rigid2(1.1, 0.7, 2.8),
            ),
            (
                Vector3::new(-5.0, 3.0, 3.1),
                Vector3::new(-4.0, 2.0, -3.1),
                rigid2(0.9, -0.2, 0.05),
            ),
            (
                Vector3::new(10.0, 0.0, -1.5),
                Vector3::new(10.5, 1.0, 1.5),
                rigid2(-0.4, 0.3, -3.0),
            ),
        ]
    }

    #[test]
    fn fast_error_matches_rigid_error() {
        let cases = cases();
        assert!(cases.len() >= 3);
        for (xi, xj, z) in cases {
            let c = constraint(z, Matrix3::identity());
            let expected = c.error(&Rigid2::from_xytheta(&xi), &Rigid2::from_xytheta(&xj));
            let got = PreparedMeasurement::new(&c).error(&xi, &xj);
            assert_relative_eq!(got, expected, epsilon = 1e-12);
            assert!(expected.norm() > 0.1, "cases must have a non-trivial error");
        }
    }

    #[test]
    fn jacobians_match_central_differences() {
        let h = 1e-6;
        for (xi, xj, z) in cases() {
            let m = PreparedMeasurement::new(&constraint(z, Matrix3::identity()));
            let (e, ji, jj) = m.linearize(&xi, &xj);
            assert_relative_eq!(e, m.error(&xi, &xj), epsilon = 1e-15);
            for k in 0..3 {
                let mut step = Vector3::zeros();
                step[k] = h;
                let di = (m.error(&(xi + step), &xj) - m.error(&(xi - step), &xj)) / (2.0 * h);
                let dj = (m.error(&xi, &(xj + step)) - m.error(&xi, &(xj - step))) / (2.0 * h);
                assert_relative_eq!(ji.column(k).into_owned(), di, epsilon = 1e-7);
                assert_relative_eq!(jj.column(k).into_owned(), dj, epsilon = 1e-7);
            }
        }
    }

    #[test]
    fn chi2_uses_full_information() {
        let info = Matrix3::new(2.0, 0.5, 0.1, 0.5, 3.0, 0.2, 0.1, 0.2, 4.0);
        let c = constraint(rigid2(1.0, 0.0, 0.0), info);
        let e = c.error(&rigid2(0.0, 0.0, 0.0), &rigid2(1.5, 0.25, 0.1));
        assert_relative_eq!(e, Vector3::new(0.5, 0.25, 0.1), epsilon = 1e-12);
        let expected = (e.transpose() * info * e)[0];
        assert_relative_eq!(
            c.chi2(&rigid2(0.0, 0.0, 0.0), &rigid2(1.5, 0.25, 0.1)),
            expected,
            epsilon = 1e-12
        );
    }

    #[test]
    fn robust_losses_are_continuous_and_their_weight_is_the_derivative() {
        let losses = [
            RobustLoss::Trivial,
            RobustLoss::Huber { delta: 1.5 },
            RobustLoss::Cauchy { scale: 2.0 },
            RobustLoss::Dcs { phi: 1.0 },
        ];
        for loss in losses {
            for s in [0.1, 1.0, 2.2499, 2.2501, 9.0, 100.0] {
                let h = 1e-6;
                let numeric = (loss.rho(s + h) - loss.rho(s - h)) / (2.0 * h);
                assert_relative_eq!(loss.weight(s), numeric, epsilon = 1e-6);
                assert!(
                    loss.rho(s) <= s + 1e-12,
                    "a robust loss never exceeds the quadratic"
                );
            }
        }
        assert!(RobustLoss::Huber { delta: 1.0 }.rho(100.0) < 100.0 / 2.0);
        assert!(!RobustLoss::Cauchy { scale: 0.0 }.is_valid());
        // DCS is bounded by 3Φ and its weight is the square of Agarwal's scale.
        let dcs = RobustLoss::Dcs { phi: 1.0 };
        assert!(dcs.rho(1e9) < 3.0 && dcs.rho(1e9) > 2.99);
        assert!((dcs.weight(3.0) - 0.25).abs() < 1e-12);
    }

    #[test]
    fn truncated_least_squares_is_quadratic_then_flat_with_a_zero_weight() {
        let tls = RobustLoss::TruncatedLeastSquares { threshold: 25.0 };
        assert!(tls.is_valid());
        assert!(!RobustLoss::TruncatedLeastSquares { threshold: 0.0 }.is_valid());
        assert!(
            !RobustLoss::TruncatedLeastSquares {
                threshold: f64::NAN
            }
            .is_valid()
        );
        // Brute force over a grid: ρ(s) = min(s, c̄²), and the weight is its derivative away from the kink.
        let h = 1e-6;
        let mut below = 0;
        let mut beyond = 0;
        for k in 0..200 {
            let s = 0.37 * f64::from(k);
            assert_relative_eq!(tls.rho(s), if s < 25.0 { s } else { 25.0 }, epsilon = 1e-12);
            if (s - 25.0).abs() > 2.0 * h {
                let numeric = (tls.rho(s + h) - tls.rho(s - h)) / (2.0 * h);
                assert_relative_eq!(tls.weight(s), numeric, epsilon = 1e-6);
                if s < 25.0 {
                    below += 1;
                } else {
                    beyond += 1;
                }
            }
        }
        assert!(
            below > 10 && beyond > 10,
            "both sides of the threshold are checked"
        );
        // Exactly 0 beyond: a rejected constraint does not pull at all.
        assert_eq!(tls.weight(25.0 + 1e-9).to_bits(), 0.0_f64.to_bits());
        assert_eq!(tls.weight(25.0).to_bits(), 1.0_f64.to_bits());
        assert_eq!(tls.rho(1e12).to_bits(), 25.0_f64.to_bits());
    }
}
