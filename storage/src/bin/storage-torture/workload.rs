//! The deterministic workload of the kill -9 test, shared by the `storage-torture` writer and the checker in
//! `tests/kill_nine.rs` (which includes this file with `#[path]`).
//!
//! Batch `seq` (1, 2, ...) of site [`SITE`], conditional on session [`SESSION`] sequence number `seq`:
//! - puts `node_count(seq)` Node records `(seq, i)` with `node_value(seq, i)` (16 B to 1 KiB, one in 128 of 20-100 KiB
//!   so sled's large-value path is exercised too);
//! - overwrites SiteMeta `"latest"` with `seq`;
//! - puts Outbox `seq` and deletes Outbox `seq - 1`;
//! - bumps the map version.
//!
//! So after batches 1..=n exactly: map version n, session n, latest n, a single Outbox record `n`, and the
//! Node records of batches 1..=n and no others. Any partial batch breaks one of these.

use storage::{RecordId, RecordKind, WriteBatch};

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
    let mut state = seed;
    (0..len)
        .map(|_| {
            state = mix(state);
            state as u8
        })
        .collect()
}

/// Value of Outbox record `seq`.
pub fn outbox_value(seq: u64) -> Vec<u8> {
    format!("upload {seq}").into_bytes()
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
    batch.bump_map_version().for_session(SESSION, seq);
    batch
}
