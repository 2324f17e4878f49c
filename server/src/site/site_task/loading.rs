//! Rebuilding a site map from its store (its newest readable checkpoint and the log after it), and
//! making the result the task's map.

use std::sync::Arc;
use std::time::{Duration, Instant};

use mapping::lifelong::LifelongOptions;
use prost::Message as _;
use proto::{SiteCheckpoint, UploadBatch, pb};
use storage::MapStore;

use super::{SITE_LOG_KIND, SiteTask};
use crate::site::{SiteError, SiteMap};

impl SiteTask {
    /// [`load`] on the blocking pool. A map below the published version is refused as a corrupt log
    /// (what was published was durable); `what` names the store in that error.
    pub(super) async fn load_from_store(&self, what: &str) -> Result<Loaded, SiteError> {
        let (site, store, options) = (self.site(), Arc::clone(&self.store), self.options.clone());
        let use_checkpoints = self.checkpoints.enabled;
        let loaded = tokio::task::spawn_blocking(move || {
            load(&site, options, store.as_ref(), use_checkpoints)
        })
        .await
        .map_err(SiteError::Worker)??;
        let (version, published) = (loaded.map.version(), self.versions.borrow().version);
        if version < published {
            return Err(SiteError::CorruptLog {
                index: version + 1,
                reason: format!(
                    "{what} ends at version {version}, below the published {published}"
                ),
            });
        }
        Ok(loaded)
    }

    /// Makes `loaded` the task's map, built under the store's `generation`.
    pub(super) fn install(&mut self, loaded: Loaded, generation: u64) {
        let map = loaded.map;
        self.checkpointed_version = loaded.checkpoint.unwrap_or(0);
        let now = tokio::time::Instant::now();
        let open: Vec<String> = map.open_sessions().into_iter().map(|(s, _)| s).collect();
        self.last_heard.retain(|session, _| open.contains(session));
        for session in open {
            self.last_heard.entry(session).or_insert(now);
        }
        self.map = Some(Box::new(map));
        self.generation = generation;
        self.unflushed = false;
    }
}

/// What [`load`] rebuilt a site from.
pub(crate) struct Loaded {
    pub(crate) map: SiteMap,
    /// The log index of the checkpoint it started from (`None`: the whole log).
    pub(crate) checkpoint: Option<u64>,
    /// Log entries replayed after it.
    pub(crate) replayed: u64,
    /// Where the time went.
    pub(crate) times: LoadTimes,
}

/// Where a [`load`]'s time went, wall-clock time of each step (logged with every load and restore).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct LoadTimes {
    /// Reading the checkpoints' bytes (index, file, CRC), every one tried.
    pub(crate) read: Duration,
    /// Decoding them (protobuf, then the checks of `SiteCheckpoint`'s conversion).
    pub(crate) decode: Duration,
    /// Building the site map from the decoded state (`SiteMap::restore`: what the checkpoint does not
    /// store, such as the branch-and-bound precomputation grids).
    pub(crate) rebuild: Duration,
    /// Reading the log and replaying the entries after the checkpoint.
    pub(crate) replay: Duration,
}

/// Rebuilds a site map from its store: the newest checkpoint that reads back (when `use_checkpoints`)
/// and the log after it, or the whole log (see the module docs of `site_task` for which checkpoints are skipped and
/// which stop the site).
pub(crate) fn load(
    site: &str,
    options: LifelongOptions,
    store: &dyn MapStore,
    use_checkpoints: bool,
) -> Result<Loaded, SiteError> {
    let mut from = None;
    let mut times = LoadTimes::default();
    if use_checkpoints {
        for index in store.checkpoint_indexes(site)? {
            match restore_checkpoint(site, options.clone(), store, index, &mut times) {
                Ok(Some(map)) => {
                    from = Some((index, map));
                    break;
                }
                Ok(None) => {}
                Err(
                    e @ (SiteError::CorruptCheckpoint { .. }
                    | SiteError::Storage(storage::StorageError::Corrupt { .. })),
                ) => {
                    tracing::warn!(
                        index,
                        "site checkpoint unreadable, falling back to the one before it: {e}"
                    );
                }
                Err(e) => return Err(e),
            }
        }
    }
    let checkpoint = from.as_ref().map(|(index, _)| *index);
    let mut map = match from {
        Some((_, map)) => map,
        None => SiteMap::new(site, options).map_err(SiteError::Map)?,
    };
    let started = Instant::now();
    let replayed = replay_after(&mut map, store)?;
    times.replay = started.elapsed();
    Ok(Loaded {
        map,
        checkpoint,
        replayed,
        times,
    })
}

/// The site the checkpoint at `index` holds; `Ok(None)` if it is gone (compacted since it was listed).
pub(crate) fn restore_checkpoint(
    site: &str,
    options: LifelongOptions,
    store: &dyn MapStore,
    index: u64,
    times: &mut LoadTimes,
) -> Result<Option<SiteMap>, SiteError> {
    let corrupt = |reason: String| SiteError::CorruptCheckpoint {
        index,
        reason,
        source: None,
    };
    let started = Instant::now();
    let bytes = store.checkpoint(site, index);
    times.read += started.elapsed();
    let Some(bytes) = bytes? else {
        return Ok(None);
    };
    let started = Instant::now();
    let message =
        pb::SiteCheckpoint::decode(bytes.as_slice()).map_err(|e| SiteError::CorruptCheckpoint {
            index,
            reason: format!("it does not decode: {e}"),
            source: Some(e.into()),
        })?;
    // A version this build does not read is never guessed at, never rebuilt behind: the log it covers
    // may be compacted away.
    proto::check_checkpoint_format_version(message.format_version).map_err(|e| {
        SiteError::CheckpointRefused {
            index,
            source: e.into(),
        }
    })?;
    let checkpoint = SiteCheckpoint::try_from(&message).map_err(|e| SiteError::CorruptCheckpoint {
        index,
        reason: e.to_string(),
        source: Some(e.into()),
    });
    drop(message);
    times.decode += started.elapsed();
    let checkpoint = checkpoint?;
    if checkpoint.log_index != index {
        return Err(corrupt(format!(
            "it is stored under log index {index} but says it covers {}",
            checkpoint.log_index
        )));
    }
    let started = Instant::now();
    let map = SiteMap::restore(site, options, checkpoint);
    times.rebuild += started.elapsed();
    map.map(Some)
}

/// Replays the log entries after `map`'s version (entries at or before it, kept for a fallback or for
/// audit, are skipped undecoded); the log must continue the map without a gap and end at the store's
/// version. Returns the number of entries replayed.
fn replay_after(map: &mut SiteMap, store: &dyn MapStore) -> Result<u64, SiteError> {
    let site = map.site().to_owned();
    let stored_version = store.map_version(&site)?;
    let mut replayed = 0;
    for record in store.scan(&site, SITE_LOG_KIND)? {
        let (id, bytes) = record?;
        let index = id.as_u64().ok_or_else(|| SiteError::CorruptLog {
            index: 0,
            reason: format!("log record id {id} is not a number"),
        })?;
        if index <= map.version() {
            continue;
        }
        let corrupt = |reason: String| SiteError::CorruptLog { index, reason };
        let undecodable = |source: Box<dyn std::error::Error + Send + Sync>| {
            SiteError::CorruptEntry { index, source }
        };
        if index != map.version() + 1 {
            return Err(corrupt(if map.version() == 0 {
                "the log before it is compacted away and no readable checkpoint covers it".into()
            } else {
                format!("expected entry {}", map.version() + 1)
            }));
        }
        let entry =
            pb::SiteLogEntry::decode(bytes.as_slice()).map_err(|e| undecodable(e.into()))?;
        proto::check_format_version("SiteLogEntry", entry.format_version)
            .map_err(|e| undecodable(e.into()))?;
        match entry.entry {
            Some(pb::site_log_entry::Entry::SessionOpened(open)) => {
                map.open_session(&open.robot_id, &open.session_uuid, open.trajectory, index)?;
            }
            Some(pb::site_log_entry::Entry::Upload(upload)) => {
                let batch = UploadBatch::try_from(&upload).map_err(|e| undecodable(e.into()))?;
                map.apply_upload(&batch, index)?;
            }
            Some(pb::site_log_entry::Entry::SessionClosed(close)) => {
                let robot = map
                    .session_robot(&close.session_uuid)
                    .ok_or_else(|| corrupt("closes an unknown session".into()))?
                    .to_owned();
                map.close_session(&robot, &close.session_uuid, index)?;
            }
            None => return Err(corrupt("empty entry".into())),
        }
        replayed += 1;
    }
    if map.version() != stored_version {
        return Err(SiteError::CorruptLog {
            index: map.version() + 1,
            reason: format!(
                "the log ends at version {} but the store is at {stored_version}",
                map.version()
            ),
        });
    }
    Ok(replayed)
}
