//! Planar rigid transforms (SE(2)) and angle helpers.
//!
//! We use [`nalgebra::Isometry2<f64>`] as the SE(2) type under the alias [`Rigid2`]; this module adds the
//! conversions every SLAM component needs (`(x, y, θ)` vectors, the exponential and logarithm maps).

mod se2;

pub use se2::{Rigid2, Rigid2Ext, normalize_angle, rigid2, se2_exp, se2_log, yaw_from_quaternion};
