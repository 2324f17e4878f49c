//! Helpers shared by the storage crate's integration tests (each test file is its own binary and
//! includes this module with `mod support;`).

use storage::{RecordKind, WriteBatch};
use test_support::noise;

/// Version `version` of site `"site"`'s log as the server writes it: one trajectory entry of `len` bytes
/// of noise drawn from `state` (advanced), and the map version bumped.
pub fn site_log_version(state: &mut u64, version: u64, len: usize) -> WriteBatch {
    let mut batch = WriteBatch::new("site");
    batch
        .put(RecordKind::Trajectory, version, noise(state, len))
        .bump_map_version();
    batch
}
