//! Where a store keeps the bytes of its site checkpoints: files of their own, apart from the key-value
//! database, which holds only each checkpoint's index entry (`checkpoint_entry`).
//!
//! Why: a checkpoint is a site's whole state, 17–28 MB for a 16-session site, rewritten every few hundred
//! map versions. sled 0.34 keeps the blob and segment space of overwritten and removed large values for a
//! long time (measured: a 16-session site's store grew to 1.6 GB with checkpoints, 22 MB without), so
//! checkpoints stored as sled values defeat their purpose. A file is freed the moment it is deleted.
//!
//! Layout, under the store's checkpoint directory ([`crate::SledStore`]: `<database dir>/checkpoints`):
//!
//! ```text
//! <site dir>/<log index, 20 decimal digits>-<CRC32, 8 hex digits>.ckpt
//! ```
//!
//! The site directory is the site id with every byte other than `A-Z a-z 0-9 - _` written `%XX` (so no
//! site is `.` or `..` or holds a `/`), e.g. `store-1`, `Halle%207`; an id whose escaped form is longer
//! than [`MAX_SITE_DIR_BYTES`] is cut to a prefix and `~` and the FNV-1a-64 hash of the whole id (`~` is
//! never in an escaped id, so the two forms cannot meet). The CRC in the name makes a checkpoint rewritten
//! at the same log index with other bytes a new file, so the file an index entry names is never replaced
//! under it.
//!
//! Implementations: `CheckpointDir` (files on disk, written crash-safely) and `MemCheckpointFiles` (the
//! in-memory store's, for tests).

mod checkpoint_dir;
mod mem_checkpoint_files;

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::{MutexGuard, PoisonError, RwLock};

pub(crate) use checkpoint_dir::CheckpointDir;
pub(crate) use mem_checkpoint_files::MemCheckpointFiles;

use crate::Result;

/// Longest site directory name, in bytes (file systems allow 255).
pub(crate) const MAX_SITE_DIR_BYTES: usize = 200;

/// A step of storing or removing a checkpoint's file, reported to the hook set with
/// [`crate::SledStore::on_checkpoint_step`] (crash tests stop the process there).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CheckpointStep {
    /// The checkpoint's file is durable (written, fsynced, renamed, its directory fsynced); its index
    /// entry is not stored yet. A crash here leaves an orphan file, removed when the store opens.
    FileDurable {
        /// The log index the checkpoint covers.
        log_index: u64,
    },
    /// The checkpoint's index entry was removed durably (by a compaction, or replaced by a rewrite at the
    /// same log index); its file is not deleted yet. A crash here leaves an orphan file, removed when the
    /// store opens.
    IndexRemoved {
        /// The log index the removed checkpoint covered.
        log_index: u64,
    },
}

/// The hook [`CheckpointFiles::step`] calls.
type Hook = Box<dyn Fn(CheckpointStep) + Send + Sync>;

/// A settable [`CheckpointStep`] hook, shared by the implementations.
#[derive(Default)]
pub(crate) struct StepHook(RwLock<Option<Hook>>);

impl StepHook {
    /// Sets the hook (replacing any).
    pub(crate) fn set(&self, hook: Hook) {
        *self.0.write().unwrap_or_else(PoisonError::into_inner) = Some(hook);
    }

    /// Calls the hook, if set.
    pub(crate) fn call(&self, step: CheckpointStep) {
        if let Some(hook) = self
            .0
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
        {
            hook(step);
        }
    }
}

impl std::fmt::Debug for StepHook {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let set = self
            .0
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .is_some();
        f.debug_tuple("StepHook").field(&set).finish()
    }
}

/// Checkpoint files addressed by their name relative to the checkpoint directory (`<site dir>/<file>`).
/// `site` arguments only name the site in errors. Thread-safe.
pub(crate) trait CheckpointFiles: Send + Sync {
    /// Writes `bytes` as the file `name`, replacing one of that name: when it returns, the file and its
    /// name are durable. On failure nothing of it is left (no partial file under `name`).
    fn write(&self, site: &str, name: &str, bytes: &[u8]) -> Result<()>;

    /// The file's bytes, `None` if it does not exist.
    fn read(&self, site: &str, name: &str) -> Result<Option<Vec<u8>>>;

    /// Deletes the file (absent: not an error). Not made durable: a deletion a crash undoes leaves an
    /// orphan, removed by [`CheckpointFiles::retain`] at the next open.
    fn remove(&self, site: &str, name: &str) -> Result<()>;

    /// Deletes the site directory `dir` and everything in it (absent: not an error).
    fn remove_dir(&self, site: &str, dir: &str) -> Result<()>;

    /// Deletes every file whose name is not in `keep` (temporary files of interrupted writes included)
    /// and the directories left empty; returns how many files it deleted.
    fn retain(&self, keep: &BTreeSet<String>) -> Result<u64>;

    /// Bytes of all the files.
    fn total_bytes(&self) -> Result<u64>;

    /// The file's full path, for messages.
    fn path(&self, name: &str) -> PathBuf;

    /// Held while a file is written until its index entry is stored, and while a file is checked
    /// unreferenced and deleted, so that no deletion removes a file an entry has just come to name.
    fn lock(&self) -> MutexGuard<'_, ()>;

    /// Reports a step to the hook, if one is set.
    fn step(&self, step: CheckpointStep);
}

/// The directory of a site's checkpoint files (see the module docs).
pub(crate) fn site_dir(site: &str) -> String {
    let mut dir = String::with_capacity(site.len());
    for byte in site.bytes() {
        if byte.is_ascii_alphanumeric() || byte == b'-' || byte == b'_' {
            dir.push(char::from(byte));
        } else {
            let _ = write!(dir, "%{byte:02X}");
        }
    }
    if dir.len() <= MAX_SITE_DIR_BYTES {
        return dir;
    }
    // Cut before an escape, never inside one.
    let mut cut = MAX_SITE_DIR_BYTES - 20;
    while dir.as_bytes()[cut - 1] == b'%' || dir.as_bytes()[cut - 2] == b'%' {
        cut -= 1;
    }
    dir.truncate(cut);
    let _ = write!(dir, "~{:016x}", fnv1a64(site.as_bytes()));
    dir
}

/// The file name of a site's checkpoint at `log_index` whose checksum is `crc` (relative to the checkpoint
/// directory).
pub(crate) fn file_name(site: &str, log_index: u64, crc: u32) -> String {
    format!("{}/{log_index:020}-{crc:08x}.ckpt", site_dir(site))
}

/// Whether `name` is a file name [`file_name`] makes: `<dir>/<file>`, neither part empty, `.` or `..`.
/// An index entry naming anything else is corrupt (and is never joined to a path).
pub(crate) fn is_file_name(name: &str) -> bool {
    let mut parts = name.split('/');
    let (Some(dir), Some(file), None) = (parts.next(), parts.next(), parts.next()) else {
        return false;
    };
    [dir, file]
        .iter()
        .all(|part| !part.is_empty() && *part != "." && *part != ".." && !part.contains('\\'))
}

/// FNV-1a, 64 bits: a hash fixed forever (it names directories on disk).
fn fnv1a64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |hash, &byte| {
        (hash ^ u64::from(byte)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn site_directories_are_escaped_injectively_and_bounded() {
        assert_eq!(site_dir("store-1"), "store-1");
        assert_eq!(site_dir("Halle 7/a.b"), "Halle%207%2Fa%2Eb");
        assert_eq!(site_dir(".."), "%2E%2E");
        assert_eq!(site_dir("%41"), "%2541");
        assert_eq!(site_dir("é"), "%C3%A9");
        let long = "ü".repeat(127);
        let dir = site_dir(&long);
        assert!(dir.len() <= MAX_SITE_DIR_BYTES, "{}", dir.len());
        assert!(dir.contains('~'), "{dir}");
        assert_ne!(dir, site_dir(&format!("{long}x")));
        // A cut never splits an escape: every '%' is followed by two hex digits.
        for n in 60..=127 {
            let dir = site_dir(&"a.".repeat(n));
            let escaped = dir
                .split_once('~')
                .map_or(dir.as_str(), |(escaped, _)| escaped);
            let bytes = escaped.as_bytes();
            for (i, _) in bytes.iter().enumerate().filter(|(_, b)| **b == b'%') {
                assert!(i + 3 <= bytes.len(), "{dir}");
            }
        }
        assert_eq!(fnv1a64(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64(b"a"), 0xaf63_dc4c_8601_ec8c);
    }

    #[test]
    fn file_names_are_checked_before_use() {
        let name = file_name("depot", 42, 0xdead_beef);
        assert_eq!(name, "depot/00000000000000000042-deadbeef.ckpt");
        assert!(is_file_name(&name));
        for bad in [
            "", "a", "a/", "/a", "../a", "a/..", "a/b/c", "a/./", "a\\b/c",
        ] {
            assert!(!is_file_name(bad), "{bad:?}");
        }
    }
}
