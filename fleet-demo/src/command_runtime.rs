//! What the one-process commands (`demo`, `load`) share: a fresh output folder and a tokio runtime.

use std::future::Future;
use std::path::Path;

use anyhow::Context as _;

/// Deletes `out` if it exists and creates it again, empty.
pub fn recreate_dir(out: &Path) -> anyhow::Result<()> {
    if out.exists() {
        eprintln!("removing the previous output in {}", out.display());
        std::fs::remove_dir_all(out).with_context(|| format!("cannot remove {}", out.display()))?;
    }
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))
}

/// Runs `job` to completion on a new multi-threaded tokio runtime.
pub fn block_on<T>(job: impl Future<Output = anyhow::Result<T>>) -> anyhow::Result<T> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?
        .block_on(job)
}
