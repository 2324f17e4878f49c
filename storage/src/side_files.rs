//! Files beside the key-value database: where a store keeps the bytes of its site checkpoints and of
//! its large record values, apart from the database, which holds only each one's entry (length, CRC32,
//! file name: `checkpoint_entry`, `value_entry`).
//!
//! Why: sled 0.34 keeps the space of the large values it held long after they are overwritten or removed.
//! A checkpoint (a site's whole state, 17–28 MB for a 16-session site) stored as a sled value made a
//! store 1.6 GB against 22 MB without; a site log of 30-kB entries leaves sled blob files behind at every
//! reopen of the database (`value_files`). A file is freed the moment it is deleted.
//!
//! Layout: one directory per purpose ([`crate::SledStore`]: `<database dir>/checkpoints` and
//! `<database dir>/values`), holding one directory per site:
//!
//! ```text
//! checkpoints/<site dir>/<log index, 20 decimal digits>-<CRC32, 8 hex digits>.ckpt
//! values/<site dir>/<serial number, 16 hex digits>-<CRC32, 8 hex digits>.val
//! ```
//!
//! The site directory is the site id with every byte other than `A-Z a-z 0-9 - _` written `%XX` (so no
//! site is `.` or `..` or holds a `/`), e.g. `store-1`, `Halle%207`; an id whose escaped form is longer
//! than [`MAX_SITE_DIR_BYTES`] is cut to a prefix and `~` and the FNV-1a-64 hash of the whole id (`~` is
//! never in an escaped id, so the two forms cannot meet). A file name is never given to other bytes while
//! an entry may name it: a checkpoint's carries the CRC of its bytes (a checkpoint rewritten at the same
//! log index with other bytes is a new file), a value's a serial number never used before in the store.
//!
//! Implementations: `FileDir` (files on disk, written crash-safely) and `MemFiles` (the in-memory store's,
//! for tests).

mod file_dir;
mod mem_files;

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::{RwLockReadGuard, RwLockWriteGuard};

pub(crate) use file_dir::FileDir;
pub(crate) use mem_files::MemFiles;

use crate::Result;

/// Longest site directory name, in bytes (file systems allow 255).
pub(crate) const MAX_SITE_DIR_BYTES: usize = 200;

/// Files addressed by their name relative to their directory (`<site dir>/<file>`). `site` arguments only
/// name the site in errors. Thread-safe.
pub(crate) trait SideFiles: Send + Sync {
    /// Writes `bytes` as the file `name`, replacing one of that name: when it returns, the file and its
    /// name are durable. On failure nothing of it is left (no partial file under `name`).
    fn write(&self, site: &str, name: &str, bytes: &[u8]) -> Result<()>;

    /// The file's bytes, `None` if it does not exist.
    fn read(&self, site: &str, name: &str) -> Result<Option<Vec<u8>>>;

    /// Deletes the file (absent: not an error). Not made durable: a deletion a crash undoes leaves an
    /// orphan, removed by [`SideFiles::retain`] at the next open.
    fn remove(&self, site: &str, name: &str) -> Result<()>;

    /// Deletes the site directory `dir` and everything in it (absent: not an error).
    fn remove_dir(&self, site: &str, dir: &str) -> Result<()>;

    /// The names of all the files (temporary files of interrupted writes included), sorted.
    fn names(&self) -> Result<Vec<String>>;

    /// Deletes every file whose name is not in `keep` (temporary files of interrupted writes included)
    /// and the directories left empty; returns how many files it deleted.
    fn retain(&self, keep: &BTreeSet<String>) -> Result<u64>;

    /// Bytes of all the files.
    fn total_bytes(&self) -> Result<u64>;

    /// The file's full path, for messages.
    fn path(&self, name: &str) -> PathBuf;

    /// Shared with other writers while a file is written until the entry naming it is stored (value
    /// files, whose names are never reused); see [`SideFiles::exclusive`].
    fn shared(&self) -> RwLockReadGuard<'_, ()>;

    /// Held alone while files are checked unreferenced and deleted in a way that could meet a file just
    /// written (a whole site directory; a checkpoint file, whose name a rewrite reuses) — and, for
    /// checkpoints, while a file is written until its entry is stored — so that no deletion removes a
    /// file an entry has just come to name.
    fn exclusive(&self) -> RwLockWriteGuard<'_, ()>;
}

/// The directory of a site's files (see the module docs).
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

/// Whether `name` has the shape of a file name: `<dir>/<file>`, neither part empty, `.` or `..`, no `\\`.
/// An entry naming anything else is corrupt (and is never joined to a path).
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
        assert!(is_file_name("depot/00000000000000000042-deadbeef.ckpt"));
        for bad in [
            "", "a", "a/", "/a", "../a", "a/..", "a/b/c", "a/./", "a\\b/c",
        ] {
            assert!(!is_file_name(bad), "{bad:?}");
        }
    }
}
