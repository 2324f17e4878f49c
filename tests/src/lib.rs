//! # tests — evermap's end-to-end tests
//!
//! Shared helpers for the integration tests under `tests/tests/` ([`CuttableLink`], [`free_port`], [`OneRobotSite`]), and the decoder fuzz harness ([`fuzz`],
//! run by the `evermap-fuzz` binary and by `tests/tests/fuzz_decoders.rs`).

use std::path::PathBuf;

mod cuttable_link;
pub mod fuzz;
mod one_robot_site;

pub use cuttable_link::CuttableLink;
pub use one_robot_site::{NodePoses, OneRobotSite};

/// The shared data sets folder, `../shared/datasets` next to the repository root. Found by walking up from
/// this crate, so that it works from the main checkout (`/work/main`) and from worktrees one level deeper
/// (`/work/wt/<name>`); falls back to the main checkout's relative path.
pub fn datasets_dir() -> PathBuf {
    let manifest = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    manifest
        .ancestors()
        .skip(1)
        .map(|dir| dir.join("shared/datasets"))
        .find(|dir| dir.is_dir())
        .unwrap_or_else(|| manifest.join("../../shared/datasets"))
}

/// A loopback TCP port free right now (bound, then released), for zenoh endpoints that cannot take
/// port 0. Another process could take it in between; tests on a shared machine prefer that small risk
/// to fixed ports that collide.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map_or(0, |a| a.port())
}
