//! A real size-limited filesystem for disk-full tests: a tmpfs mounted on a temporary directory, and a
//! filler that fills it.

use std::io::Write as _;
use std::path::Path;
use std::process::Command;

/// Whether the tmpfs tests were asked for (`EVERMAP_TMPFS_TESTS` set; they need root); says so when not.
pub fn tmpfs_tests_enabled() -> bool {
    let enabled = std::env::var_os("EVERMAP_TMPFS_TESTS").is_some();
    if !enabled {
        eprintln!("skipped: set EVERMAP_TMPFS_TESTS=1 to run it (needs root to mount a tmpfs)");
    }
    enabled
}

/// A tmpfs mounted on a temporary directory, unmounted on drop. Mounting needs root
/// (`CAP_SYS_ADMIN`).
pub struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    /// Mounts a tmpfs of `mib` MiB; panics if it cannot (the tests that use it run only when asked to,
    /// and then fail rather than skip).
    pub fn mount(mib: u64) -> Self {
        let dir = tempfile::tempdir().expect("a temporary directory");
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mib}m"), "tmpfs"])
            .arg(dir.path())
            .status()
            .expect("run mount");
        assert!(
            status.success(),
            "cannot mount a tmpfs (needs root): {status}"
        );
        Self { dir }
    }

    /// Where it is mounted.
    pub fn path(&self) -> &Path {
        self.dir.path()
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.dir.path()).status();
    }
}

/// Fills the filesystem with `path` until it is full, writing at most `mib` MiB and a little more (the
/// size of the filesystem); panics if the filler never hits the size limit.
pub fn fill(path: &Path, mib: u64) {
    let mut file = std::fs::File::create(path).expect("create the filler");
    let chunk = vec![0_u8; 64 << 10];
    for _ in 0..(mib << 4) + 16 {
        if file
            .write_all(&chunk)
            .and_then(|()| file.sync_all())
            .is_err()
        {
            return;
        }
    }
    panic!("the filler never hit the size limit");
}
