//! The deterministic workload of the kill -9 test, shared by the `storage-torture` writer and the checker in
//! `tests/kill_nine.rs` (which includes this file with `#[path]`).
//!
//! Batch `seq` (1, 2, ...) of site [`SITE`], conditional on session [`SESSION`] sequence number `seq`:
//! - puts `node_count(seq)` Node records `(seq, i)` with `node_value(seq, i)` (16 B to 1 KiB, one in 128 of 20-100 KiB
//!   so the store's value files are exercised too);
//! - overwrites SiteMeta `"latest"` with `seq`;
//! - puts Outbox `seq` and deletes Outbox `seq - 1`;
//! - appends the site log entry [`LOG_KIND`] `seq` with `log_value(seq)` (one in 4 large enough for a value
//!   file, so compactions free value files);
//! - bumps the map version.
//!
//! So after batches 1..=n exactly: map version n, session n, latest n, a single Outbox record `n`, and the
//! Node records of batches 1..=n and no others. Any partial batch breaks one of these.
//!
//! Checkpoints (issue 34): after batch `seq` with `checkpoint_due(seq)` the writer stores a checkpoint
//! covering the log up to `seq`, [`checkpoint_payload`]: a header with the index and [`digest`] of the
//! log entries 1..=`seq` (chained, so it is derivable only from every acknowledged entry in order) and a
//! 16-256 KiB body generated from that digest; then it compacts the log, keeping [`KEEP_CHECKPOINTS`].
//! Compaction deletes the log entries before the oldest kept checkpoint, so the checker recomputes what
//! each checkpoint must hold from the workload alone.

use storage::{RecordId, RecordKind, WriteBatch};

/// The kind of the site log's entries (one per batch, id = the batch's sequence number).
pub const LOG_KIND: RecordKind = RecordKind::Trajectory;
/// Checkpoints a compaction keeps.
pub const KEEP_CHECKPOINTS: usize = 2;
/// Bytes of a checkpoint payload's header: magic, log index, digest.
const CHECKPOINT_HEADER: usize = 4 + 8 + 8;
const CHECKPOINT_MAGIC: &[u8; 4] = b"ckpt";

/// Site written by the torture workload.
pub const SITE: &str = "torture";
/// Session of the torture workload's batches.
pub const SESSION: &str = "writer";

/// SplitMix64: a small, well-mixed deterministic hash.
pub fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// `len` pseudo-random bytes drawn from `seed` by [`mix`].
fn noise(seed: u64, len: usize) -> Vec<u8> {
    let mut state = seed;
    (0..len)
        .map(|_| {
            state = mix(state);
            state as u8
        })
        .collect()
}

/// Number of Node records of batch `seq` (1..=12).
pub fn node_count(seq: u64) -> u64 {
    1 + mix(seq) % 12
}

/// Value of Node record `(seq, i)`.
pub fn node_value(seq: u64, i: u64) -> Vec<u8> {
    let seed = mix(seq.wrapping_mul(1_000_003) ^ i);
    let len = if seed.is_multiple_of(128) {
        20_000 + seed % 80_000
    } else {
        16 + seed % 1_000
    } as usize;
    noise(seed, len)
}

/// Value of Outbox record `seq`.
pub fn outbox_value(seq: u64) -> Vec<u8> {
    format!("upload {seq}").into_bytes()
}

/// Value of the site log entry `seq`: 24-280 bytes, or one in 4 5-20 kB (in a value file).
pub fn log_value(seq: u64) -> Vec<u8> {
    let seed = mix(seq ^ 0x0106_0106);
    let len = if seed.is_multiple_of(4) {
        5_000 + (seed % 15_000) as usize
    } else {
        24 + (seed % 257) as usize
    };
    noise(seed, len)
}

/// The digest of the log entries up to `seq`, from the digest up to `seq - 1` and entry `seq`'s value
/// (the digest of the empty log is 0).
pub fn digest(previous: u64, seq: u64, log_value: &[u8]) -> u64 {
    log_value
        .chunks(8)
        .fold(mix(previous ^ seq.rotate_left(17)), |h, chunk| {
            let mut word = [0; 8];
            word[..chunk.len()].copy_from_slice(chunk);
            mix(h ^ u64::from_le_bytes(word))
        })
}

/// Whether a checkpoint is written after batch `seq` (about one batch in 8).
pub fn checkpoint_due(seq: u64) -> bool {
    mix(seq ^ 0xC4EC_4B01).is_multiple_of(8)
}

/// The checkpoint covering the log up to `log_index`, whose digest is `digest`: the header (magic, index,
/// digest) and 16-256 KiB generated from the digest.
pub fn checkpoint_payload(log_index: u64, digest: u64) -> Vec<u8> {
    let len = 16_384 + (mix(digest) % (256 * 1024 - 16_384)) as usize;
    let mut payload = Vec::with_capacity(CHECKPOINT_HEADER + len + 8);
    payload.extend_from_slice(CHECKPOINT_MAGIC);
    payload.extend_from_slice(&log_index.to_le_bytes());
    payload.extend_from_slice(&digest.to_le_bytes());
    let mut state = digest;
    while payload.len() < CHECKPOINT_HEADER + len {
        state = mix(state);
        payload.extend_from_slice(&state.to_le_bytes());
    }
    payload.truncate(CHECKPOINT_HEADER + len);
    payload
}

/// The (log index, digest) a checkpoint payload's header states, `None` if it has none.
pub fn checkpoint_header(payload: &[u8]) -> Option<(u64, u64)> {
    let header = payload.get(..CHECKPOINT_HEADER)?;
    let word = |at: usize| {
        let mut bytes = [0; 8];
        bytes.copy_from_slice(&header[at..at + 8]);
        u64::from_le_bytes(bytes)
    };
    (&header[..4] == CHECKPOINT_MAGIC).then(|| (word(4), word(12)))
}

/// The whole batch `seq`.
pub fn batch(seq: u64) -> WriteBatch {
    let mut batch = WriteBatch::new(SITE);
    for i in 0..node_count(seq) {
        batch.put(
            RecordKind::Node,
            RecordId::from_pair(seq, i),
            node_value(seq, i),
        );
    }
    batch.put(RecordKind::SiteMeta, "latest", seq.to_le_bytes().to_vec());
    batch.put(RecordKind::Outbox, seq, outbox_value(seq));
    if seq > 1 {
        batch.delete(RecordKind::Outbox, seq - 1);
    }
    batch.put(LOG_KIND, seq, log_value(seq));
    batch.bump_map_version().for_session(SESSION, seq);
    batch
}
