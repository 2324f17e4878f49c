//! # tests — evermap's end-to-end tests
//!
//! Shared helpers for the integration tests under `tests/tests/` ([`CuttableLink`], [`free_port`], [`OneRobotSite`],
//! [`zenoh_router`]), and the decoder fuzz harness ([`fuzz`],
//! run by the `evermap-fuzz` binary and by `tests/tests/fuzz_decoders.rs`).

mod cuttable_link;
pub mod fuzz;
mod one_robot_site;
mod zenoh_router;

pub use cuttable_link::CuttableLink;
pub use one_robot_site::{NodePoses, OneRobotSite};
/// The shared data sets folder and a free loopback port, from the workspace's `test-support` crate
/// (re-exported so that the tests here keep importing them from `tests`).
pub use test_support::{datasets_dir, free_port};
pub use zenoh_router::zenoh_router;
