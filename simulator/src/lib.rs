//! # simulator — a seeded changing supermarket
//!
//! A seeded simulator of a changing supermarket, for the lifelong experiments (the paper's month in a
//! store, whose data are not public), the fleet demo and the load benchmark. Its own crate, over the
//! `mapping` core: the shells that simulate (`evermap-demo`) link it, the server does not.
//!
//! * [`Store`] lays out one of two worlds ([`WorldOptions`]), both 120 m × 90 m = 10,800 m² by default:
//!   - `store` ([`StoreOptions`], the default): a supermarket after typical published floor plans —
//!     checkouts, entrance and a service desk at the front, refrigerated and frozen cases along the walls,
//!     service counters at the back, produce islands at the entrance side, gondola runs of different
//!     lengths with end caps in banks, structural columns on a grid (see [`store_layout`] for the figures
//!     and what they are based on);
//!   - `aisles` ([`AislesOptions`]): the adversarial case, blocks of identical shelf rows with pillars at
//!     some row ends, where from inside an aisle no method can tell which aisle it is in.
//!
//!   Both have fixed structure that never moves and movable items — goods on every shelf section
//!   (protruding in 0.1 m steps or absent), pallets, displays and promotions, cart rows, doors open or
//!   closed. Each movable item changes state between sessions with a fixed probability (a seeded Markov
//!   chain per item), so the layout of day `k` is reproducible without simulating days `0..k` of sensor
//!   data. Pedestrians and carts walk the aisles during a session.
//! * [`Store::session`] drives the robot along a cleaning route — session 0 drives the whole route once
//!   (the mapping run); later sessions start at a random place on it and clean for
//!   [`SessionOptions::max_duration_s`] — and returns the sensor events a recording would hold (SICK
//!   TiM571-like scans, drifting wheel odometry, a biased gyro) plus ground truth.
//!
//! * [`layout_to_rgb`]: a day's layout as a picture (structure, what changes, the route).
//! * [`World`]: the worlds by name (`--world store|aisles`), at the benchmark's size or the demo's.
//! * [`testing`] (feature `testing`): real simulated sessions fed to a lifelong map, resumable at any
//!   node, for the checkpoint round-trip tests of `mapping` and `proto`.
//!
//! Pure and deterministic: the same options and seed give the same sessions bit for bit. No I/O, no
//! clocks, no threads, as in `mapping`.

mod aisles;
mod aisles_options;
mod layout_image;
mod ray_caster;
mod session_options;
mod simulated_session;
mod store;
pub mod store_layout;
mod store_options;
mod world;
mod world_options;

pub use aisles_options::AislesOptions;
pub use layout_image::layout_to_rgb;
pub use ray_caster::{Aabb, RayCaster};
pub use session_options::SessionOptions;
pub use simulated_session::SimulatedSession;
pub use store::{ItemKind, Store, TruthOccupancy};
pub use store_options::StoreOptions;
pub use world::World;
pub use world_options::WorldOptions;

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

#[cfg(any(test, feature = "testing"))]
pub mod testing;
#[cfg(test)]
mod tests;
