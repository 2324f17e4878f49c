//! # tests — evermap's end-to-end tests
//!
//! Shared helpers for the integration tests under `tests/tests/`.

use std::path::PathBuf;

/// The shared data sets folder, `../shared/datasets` next to the repository root.
pub fn datasets_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/datasets")
}
