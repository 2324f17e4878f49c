//! SE(2) helpers on top of nalgebra.
//!
//! Math: a pose `T = (R(θ), t)` acts on points as `p ↦ R p + t`. The tangent vector is `ξ = (ρ, θ)` with
//! `exp(ξ) = (R(θ), V(θ) ρ)`, `V(θ) = [[sin θ/θ, −(1−cos θ)/θ], [(1−cos θ)/θ, sin θ/θ]]`.

use nalgebra::{Isometry2, Matrix2, Vector2, Vector3};

/// A rigid transform in the plane, `target_from_source`.
pub type Rigid2 = Isometry2<f64>;

/// Builds `Rigid2` from a translation in metres and a rotation in radians.
pub fn rigid2(x: f64, y: f64, theta: f64) -> Rigid2 {
    Isometry2::new(Vector2::new(x, y), theta)
}

/// The yaw (rad, about z) of the unit quaternion `[x, y, z, w]`: a 3-D orientation projected to the plane
/// (ROS messages, TUM files).
pub fn yaw_from_quaternion([x, y, z, w]: [f64; 4]) -> f64 {
    (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z))
}

/// Wraps an angle to `(−π, π]`.
pub fn normalize_angle(angle: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut a = angle % two_pi;
    if a <= -std::f64::consts::PI {
        a += two_pi;
    } else if a > std::f64::consts::PI {
        a -= two_pi;
    }
    a
}

/// Convenience accessors for [`Rigid2`].
pub trait Rigid2Ext {
    /// Translation x in metres.
    fn x(&self) -> f64;
    /// Translation y in metres.
    fn y(&self) -> f64;
    /// Rotation angle in radians, in `(−π, π]`.
    fn theta(&self) -> f64;
    /// `(x, y, θ)`.
    fn to_xytheta(&self) -> Vector3<f64>;
    /// Inverse of [`Rigid2Ext::to_xytheta`].
    fn from_xytheta(v: &Vector3<f64>) -> Self;
}

impl Rigid2Ext for Rigid2 {
    fn x(&self) -> f64 {
        self.translation.vector.x
    }
    fn y(&self) -> f64 {
        self.translation.vector.y
    }
    fn theta(&self) -> f64 {
        self.rotation.angle()
    }
    fn to_xytheta(&self) -> Vector3<f64> {
        Vector3::new(self.x(), self.y(), self.theta())
    }
    fn from_xytheta(v: &Vector3<f64>) -> Self {
        rigid2(v.x, v.y, v.z)
    }
}

fn v_matrix(theta: f64) -> Matrix2<f64> {
    let (s, c) = theta.sin_cos();
    let (a, b) = if theta.abs() < 1e-6 {
        // Taylor expansions of sin θ/θ and (1−cos θ)/θ.
        (
            1.0 - theta * theta / 6.0,
            theta / 2.0 - theta.powi(3) / 24.0,
        )
    } else {
        (s / theta, (1.0 - c) / theta)
    };
    Matrix2::new(a, -b, b, a)
}

/// The SE(2) exponential map of the tangent vector `(ρx, ρy, θ)`.
pub fn se2_exp(xi: &Vector3<f64>) -> Rigid2 {
    let t = v_matrix(xi.z) * Vector2::new(xi.x, xi.y);
    Isometry2::new(t, xi.z)
}

/// The SE(2) logarithm map, inverse of [`se2_exp`] for `θ ∈ (−π, π]`.
pub fn se2_log(pose: &Rigid2) -> Vector3<f64> {
    let theta = pose.theta();
    let v = v_matrix(theta);
    // V is a scaled rotation, invertible for |θ| < 2π.
    let rho = v.try_inverse().unwrap_or_else(Matrix2::identity) * pose.translation.vector;
    Vector3::new(rho.x, rho.y, theta)
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;
    use proptest::prelude::*;

    use super::*;

    fn pose() -> impl Strategy<Value = Rigid2> {
        (-100.0..100.0f64, -100.0..100.0f64, -3.1..3.1f64).prop_map(|(x, y, t)| rigid2(x, y, t))
    }

    proptest! {
        #[test]
        fn inverse_is_identity(a in pose()) {
            assert_relative_eq!(a * a.inverse(), Rigid2::identity(), epsilon = 1e-9);
        }

        #[test]
        fn composition_is_associative(a in pose(), b in pose(), c in pose()) {
            assert_relative_eq!((a * b) * c, a * (b * c), epsilon = 1e-7);
        }

        #[test]
        fn exp_log_round_trip(a in pose()) {
            assert_relative_eq!(se2_exp(&se2_log(&a)), a, epsilon = 1e-7);
        }

        #[test]
        fn xytheta_round_trip(a in pose()) {
            assert_relative_eq!(Rigid2::from_xytheta(&a.to_xytheta()), a, epsilon = 1e-12);
        }

        #[test]
        fn normalized_angle_is_in_range_and_equivalent(a in -100.0..100.0f64) {
            let n = normalize_angle(a);
            prop_assert!(n > -std::f64::consts::PI && n <= std::f64::consts::PI);
            prop_assert!(((a - n) / std::f64::consts::TAU - ((a - n) / std::f64::consts::TAU).round()).abs() < 1e-9);
        }
    }

    #[test]
    fn exp_of_small_angle_matches_first_order() {
        let xi = Vector3::new(1.0, 2.0, 1e-9);
        let p = se2_exp(&xi);
        assert_relative_eq!(p.translation.vector, Vector2::new(1.0, 2.0), epsilon = 1e-8);
    }
}
