//! The semantics of [`crate::MapStore`], written once over a minimal transactional key-value interface that
//! each backend implements (private). Keeping the logic here guarantees `SledStore` and `MemStore` behave alike.

use std::io::{Read, Write};

use crate::checkpoints;
use crate::envelope::{self, decode_u64};
use crate::file_step::FileStep;
use crate::key::{
    self, INTERNAL_KIND_MIN, KIND_CHECKPOINT, KIND_CHECKPOINT_FILE, KIND_MAP_VERSION,
    KIND_SESSION_SEQ,
};
use crate::side_files::SideFiles;
use crate::site_archive::{ArchiveReader, ArchiveWriter, Chunk};
use crate::value_files::{self, ValueFiles};
use crate::{
    BatchOp, BatchOutcome, MAX_INLINE_VALUE_BYTES, RecordId, RecordIter, RecordKind, Result,
    StorageError, TransferSummary, WriteBatch, validate_session_id, validate_site_id,
};

/// Raw (key, value) pairs under a prefix, in key order.
pub(crate) type RawIter<'a> = Box<dyn Iterator<Item = Result<(Vec<u8>, Vec<u8>)>> + Send + 'a>;

/// Reads and writes inside one atomic transaction.
pub(crate) trait RawTxn {
    fn get(&mut self, key: &[u8]) -> Result<Option<Vec<u8>>>;
    /// Stores `value` under `key`; returns the value it replaced.
    fn insert(&mut self, key: &[u8], value: Vec<u8>) -> Result<Option<Vec<u8>>>;
    /// Removes `key`; returns the value it held.
    fn remove(&mut self, key: &[u8]) -> Result<Option<Vec<u8>>>;
}

/// A transactional ordered key-value store, with files beside it for the bytes of checkpoints and of
/// large record values.
pub(crate) trait RawKv: Send + Sync {
    /// Where the bytes of checkpoints go (see the `checkpoints` module).
    fn checkpoint_files(&self) -> &dyn SideFiles;
    /// Where large record values go (see the `value_files` module).
    fn value_files(&self) -> &ValueFiles;
    /// Reports a step between a file and its entry to the hook, if one is set.
    fn step(&self, step: FileStep);
    fn raw_get(&self, key: &[u8]) -> Result<Option<Vec<u8>>>;
    fn raw_scan(&self, prefix: &[u8]) -> RawIter<'_>;
    /// Runs `body` atomically and serializably: its writes all land if it returns `Ok`, none otherwise.
    /// `body` may be run more than once (optimistic retries), so it must have no other side effects.
    fn transact<T>(&self, body: &dyn Fn(&mut dyn RawTxn) -> Result<T>) -> Result<T>;
    fn raw_flush(&self) -> Result<()>;
    /// See [`crate::MapStore::generation`].
    fn generation(&self) -> u64 {
        0
    }
}

/// State of a site in the registry (the payload of its registry entry).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SiteState {
    Complete = 1,
    Incomplete = 2,
}

/// Records written per transaction when importing or deleting a site.
const CHUNK_RECORDS: usize = 512;
/// Payload bytes written per transaction when importing.
const CHUNK_BYTES: usize = 8 << 20;

fn site_state(site_key: &[u8], stored: Option<&[u8]>) -> Result<Option<SiteState>> {
    let Some(stored) = stored else {
        return Ok(None);
    };
    match envelope::open(site_key, stored)? {
        [1] => Ok(Some(SiteState::Complete)),
        [2] => Ok(Some(SiteState::Incomplete)),
        other => Err(StorageError::Corrupt {
            key: key::describe(site_key),
            reason: format!("unknown site state {other:?}"),
        }),
    }
}

/// Refuses an unknown or incomplete site (`stored`: its registry entry).
pub(crate) fn site_must_be_complete(
    site: &str,
    site_key: &[u8],
    stored: Option<&[u8]>,
) -> Result<()> {
    match site_state(site_key, stored)? {
        Some(SiteState::Complete) => Ok(()),
        Some(SiteState::Incomplete) => Err(StorageError::SiteIncomplete {
            site: site.to_owned(),
        }),
        None => Err(StorageError::SiteNotFound {
            site: site.to_owned(),
        }),
    }
}

fn sealed_state(site_key: &[u8], state: SiteState) -> Vec<u8> {
    envelope::seal(site_key, &[state as u8])
}

fn read_counter(kv: &impl RawKv, key: &[u8]) -> Result<Option<u64>> {
    kv.raw_get(key)?
        .map(|stored| decode_u64(key, envelope::open(key, &stored)?))
        .transpose()
}

fn txn_counter(txn: &mut dyn RawTxn, key: &[u8]) -> Result<Option<u64>> {
    txn.get(key)?
        .map(|stored| decode_u64(key, envelope::open(key, &stored)?))
        .transpose()
}

/// Makes every change so far durable, then deletes the value files that changes made before it unnamed,
/// and those of changes a reopen of the database lost (see the `value_files` module). Every flush of the
/// crate's semantics goes through here.
pub(crate) fn flush(kv: &impl RawKv) -> Result<()> {
    let values = kv.value_files();
    let due = values.take_unnamed();
    let fresh = values.take_fresh();
    let flushed = kv.raw_flush();
    value_files::settle_fresh(kv, fresh, flushed.is_ok());
    if let Err(error) = flushed {
        values.restore_unnamed(due);
        return Err(error);
    }
    value_files::remove_unnamed(kv, due);
    Ok(())
}

pub(crate) fn apply(kv: &impl RawKv, batch: &WriteBatch) -> Result<BatchOutcome> {
    batch.validate()?;
    let site = batch.site();
    let site_key = key::site_key(site);
    let version_key = key::record_key(site, KIND_MAP_VERSION, &[]);
    let session_key = batch.session().map(|(session, seq)| {
        (
            key::record_key(site, KIND_SESSION_SEQ, session.as_bytes()),
            seq,
        )
    });
    let values = kv.value_files();
    // Held from the first value file until the entries naming them are stored: a site's value directory
    // is not deleted under them.
    let writing = batch
        .ops()
        .iter()
        .any(|op| matches!(op, BatchOp::Put { value, .. } if value.len() > MAX_INLINE_VALUE_BYTES))
        .then(|| values.files().shared());
    // Seal outside the transaction: it may be retried, and sealing is the costly part. Large values go to
    // their files now, durably, before any entry can name them.
    let mut writes: Vec<(Vec<u8>, Option<Vec<u8>>)> = Vec::with_capacity(batch.len());
    let mut written: Vec<(Vec<u8>, String)> = Vec::new();
    for op in batch.ops() {
        match op {
            BatchOp::Put { kind, id, value } => {
                let key = key::record_key(site, kind.as_byte(), id.as_bytes());
                match values.seal(site, &key, value) {
                    Ok((sealed, file)) => {
                        if let Some(file) = file {
                            written.push((key.clone(), file));
                        }
                        writes.push((key, Some(sealed)));
                    }
                    Err(error) => {
                        // Best effort: an orphan left here goes at the next open.
                        for (_, file) in &written {
                            let _ = values.files().remove(site, file);
                        }
                        return Err(error);
                    }
                }
            }
            BatchOp::Delete { kind, id } => {
                writes.push((key::record_key(site, kind.as_byte(), id.as_bytes()), None));
            }
        }
    }
    if !written.is_empty() {
        kv.step(FileStep::ValueFilesDurable {
            files: written.len(),
        });
    }
    let outcome = kv.transact(&|txn| {
        let state = site_state(&site_key, txn.get(&site_key)?.as_deref())?;
        if state == Some(SiteState::Incomplete) {
            return Err(StorageError::SiteIncomplete {
                site: site.to_owned(),
            });
        }
        if let Some((session_key, seq)) = &session_key
            && let Some(last_applied) = txn_counter(txn, session_key)?
            && *seq <= last_applied
        {
            return Ok((BatchOutcome::Duplicate { last_applied }, Vec::new()));
        }
        if state.is_none() {
            txn.insert(&site_key, sealed_state(&site_key, SiteState::Complete))?;
        }
        // The values the batch replaces or removes that name files (a later op on the same key replaces
        // an earlier one's, whose file is then unnamed too).
        let mut replaced = Vec::new();
        for (key, value) in &writes {
            let old = match value {
                Some(sealed) => txn.insert(key, sealed.clone())?,
                None => txn.remove(key)?,
            };
            if let Some(old) = old.filter(|old| value_files::names_a_file(old)) {
                replaced.push((key.clone(), old));
            }
        }
        let mut map_version = txn_counter(txn, &version_key)?.unwrap_or(0);
        if batch.bumps_map_version() {
            map_version += 1;
            txn.insert(
                &version_key,
                envelope::seal(&version_key, &map_version.to_le_bytes()),
            )?;
        }
        if let Some((session_key, seq)) = &session_key {
            txn.insert(session_key, envelope::seal(session_key, &seq.to_le_bytes()))?;
        }
        Ok((BatchOutcome::Applied { map_version }, replaced))
    });
    drop(writing);
    match outcome {
        Ok((applied @ BatchOutcome::Applied { .. }, replaced)) => {
            for (key, old) in replaced {
                values.unname(site, &key, &old);
            }
            // Read after the transaction: a reopen it made (a wedged store's) came before its entries.
            let generation = kv.generation();
            for (key, file) in written {
                values.note_fresh(site, &key, file, generation);
            }
            Ok(applied)
        }
        Ok((duplicate, _)) => {
            // Nothing was written: no entry names the files (best effort, as below).
            for (_, file) in &written {
                let _ = values.files().remove(site, file);
            }
            Ok(duplicate)
        }
        Err(error) => {
            // Best effort: an orphan left here goes at the next open.
            for (key, file) in &written {
                let _ = value_files::remove_unless_named(kv, site, key, file);
            }
            Err(error)
        }
    }
}

pub(crate) fn get(
    kv: &impl RawKv,
    site: &str,
    kind: RecordKind,
    id: &RecordId,
) -> Result<Option<Vec<u8>>> {
    validate_site_id(site)?;
    let key = key::record_key(site, kind.as_byte(), id.as_bytes());
    kv.raw_get(&key)?
        .map(|stored| kv.value_files().read(site, &key, &stored))
        .transpose()
}

pub(crate) fn scan<'a>(kv: &'a impl RawKv, site: &str, kind: RecordKind) -> Result<RecordIter<'a>> {
    validate_site_id(site)?;
    let prefix = key::kind_prefix(site, kind.as_byte());
    let prefix_len = prefix.len();
    let site = site.to_owned();
    Ok(Box::new(kv.raw_scan(&prefix).map(move |item| {
        let (key, stored) = item?;
        let payload = kv.value_files().read(&site, &key, &stored)?;
        Ok((RecordId::new(&key[prefix_len..]), payload))
    })))
}

pub(crate) fn list_sites(kv: &impl RawKv) -> Result<Vec<String>> {
    let mut sites = Vec::new();
    for item in kv.raw_scan(&[key::NS_SITE]) {
        let (site_key, stored) = item?;
        if site_state(&site_key, Some(&stored))? == Some(SiteState::Complete) {
            let site = std::str::from_utf8(&site_key[1..]).map_err(|_| StorageError::Corrupt {
                key: key::describe(&site_key),
                reason: "site id is not UTF-8".to_owned(),
            })?;
            sites.push(site.to_owned());
        }
    }
    sites.sort();
    Ok(sites)
}

pub(crate) fn map_version(kv: &impl RawKv, site: &str) -> Result<u64> {
    validate_site_id(site)?;
    Ok(read_counter(kv, &key::record_key(site, KIND_MAP_VERSION, &[]))?.unwrap_or(0))
}

pub(crate) fn last_applied_seq(kv: &impl RawKv, site: &str, session: &str) -> Result<Option<u64>> {
    validate_site_id(site)?;
    validate_session_id(session)?;
    read_counter(
        kv,
        &key::record_key(site, KIND_SESSION_SEQ, session.as_bytes()),
    )
}

/// Marks the site incomplete, then removes its records chunk by chunk, its checkpoint and value files, then
/// its registry entry.
pub(crate) fn delete_site(kv: &impl RawKv, site: &str) -> Result<()> {
    validate_site_id(site)?;
    let site_key = key::site_key(site);
    kv.transact(&|txn| txn.insert(&site_key, sealed_state(&site_key, SiteState::Incomplete)))?;
    purge_records(kv, site)?;
    remove_site_files(kv, site)?;
    kv.transact(&|txn| txn.remove(&site_key))?;
    flush(kv)
}

/// Deletes a site's checkpoint and value files once its records are gone (deleted or purged for an
/// import): flushes first, so no durable entry names a deleted file.
fn remove_site_files(kv: &impl RawKv, site: &str) -> Result<()> {
    flush(kv)?;
    checkpoints::remove_site_files(kv, site)?;
    value_files::remove_site_files(kv, site)
}

fn purge_records(kv: &impl RawKv, site: &str) -> Result<()> {
    let prefix = key::site_prefix(site);
    loop {
        let keys: Vec<Vec<u8>> = kv
            .raw_scan(&prefix)
            .take(CHUNK_RECORDS)
            .map(|item| item.map(|(key, _)| key))
            .collect::<Result<_>>()?;
        if keys.is_empty() {
            return Ok(());
        }
        // Their value files go with the site's directory.
        kv.transact(&|txn| keys.iter().try_for_each(|key| txn.remove(key).map(drop)))?;
    }
}

pub(crate) fn export_site(
    kv: &impl RawKv,
    site: &str,
    out: &mut dyn Write,
) -> Result<TransferSummary> {
    validate_site_id(site)?;
    let site_key = key::site_key(site);
    match site_state(&site_key, kv.raw_get(&site_key)?.as_deref())? {
        None => {
            return Err(StorageError::SiteNotFound {
                site: site.to_owned(),
            });
        }
        Some(SiteState::Incomplete) => {
            return Err(StorageError::SiteIncomplete {
                site: site.to_owned(),
            });
        }
        Some(SiteState::Complete) => {}
    }
    let prefix = key::site_prefix(site);
    let mut writer = ArchiveWriter::new(out, site)?;
    for item in kv.raw_scan(&prefix) {
        let (key, stored) = item?;
        let Some((&kind, id)) = key[prefix.len()..].split_first() else {
            return Err(StorageError::Corrupt {
                key: key::describe(&key),
                reason: "key has no kind".to_owned(),
            });
        };
        if kind == KIND_CHECKPOINT_FILE {
            // A checkpoint in a file travels as the checkpoint record it stands for.
            let bytes = checkpoints::file_bytes(kv, site, &key, &stored)?;
            writer.record(KIND_CHECKPOINT, id, &bytes)?;
        } else if kind < INTERNAL_KIND_MIN {
            // A record travels with its value, in a file or not.
            writer.record(kind, id, &kv.value_files().read(site, &key, &stored)?)?;
        } else {
            writer.record(kind, id, envelope::open(&key, &stored)?)?;
        }
    }
    writer.finish()
}

pub(crate) fn import_site(
    kv: &impl RawKv,
    site: &str,
    input: &mut dyn Read,
) -> Result<TransferSummary> {
    validate_site_id(site)?;
    let site_key = key::site_key(site);
    let state = site_state(&site_key, kv.raw_get(&site_key)?.as_deref())?;
    let has_records = kv
        .raw_scan(&key::site_prefix(site))
        .next()
        .transpose()?
        .is_some();
    if state == Some(SiteState::Complete) || (state.is_none() && has_records) {
        return Err(StorageError::SiteNotEmpty {
            site: site.to_owned(),
        });
    }
    // Claim the site atomically (a concurrent batch or import may have created it since the check).
    kv.transact(
        &|txn| match site_state(&site_key, txn.get(&site_key)?.as_deref())? {
            Some(SiteState::Complete) => Err(StorageError::SiteNotEmpty {
                site: site.to_owned(),
            }),
            _ => txn.insert(&site_key, sealed_state(&site_key, SiteState::Incomplete)),
        },
    )?;
    purge_records(kv, site)?;
    remove_site_files(kv, site)?;
    match import_records(kv, site, input) {
        Ok(summary) => {
            kv.transact(&|txn| {
                txn.insert(&site_key, sealed_state(&site_key, SiteState::Complete))
            })?;
            flush(kv)?;
            Ok(summary)
        }
        Err(error) => {
            // Best effort: if the cleanup fails too, the site stays incomplete (unlisted, write-protected).
            let _ = delete_site(kv, site);
            Err(error)
        }
    }
}

fn import_records(kv: &impl RawKv, site: &str, input: &mut dyn Read) -> Result<TransferSummary> {
    let bad = |reason: String| StorageError::BadArchive { reason };
    let mut reader = ArchiveReader::new(input)?;
    let Chunk::Begin { .. } = reader.next_chunk()? else {
        return Err(bad("first chunk is not the begin chunk".to_owned()));
    };
    let mut summary = TransferSummary::default();
    let mut pending: Vec<(Vec<u8>, Vec<u8>)> = Vec::new();
    let mut pending_bytes = 0;
    let values = kv.value_files();
    // Held while value files are written until their entries are stored (see `apply`); the caller
    // cleans up after a failure only once it is released.
    let _writing = values.files().shared();
    let write = |pending: &mut Vec<(Vec<u8>, Vec<u8>)>| {
        kv.transact(&|txn| {
            pending
                .iter()
                .try_for_each(|(key, sealed)| txn.insert(key, sealed.clone()).map(drop))
        })?;
        pending.clear();
        Ok::<_, StorageError>(())
    };
    loop {
        match reader.next_chunk()? {
            Chunk::Begin { .. } => return Err(bad("second begin chunk".to_owned())),
            Chunk::Record { kind, id, payload } => {
                check_imported_kind(kind, &id, &payload).map_err(bad)?;
                summary.records += 1;
                summary.payload_bytes += payload.len() as u64;
                pending_bytes += payload.len();
                if kind == KIND_CHECKPOINT {
                    pending.push(checkpoints::import_file(kv, site, &id, &payload)?);
                } else if kind < INTERNAL_KIND_MIN {
                    // A large value goes to its file, as a batch's does.
                    let key = key::record_key(site, kind, &id);
                    let (sealed, _) = values.seal(site, &key, &payload)?;
                    pending.push((key, sealed));
                } else {
                    let key = key::record_key(site, kind, &id);
                    pending.push((key.clone(), envelope::seal(&key, &payload)));
                }
                if pending.len() >= CHUNK_RECORDS || pending_bytes >= CHUNK_BYTES {
                    write(&mut pending)?;
                    pending_bytes = 0;
                }
            }
            Chunk::End { records } => {
                if records != summary.records {
                    return Err(bad(format!(
                        "end chunk counts {records} records, the stream held {}",
                        summary.records
                    )));
                }
                write(&mut pending)?;
                return Ok(summary);
            }
        }
    }
}

fn check_imported_kind(kind: u8, id: &[u8], payload: &[u8]) -> Result<(), String> {
    match kind {
        KIND_MAP_VERSION if id.is_empty() && payload.len() == 8 => Ok(()),
        KIND_CHECKPOINT if id.len() == 8 => Ok(()),
        KIND_SESSION_SEQ if payload.len() == 8 => std::str::from_utf8(id)
            .ok()
            .filter(|session| validate_session_id(session).is_ok())
            .map(|_| ())
            .ok_or_else(|| "bad session id in a session counter".to_owned()),
        kind if kind >= INTERNAL_KIND_MIN => {
            Err(format!("malformed internal record of kind {kind:#04x}"))
        }
        kind if RecordKind::from_byte(kind).is_none() => Err(format!("unknown record kind {kind}")),
        _ if id.len() > crate::MAX_ID_BYTES => Err("record id too long".to_owned()),
        _ => Ok(()),
    }
}

/// Implements [`crate::MapStore`] for a type implementing [`RawKv`] by delegating to this module.
macro_rules! impl_map_store_via_raw_kv {
    ($store:ty) => {
        impl $crate::MapStore for $store {
            fn apply(&self, batch: &$crate::WriteBatch) -> $crate::Result<$crate::BatchOutcome> {
                $crate::raw_kv::apply(self, batch)
            }

            fn flush(&self) -> $crate::Result<()> {
                $crate::raw_kv::flush(self)
            }

            fn generation(&self) -> u64 {
                $crate::raw_kv::RawKv::generation(self)
            }

            fn get(
                &self,
                site: &str,
                kind: $crate::RecordKind,
                id: &$crate::RecordId,
            ) -> $crate::Result<Option<Vec<u8>>> {
                $crate::raw_kv::get(self, site, kind, id)
            }

            fn scan(
                &self,
                site: &str,
                kind: $crate::RecordKind,
            ) -> $crate::Result<$crate::RecordIter<'_>> {
                $crate::raw_kv::scan(self, site, kind)
            }

            fn list_sites(&self) -> $crate::Result<Vec<String>> {
                $crate::raw_kv::list_sites(self)
            }

            fn map_version(&self, site: &str) -> $crate::Result<u64> {
                $crate::raw_kv::map_version(self, site)
            }

            fn last_applied_seq(&self, site: &str, session: &str) -> $crate::Result<Option<u64>> {
                $crate::raw_kv::last_applied_seq(self, site, session)
            }

            fn delete_site(&self, site: &str) -> $crate::Result<()> {
                $crate::raw_kv::delete_site(self, site)
            }

            fn put_checkpoint(
                &self,
                site: &str,
                log_index: u64,
                checkpoint: &[u8],
            ) -> $crate::Result<()> {
                $crate::checkpoints::put_checkpoint(self, site, log_index, checkpoint)
            }

            fn checkpoint_indexes(&self, site: &str) -> $crate::Result<Vec<u64>> {
                $crate::checkpoints::checkpoint_indexes(self, site)
            }

            fn checkpoint(&self, site: &str, log_index: u64) -> $crate::Result<Option<Vec<u8>>> {
                $crate::checkpoints::checkpoint(self, site, log_index)
            }

            fn compact(
                &self,
                site: &str,
                log_kind: $crate::RecordKind,
                retention: &$crate::CheckpointRetention,
            ) -> $crate::Result<$crate::Compaction> {
                $crate::checkpoints::compact(self, site, log_kind, retention)
            }

            fn export_site(
                &self,
                site: &str,
                out: &mut dyn std::io::Write,
            ) -> $crate::Result<$crate::TransferSummary> {
                $crate::raw_kv::export_site(self, site, out)
            }

            fn import_site(
                &self,
                site: &str,
                input: &mut dyn std::io::Read,
            ) -> $crate::Result<$crate::TransferSummary> {
                $crate::raw_kv::import_site(self, site, input)
            }
        }
    };
}
pub(crate) use impl_map_store_via_raw_kv;
