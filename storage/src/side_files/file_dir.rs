//! Files beside the database, on disk, written crash-safely: each to a temporary file in its final directory,
//! fsynced, renamed over its name, the directory fsynced (the way etcd writes its snapshots). A crash at
//! any point leaves either the old name or the whole new file; a temporary file it leaves behind is an
//! orphan, deleted by [`SideFiles::retain`] when the store next opens.

use std::collections::BTreeSet;
use std::fs::{self, File};
use std::io::{self, Write as _};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard};

use super::SideFiles;
use crate::{Result, StorageError};

/// A directory of files beside a [`crate::SledStore`]'s database (see the parent module for its layout).
#[derive(Debug)]
pub(crate) struct FileDir {
    root: PathBuf,
    /// What the files hold, for messages: `"checkpoint"`, `"value"`.
    what: &'static str,
    lock: RwLock<()>,
    /// Temporary files begun by this process (their names are unique with it).
    temp_files: AtomicU64,
}

impl FileDir {
    /// The directory `root` of `what` files (`"checkpoint"`, `"value"`: for messages), created (durably)
    /// if missing.
    pub(crate) fn open(root: PathBuf, what: &'static str) -> Result<Self> {
        if !root.is_dir() {
            create_dir_durably(&root).map_err(|source| StorageError::FileDir {
                what,
                path: root.clone(),
                action: "create",
                source,
            })?;
        }
        Ok(Self {
            root,
            what,
            lock: RwLock::new(()),
            temp_files: AtomicU64::new(0),
        })
    }

    fn dir_error(
        &self,
        path: PathBuf,
        action: &'static str,
    ) -> impl FnOnce(io::Error) -> StorageError {
        let what = self.what;
        move |source| StorageError::FileDir {
            what,
            path,
            action,
            source,
        }
    }

    fn file_error(
        &self,
        site: &str,
        file: PathBuf,
        action: &'static str,
    ) -> impl FnOnce(io::Error) -> StorageError {
        let (what, site) = (self.what, site.to_owned());
        move |source| StorageError::File {
            what,
            site,
            file,
            action,
            source,
        }
    }

    fn write_durably(&self, path: &Path, bytes: &[u8]) -> io::Result<()> {
        let dir = path
            .parent()
            .ok_or_else(|| io::Error::other("a file has no directory"))?;
        if !dir.is_dir() {
            create_dir_durably(dir)?;
        }
        let temp = dir.join(format!(
            ".{}.{}-{}.tmp",
            path.file_name().unwrap_or_default().to_string_lossy(),
            std::process::id(),
            self.temp_files.fetch_add(1, Ordering::Relaxed)
        ));
        let written = (|| {
            let mut file = File::create(&temp)?;
            file.write_all(bytes)?;
            file.sync_all()?;
            fs::rename(&temp, path)?;
            sync_dir(dir)
        })();
        if written.is_err() {
            let _ = fs::remove_file(&temp);
        }
        written
    }

    /// Every file under the root and the site directories.
    fn walk(&self) -> Result<Listing> {
        let (mut files, mut dirs) = (Vec::new(), Vec::new());
        let entries = |dir: &Path| {
            fs::read_dir(dir)
                .and_then(Iterator::collect::<io::Result<Vec<_>>>)
                .map_err(self.dir_error(dir.to_path_buf(), "list"))
        };
        for entry in entries(&self.root)? {
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if !entry.file_type().is_ok_and(|kind| kind.is_dir()) {
                files.push((name, path));
                continue;
            }
            for inner in entries(&path)? {
                let file = inner.file_name().to_string_lossy().into_owned();
                files.push((format!("{name}/{file}"), inner.path()));
            }
            dirs.push(path);
        }
        files.sort();
        dirs.sort();
        Ok(Listing { files, dirs })
    }
}

/// What [`FileDir::walk`] found.
struct Listing {
    /// Every file: its name relative to the root, its path.
    files: Vec<(String, PathBuf)>,
    /// The site directories.
    dirs: Vec<PathBuf>,
}

/// Creates `dir` (its parent must exist) and fsyncs the parent, so the new name is durable.
fn create_dir_durably(dir: &Path) -> io::Result<()> {
    match fs::create_dir(dir) {
        Ok(()) => {}
        Err(error) if error.kind() == io::ErrorKind::AlreadyExists => {}
        Err(error) => return Err(error),
    }
    dir.parent().map_or(Ok(()), sync_dir)
}

/// fsyncs a directory: the names created or renamed in it are durable once it returns.
fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

/// `Ok` for a file that is already gone.
fn absent_is_fine(result: io::Result<()>) -> io::Result<()> {
    match result {
        Err(error) if error.kind() == io::ErrorKind::NotFound => Ok(()),
        other => other,
    }
}

impl SideFiles for FileDir {
    fn write(&self, site: &str, name: &str, bytes: &[u8]) -> Result<()> {
        let path = self.path(name);
        self.write_durably(&path, bytes)
            .map_err(self.file_error(site, path, "write"))
    }

    fn read(&self, site: &str, name: &str) -> Result<Option<Vec<u8>>> {
        let path = self.path(name);
        match fs::read(&path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(error) if error.kind() == io::ErrorKind::NotFound => Ok(None),
            Err(source) => Err(self.file_error(site, path, "read")(source)),
        }
    }

    fn remove(&self, site: &str, name: &str) -> Result<()> {
        let path = self.path(name);
        absent_is_fine(fs::remove_file(&path)).map_err(self.file_error(site, path, "remove"))
    }

    fn remove_dir(&self, site: &str, dir: &str) -> Result<()> {
        let path = self.root.join(dir);
        absent_is_fine(fs::remove_dir_all(&path)).map_err(self.file_error(
            site,
            path,
            "remove the directory of",
        ))
    }

    fn names(&self) -> Result<Vec<String>> {
        Ok(self
            .walk()?
            .files
            .into_iter()
            .map(|(name, _)| name)
            .collect())
    }

    fn retain(&self, keep: &BTreeSet<String>) -> Result<u64> {
        let Listing { files, dirs } = self.walk()?;
        let mut removed = 0;
        for (name, path) in files {
            if keep.contains(&name) {
                continue;
            }
            let result = if path.is_dir() {
                fs::remove_dir_all(&path)
            } else {
                fs::remove_file(&path)
            };
            absent_is_fine(result).map_err(self.dir_error(path, "remove the orphan"))?;
            removed += 1;
        }
        for dir in dirs {
            // Only an empty one goes; a non-empty one is in use.
            let _ = fs::remove_dir(dir);
        }
        Ok(removed)
    }

    fn total_bytes(&self) -> Result<u64> {
        let mut total = 0;
        for (_, path) in self.walk()?.files {
            match fs::metadata(&path) {
                Ok(meta) => total += meta.len(),
                Err(error) if error.kind() == io::ErrorKind::NotFound => {}
                Err(source) => return Err(self.dir_error(path, "measure")(source)),
            }
        }
        Ok(total)
    }

    fn path(&self, name: &str) -> PathBuf {
        self.root.join(name)
    }

    fn shared(&self) -> RwLockReadGuard<'_, ()> {
        self.lock.read().unwrap_or_else(PoisonError::into_inner)
    }

    fn exclusive(&self) -> RwLockWriteGuard<'_, ()> {
        self.lock.write().unwrap_or_else(PoisonError::into_inner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_are_written_whole_listed_and_orphans_removed() {
        let temp = tempfile::tempdir().unwrap();
        let dir = FileDir::open(temp.path().join("checkpoints"), "checkpoint").unwrap();
        dir.write("depot", "depot/1.ckpt", b"one").unwrap();
        dir.write("depot", "depot/1.ckpt", b"one again").unwrap();
        dir.write("depot", "depot/2.ckpt", b"two").unwrap();
        dir.write("yard", "yard/1.ckpt", b"yard").unwrap();
        assert_eq!(
            dir.read("depot", "depot/1.ckpt").unwrap().as_deref(),
            Some(&b"one again"[..])
        );
        assert_eq!(dir.read("depot", "depot/3.ckpt").unwrap(), None);
        assert_eq!(dir.total_bytes().unwrap(), 9 + 3 + 4);
        assert_eq!(
            dir.names().unwrap(),
            ["depot/1.ckpt", "depot/2.ckpt", "yard/1.ckpt"]
        );
        // What a crash between writing and renaming leaves.
        fs::write(temp.path().join("checkpoints/depot/.2.ckpt.1-0.tmp"), b"tw").unwrap();
        fs::write(temp.path().join("checkpoints/stray"), b"?").unwrap();
        let keep = BTreeSet::from(["depot/2.ckpt".to_owned()]);
        assert_eq!(dir.retain(&keep).unwrap(), 4);
        assert_eq!(dir.walk().unwrap().files.len(), 1);
        assert!(
            !temp.path().join("checkpoints/yard").exists(),
            "empty site dirs go"
        );
        dir.remove("depot", "depot/2.ckpt").unwrap();
        dir.remove("depot", "depot/2.ckpt").unwrap();
        dir.remove_dir("depot", "depot").unwrap();
        dir.remove_dir("depot", "depot").unwrap();
        assert_eq!(dir.total_bytes().unwrap(), 0);
    }

    #[test]
    fn a_failed_write_names_the_site_and_file_and_leaves_nothing() {
        let temp = tempfile::tempdir().unwrap();
        let dir = FileDir::open(temp.path().join("checkpoints"), "checkpoint").unwrap();
        // The site "directory" is a file: nothing can be created in it.
        fs::write(temp.path().join("checkpoints/depot"), b"").unwrap();
        let error = dir.write("depot", "depot/1.ckpt", b"one").unwrap_err();
        let message = error.to_string();
        assert!(
            message.contains("checkpoint file") && message.contains("depot/1.ckpt"),
            "{message}"
        );
        assert!(message.contains("\"depot\""), "{message}");
    }
}
