//! Two Gaussian constraints on the same pair of variables, summed into one.
//!
//! For a constraint `i → j` with measurement `z = (t_z, θ_z)` the error (see [`Constraint`]) is
//! `e = A_z (r − z)` with `r = (R(−θi)(tj − ti), θj − θi)` the relative pose in `i`'s frame and
//! `A_z = diag(R(−θ_z), 1)`: affine in `r`. Two plain least-squares constraints on the same ordered pair
//! therefore cost `Σ_k (r − z_k)ᵀ M_k (r − z_k)` with `M_k = A_kᵀ Ω_k A_k`, which is, up to a constant,
//! `(r − z*)ᵀ M (r − z*)` with `M = Σ M_k` and `z* = M⁻¹ Σ M_k z_k`: one constraint with measurement `z*`
//! and information `A_{z*} M A_{z*}ᵀ`. The merge is exact (the optimizer sees the same cost surface,
//! shifted by a constant), except that angles are summed on the branch nearest the first measurement.
//! A constraint of the opposite orientation `j → i` is first turned around to first order at its own
//! measurement.
//!
//! The Chow–Liu trees of successive trims put edges on pairs that already carry one; merging keeps the
//! graph's size to one constraint per pair (issue 34).

use nalgebra::{Matrix3, Vector3};

use super::constraint::{Constraint, RobustLoss};
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle, rigid2};

/// `diag(R(−θ), 1)`: the error's rotation for a measurement at angle `θ`.
fn error_rotation(theta: f64) -> Matrix3<f64> {
    let (s, c) = theta.sin_cos();
    #[rustfmt::skip]
    let a = Matrix3::new(
        c,   s,   0.0,
        -s,  c,   0.0,
        0.0, 0.0, 1.0,
    );
    a
}

/// The Jacobian of the inversion `r ↦ r⁻¹` (`t' = −R(−θ) t`, `θ' = −θ`) at `r = z`. The inversion is its
/// own inverse, so the Jacobian at `z⁻¹` is this one's inverse.
fn inversion_jacobian(z: &Rigid2) -> Matrix3<f64> {
    let (tx, ty) = (z.x(), z.y());
    let (s, c) = z.theta().sin_cos();
    #[rustfmt::skip]
    let j = Matrix3::new(
        -c, -s, s * tx - c * ty,
        s,  -c, c * tx + s * ty,
        0.0, 0.0, -1.0,
    );
    j
}

/// The same measurement seen from the other end, `j → i`, with its information carried over to first
/// order at the measurement.
fn reversed(constraint: &Constraint) -> Constraint {
    let z = constraint.from_from_to;
    let inverse = z.inverse();
    // e' = A' (r' − z') ≈ A' J (r − z); want e'ᵀ Ω' e' = (r − z)ᵀ M (r − z) with M = Aᵀ Ω A, so
    // Ω' = K⁻ᵀ M K⁻¹ with K = A' J, K⁻¹ = J(z⁻¹) A'ᵀ.
    let a = error_rotation(z.theta());
    let m = a.transpose() * constraint.information * a;
    let k_inverse = inversion_jacobian(&inverse) * error_rotation(inverse.theta()).transpose();
    let information = k_inverse.transpose() * m * k_inverse;
    Constraint {
        kind: constraint.kind,
        from: constraint.to,
        to: constraint.from,
        from_from_to: inverse,
        information: 0.5 * (information + information.transpose()),
        loss: constraint.loss,
    }
}

/// `existing` and `added` summed into one constraint on `existing`'s pair and orientation, keeping its
/// kind. `None` if they are not on the same pair of variables, if either has a robust loss (a robust
/// loss of a sum is not the sum of robust losses), or if the summed information is singular.
pub(crate) fn merged(existing: &Constraint, added: &Constraint) -> Option<Constraint> {
    if existing.loss != RobustLoss::Trivial || added.loss != RobustLoss::Trivial {
        return None;
    }
    let added = if added.from == existing.from && added.to == existing.to {
        added.clone()
    } else if added.from == existing.to && added.to == existing.from {
        reversed(added)
    } else {
        return None;
    };
    let z0 = existing.from_from_to;
    let vector = |z: &Rigid2| {
        // On the branch nearest the first measurement's angle.
        let theta = z0.theta() + normalize_angle(z.theta() - z0.theta());
        Vector3::new(z.x(), z.y(), theta)
    };
    let m0 = {
        let a = error_rotation(z0.theta());
        a.transpose() * existing.information * a
    };
    let m1 = {
        let a = error_rotation(added.from_from_to.theta());
        a.transpose() * added.information * a
    };
    let m = m0 + m1;
    let mean = m
        .cholesky()?
        .solve(&(m0 * vector(&z0) + m1 * vector(&added.from_from_to)));
    let a = error_rotation(mean.z);
    let information = a * m * a.transpose();
    Some(Constraint {
        kind: existing.kind,
        from: existing.from,
        to: existing.to,
        from_from_to: rigid2(mean.x, mean.y, normalize_angle(mean.z)),
        information: 0.5 * (information + information.transpose()),
        loss: RobustLoss::Trivial,
    })
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;

    use super::*;
    use crate::pose_graph::{ConstraintKind, NodeId, SubmapId, VariableId};

    fn ends() -> (VariableId, VariableId) {
        (
            VariableId::Submap(SubmapId {
                trajectory: 0,
                index: 3,
            }),
            VariableId::Node(NodeId {
                trajectory: 1,
                index: 7,
            }),
        )
    }

    fn constraint(z: Rigid2, information: Matrix3<f64>) -> Constraint {
        let (from, to) = ends();
        Constraint {
            kind: ConstraintKind::NodeToSubmapInter,
            from,
            to,
            from_from_to: z,
            information,
            loss: RobustLoss::Trivial,
        }
    }

    fn spd(a: f64, b: f64, c: f64, off: f64) -> Matrix3<f64> {
        let l = Matrix3::new(a, 0.0, 0.0, off, b, 0.0, 0.3 * off, -off, c);
        l * l.transpose()
    }

    fn poses() -> Vec<(Rigid2, Rigid2)> {
        vec![
            (rigid2(0.0, 0.0, 0.0), rigid2(1.0, 2.0, 0.7)),
            (rigid2(3.0, -1.0, 2.9), rigid2(1.2, 2.5, -3.0)),
            (rigid2(-5.0, 4.0, -1.2), rigid2(-3.1, 6.2, -0.4)),
            (rigid2(0.4, 0.2, 0.3), rigid2(1.5, 2.0, 1.1)),
        ]
    }

    #[test]
    fn merged_costs_the_sum_up_to_a_constant_everywhere() {
        let first = constraint(rigid2(1.1, 2.0, 0.75), spd(3.0, 2.0, 5.0, 0.4));
        let second = constraint(rigid2(0.9, 2.2, 0.6), spd(1.0, 4.0, 2.0, -0.7));
        let merged = merged(&first, &second).expect("same pair, plain least squares");
        let offsets: Vec<f64> = poses()
            .iter()
            .map(|(i, j)| first.chi2(i, j) + second.chi2(i, j) - merged.chi2(i, j))
            .collect();
        for offset in &offsets {
            assert_relative_eq!(*offset, offsets[0], epsilon = 1e-9);
        }
        assert!(
            offsets[0] >= -1e-12,
            "the constant is a residual: {}",
            offsets[0]
        );
    }

    #[test]
    fn merging_a_constraint_with_itself_doubles_its_information() {
        let first = constraint(rigid2(-0.4, 1.3, -2.2), spd(2.0, 3.0, 4.0, 0.2));
        let merged = merged(&first, &first).unwrap();
        assert_relative_eq!(merged.from_from_to, first.from_from_to, epsilon = 1e-12);
        assert_relative_eq!(merged.information, 2.0 * first.information, epsilon = 1e-9);
    }

    #[test]
    fn a_reversed_constraint_is_merged_to_first_order() {
        let first = constraint(rigid2(1.1, 2.0, 0.75), spd(3.0, 2.0, 5.0, 0.4));
        let second = constraint(rigid2(1.12, 1.98, 0.76), spd(1.0, 4.0, 2.0, -0.7));
        let turned = reversed(&second);
        assert_eq!((turned.from, turned.to), (second.to, second.from));
        // Near the measurement the turned constraint costs what the original does.
        let i = rigid2(0.3, -0.2, 0.1);
        let j = i * rigid2(1.125, 1.985, 0.765);
        assert_relative_eq!(
            turned.chi2(&j, &i),
            second.chi2(&i, &j),
            max_relative = 1e-2
        );
        let direct = merged(&first, &second).unwrap();
        let via_reversed = merged(&first, &turned).unwrap();
        assert_relative_eq!(
            via_reversed.from_from_to,
            direct.from_from_to,
            epsilon = 1e-6
        );
        assert_relative_eq!(
            via_reversed.information,
            direct.information,
            max_relative = 1e-3
        );
    }

    #[test]
    fn robust_or_unrelated_constraints_are_not_merged() {
        let first = constraint(rigid2(1.0, 2.0, 0.7), Matrix3::identity());
        let mut robust = first.clone();
        robust.loss = RobustLoss::Huber { delta: 1.0 };
        assert!(merged(&first, &robust).is_none());
        assert!(merged(&robust, &first).is_none());
        let mut elsewhere = first.clone();
        elsewhere.to = VariableId::Node(NodeId {
            trajectory: 1,
            index: 8,
        });
        assert!(merged(&first, &elsewhere).is_none());
    }
}
