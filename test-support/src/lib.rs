//! # test-support — helpers the evermap test suites share
//!
//! The few helpers that integration and unit tests across the workspace need alike, written once:
//! [`datasets_dir`] (the shared recordings and pose graphs), [`free_port`] (a loopback port for
//! endpoints that cannot take port 0), [`noise`] (incompressible values), [`Tmpfs`] with [`fill`] (a
//! real full disk) and [`files_in_site_dirs`] (what a store keeps on disk per site). No workspace crate is a dependency, so any crate can take this one as a
//! dev-dependency; its one dependency is `tempfile`, small and already among the workspace's
//! dev-dependencies.

use std::path::{Path, PathBuf};

mod tmpfs;

pub use tmpfs::{Tmpfs, fill, tmpfs_tests_enabled};

/// The shared data sets folder, `../shared/datasets` next to the repository root. Found by walking up from
/// this crate, so that it works from the main checkout (`/work/main`) and from worktrees one level deeper
/// (`/work/wt/<name>`); falls back to the main checkout's relative path. Every workspace crate sits at this
/// crate's depth, so the walk finds the same folder for all of them.
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

/// `len` bytes of xorshift noise from `state` (advanced): incompressible test values, the same for the
/// same seed.
pub fn noise(state: &mut u64, len: usize) -> Vec<u8> {
    (0..len)
        .map(|_| {
            *state ^= *state << 13;
            *state ^= *state >> 7;
            *state ^= *state << 17;
            state.to_le_bytes()[0]
        })
        .collect()
}

/// The files in each directory under `root` (one per site, as the store keeps checkpoints and value
/// files), as `site/file`, sorted; empty when `root` does not exist.
pub fn files_in_site_dirs(root: &Path) -> Vec<String> {
    let mut names = Vec::new();
    let Ok(sites) = std::fs::read_dir(root) else {
        return names;
    };
    for site in sites {
        let site = site.expect("a site directory entry");
        for file in std::fs::read_dir(site.path()).expect("a site directory") {
            names.push(format!(
                "{}/{}",
                site.file_name().to_string_lossy(),
                file.expect("a file entry").file_name().to_string_lossy()
            ));
        }
    }
    names.sort();
    names
}
