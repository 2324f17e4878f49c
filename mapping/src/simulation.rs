//! A seeded simulator of a changing supermarket, for the lifelong experiments (the paper's month in a
//! store, whose data are not public).
//!
//! * [`Store`] lays out a store of [`StoreOptions`] (default 120 m × 90 m = 10,800 m²): outer walls with
//!   doors, fixed shelf frames in blocks separated by cross aisles, pillars, and movable items — goods on
//!   every shelf module (protruding 0.1–0.3 m or absent), pallets in aisles, displays and promotion stands,
//!   doors open or closed. Each movable item changes state between sessions with a fixed probability (a
//!   seeded Markov chain per item), so the layout of day `k` is reproducible without simulating days
//!   `0..k` of sensor data. Pedestrians and carts walk the aisles during a session.
//! * [`Store::session`] drives the robot along a cleaning route — session 0 sweeps every aisle (the mapping
//!   run); later sessions start in a random aisle and clean for [`SessionOptions::max_duration_s`] — and
//!   returns the sensor events a recording would hold (SICK TiM571-like scans, drifting wheel odometry,
//!   a biased gyro) plus ground truth.
//!
//! Pure and deterministic: the same options and seed give the same sessions bit for bit.

mod ray_caster;
mod session_options;
mod simulated_session;
mod store;
mod store_options;

pub use ray_caster::{Aabb, RayCaster};
pub use session_options::SessionOptions;
pub use simulated_session::SimulatedSession;
pub use store::{ItemKind, Store, TruthOccupancy};
pub use store_options::StoreOptions;

/// Errors of the simulator.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum SimulationError {
    /// An option is out of range.
    #[error("invalid simulation option `{field}`: {reason}")]
    InvalidOption {
        /// The option.
        field: &'static str,
        /// What it must satisfy.
        reason: String,
    },
    /// The route has no motion (a degenerate store).
    #[error("the simulated route is empty")]
    EmptyRoute,
}

#[cfg(test)]
mod tests;
