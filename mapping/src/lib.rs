//! # mapping — evermap's pure algorithm core
//!
//! Everything that turns laser scans, odometry and IMU readings into submaps, constraints and an optimized
//! multi-session pose graph lives here, and nothing else does: this crate performs no I/O, reads no clock,
//! spawns no thread and never logs at INFO or above. Parsers take `impl Read` or byte slices; long-running
//! algorithms return values (or events) and let the caller (`robot-agent`, `server`) decide where they go.
//!
//! Frames are named `target_from_source`: `world_from_submap * submap_from_scan = world_from_scan`.
//! Units are SI: metres, radians, seconds.

pub mod geometry;
pub mod global_slam;
pub mod grid;
pub mod io;
pub mod lifelong;
pub mod local_slam;
pub mod map_image;
pub mod metrics;
pub mod pose_graph;
pub mod scan_matching;
pub mod sensor;
pub mod sparsification;
