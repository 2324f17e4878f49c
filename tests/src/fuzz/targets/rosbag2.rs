//! ROS 2 recordings (rosbag2): lone MCAP and sqlite3 files through `read_recording` as the agent reads
//! them, the sqlite3 reader fed hostile rows and blobs (a valid database whose values are not what
//! rosbag2 writes), `metadata.yaml` in a folder beside its storage files, and the CDR message decoders
//! on their own.
//!
//! Seeds are cut small from `../shared/datasets` so the CI slice stays fast: the first messages of the
//! MCAP copy of MIT CSAIL (`rosbag2-derived/mit-csail`, with an IMU message after each odometry one so
//! every decoder is reached) rewritten with the `mcap` crate's writer, uncompressed and zstd-chunked; the
//! first rows of the sqlite3 copy of ACES; and rosbag2's own small test recordings as they are.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use mapping::sensor::SensorEvent;
use robot_agent::source::{self, CdrWriter, Recording, ros2_messages};

use super::super::fuzz_target::{FuzzTarget, Verdict};
use super::recordings::{MessageDecoders, check_recording, checked_message};

/// The stamps a ROS 2 header can give, seconds: `int32 sec` plus a `uint32 nanosec`.
const ROS2_STAMPS_S: (f64, f64) = (-2_147_483_648.0, 2_147_483_647.0 + 4.294_967_295);
use super::{SetupError, read_file};

fn seed_error(path: impl Into<PathBuf>, reason: impl std::fmt::Display) -> SetupError {
    SetupError::Seed {
        path: path.into(),
        reason: reason.to_string(),
    }
}

/// One message of a cut recording, with its channel.
#[derive(Clone, Debug)]
pub(super) struct CutMessage {
    /// `/scan`.
    pub topic: String,
    /// `sensor_msgs/msg/LaserScan`.
    pub type_name: String,
    /// The schema's encoding and text (`ros2msg`), for the MCAP writer.
    pub schema: (String, Vec<u8>),
    /// Nanoseconds.
    pub log_time: u64,
    /// CDR payload.
    pub data: Vec<u8>,
}

/// An IMU payload at `stamp_ns` with yaw rate 0.1 rad/s (the shared recordings have no IMU).
fn imu_payload(stamp_ns: u64) -> Vec<u8> {
    let mut w = CdrWriter::new();
    let sec = i32::try_from(stamp_ns / 1_000_000_000).unwrap_or(i32::MAX);
    w.u32(sec.cast_unsigned());
    w.u32((stamp_ns % 1_000_000_000) as u32);
    w.string("imu");
    for _ in 0..13 {
        w.f64(0.0);
    }
    for v in [0.0, 0.0, 0.1] {
        w.f64(v);
    }
    w.finish()
}

/// The first messages of the MCAP copy of MIT CSAIL, up to and including its `scans`-th scan, with an
/// IMU message after each odometry message.
pub(super) fn csail_cut(datasets: &Path, scans: usize) -> Result<Vec<CutMessage>, SetupError> {
    let path = datasets.join("rosbag2-derived/mit-csail/mit-csail.mcap");
    let bytes = read_file(&path)?;
    let stream = mcap::MessageStream::new(&bytes).map_err(|e| seed_error(&path, e))?;
    let mut out = Vec::new();
    let mut seen = 0;
    for message in stream {
        let message = message.map_err(|e| seed_error(&path, e))?;
        let (type_name, schema) = message.channel.schema.as_ref().map_or_else(
            || (String::new(), (String::new(), Vec::new())),
            |s| (s.name.clone(), (s.encoding.clone(), s.data.to_vec())),
        );
        let is_odometry = type_name == "nav_msgs/msg/Odometry";
        let is_scan = type_name == "sensor_msgs/msg/LaserScan";
        out.push(CutMessage {
            topic: message.channel.topic.clone(),
            type_name,
            schema,
            log_time: message.log_time,
            data: message.data.to_vec(),
        });
        if is_odometry {
            out.push(CutMessage {
                topic: "/imu".into(),
                type_name: "sensor_msgs/msg/Imu".into(),
                schema: ("ros2msg".into(), Vec::new()),
                log_time: message.log_time,
                data: imu_payload(message.log_time),
            });
        }
        if is_scan {
            seen += 1;
            if seen >= scans {
                break;
            }
        }
    }
    Ok(out)
}

/// `messages` as an MCAP file (ros2 profile), chunks compressed with `compression`.
pub(super) fn write_mcap(
    messages: &[CutMessage],
    compression: Option<mcap::Compression>,
) -> Result<Vec<u8>, SetupError> {
    let error = |e: mcap::McapError| seed_error("<written MCAP>", e);
    let mut writer = mcap::WriteOptions::new()
        .profile("ros2")
        .compression(compression)
        .chunk_size(Some(4096))
        .create(Cursor::new(Vec::new()))
        .map_err(error)?;
    let mut channels: BTreeMap<String, u16> = BTreeMap::new();
    for (sequence, m) in messages.iter().enumerate() {
        let channel_id = if let Some(&id) = channels.get(&m.topic) {
            id
        } else {
            let schema = writer
                .add_schema(&m.type_name, &m.schema.0, &m.schema.1)
                .map_err(error)?;
            let id = writer
                .add_channel(schema, &m.topic, "cdr", &BTreeMap::new())
                .map_err(error)?;
            channels.insert(m.topic.clone(), id);
            id
        };
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: u32::try_from(sequence).unwrap_or(u32::MAX),
                    log_time: m.log_time,
                    publish_time: m.log_time,
                },
                &m.data,
            )
            .map_err(error)?;
    }
    writer.finish().map_err(error)?;
    Ok(writer.into_inner().into_inner())
}

/// A value of a row, as the rows target writes it into SQLite.
#[derive(Clone, Debug)]
enum Value {
    Null,
    Integer(i64),
    Real(f64),
    Text(Vec<u8>),
    Blob(Vec<u8>),
}

impl rusqlite::ToSql for Value {
    fn to_sql(&self) -> rusqlite::Result<rusqlite::types::ToSqlOutput<'_>> {
        use rusqlite::types::{ToSqlOutput, ValueRef};
        Ok(ToSqlOutput::Borrowed(match self {
            Self::Null => ValueRef::Null,
            Self::Integer(v) => ValueRef::Integer(*v),
            Self::Real(v) => ValueRef::Real(*v),
            Self::Text(v) => ValueRef::Text(v),
            Self::Blob(v) => ValueRef::Blob(v),
        }))
    }
}

/// Rows of the `topics` (4 values: id, name, type, serialization_format) and `messages` (3 values:
/// topic_id, timestamp, data) tables, in a compact binary form mutations work on: per row a table byte
/// (even: topics, odd: messages), then per value a type byte (mod 5: null, integer, real, text, blob)
/// and its bytes (8 for numbers, a u32 little-endian length and the bytes for text and blobs; a length
/// past the end takes what is left), so every input is a database.
#[derive(Default)]
struct Rows {
    topics: Vec<[Value; 4]>,
    messages: Vec<[Value; 3]>,
}

fn encode_value(out: &mut Vec<u8>, value: &Value) {
    match value {
        Value::Null => out.push(0),
        Value::Integer(v) => {
            out.push(1);
            out.extend_from_slice(&v.to_le_bytes());
        }
        Value::Real(v) => {
            out.push(2);
            out.extend_from_slice(&v.to_le_bytes());
        }
        Value::Text(v) | Value::Blob(v) => {
            out.push(if matches!(value, Value::Text(_)) {
                3
            } else {
                4
            });
            out.extend_from_slice(&u32::try_from(v.len()).unwrap_or(u32::MAX).to_le_bytes());
            out.extend_from_slice(v);
        }
    }
}

impl Rows {
    fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        for row in &self.topics {
            out.push(0);
            for v in row {
                encode_value(&mut out, v);
            }
        }
        for row in &self.messages {
            out.push(1);
            for v in row {
                encode_value(&mut out, v);
            }
        }
        out
    }

    fn decode(mut input: &[u8]) -> Self {
        fn take<'a>(input: &mut &'a [u8], n: usize) -> &'a [u8] {
            let (head, tail) = input.split_at(n.min(input.len()));
            *input = tail;
            head
        }
        fn value(input: &mut &[u8]) -> Value {
            let Some((&kind, rest)) = input.split_first() else {
                return Value::Null;
            };
            *input = rest;
            let mut eight = [0u8; 8];
            match kind % 5 {
                0 => Value::Null,
                1 | 2 => {
                    let bytes = take(input, 8);
                    eight[..bytes.len()].copy_from_slice(bytes);
                    if kind % 5 == 1 {
                        Value::Integer(i64::from_le_bytes(eight))
                    } else {
                        Value::Real(f64::from_le_bytes(eight))
                    }
                }
                k => {
                    let mut four = [0u8; 4];
                    let bytes = take(input, 4);
                    four[..bytes.len()].copy_from_slice(bytes);
                    let n = u32::from_le_bytes(four) as usize;
                    let bytes = take(input, n).to_vec();
                    if k == 3 {
                        Value::Text(bytes)
                    } else {
                        Value::Blob(bytes)
                    }
                }
            }
        }
        let mut rows = Self::default();
        while let Some((&table, rest)) = input.split_first() {
            input = rest;
            if table % 2 == 0 {
                rows.topics.push(std::array::from_fn(|_| value(&mut input)));
            } else {
                rows.messages
                    .push(std::array::from_fn(|_| value(&mut input)));
            }
        }
        rows
    }

    /// Writes the rows into a new database at `path` (replaced), with rosbag2's tables but no column
    /// types or constraints, so any value reaches the reader.
    fn write(&self, path: &Path) -> rusqlite::Result<()> {
        let _ = std::fs::remove_file(path);
        let mut db = rusqlite::Connection::open(path)?;
        db.execute_batch(
            "PRAGMA journal_mode = OFF; PRAGMA synchronous = OFF;
             CREATE TABLE topics(id, name, type, serialization_format);
             CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id, timestamp, data);",
        )?;
        let transaction = db.transaction()?;
        {
            let mut topic = transaction.prepare("INSERT INTO topics VALUES (?1, ?2, ?3, ?4)")?;
            for row in &self.topics {
                topic.execute(rusqlite::params_from_iter(row.iter()))?;
            }
            let mut message = transaction
                .prepare("INSERT INTO messages (topic_id, timestamp, data) VALUES (?1, ?2, ?3)")?;
            for row in &self.messages {
                message.execute(rusqlite::params_from_iter(row.iter()))?;
            }
        }
        transaction.commit()
    }
}

/// The topics and first `messages` message rows of the sqlite3 copy of ACES.
fn aces_rows(datasets: &Path, messages: usize) -> Result<Rows, SetupError> {
    let path = datasets.join("rosbag2-derived/aces/aces.db3");
    let error = |e: rusqlite::Error| seed_error(&path, e);
    let db = rusqlite::Connection::open_with_flags(
        format!("file:{}?mode=ro&immutable=1", path.display()),
        rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY | rusqlite::OpenFlags::SQLITE_OPEN_URI,
    )
    .map_err(error)?;
    let mut rows = Rows::default();
    let mut topics = db
        .prepare("SELECT id, name, type, serialization_format FROM topics ORDER BY id")
        .map_err(error)?;
    let mut query = topics.query([]).map_err(error)?;
    while let Some(row) = query.next().map_err(error)? {
        let text = |i| -> Result<Value, SetupError> {
            Ok(Value::Text(
                row.get::<_, String>(i).map_err(error)?.into_bytes(),
            ))
        };
        rows.topics.push([
            Value::Integer(row.get(0).map_err(error)?),
            text(1)?,
            text(2)?,
            text(3)?,
        ]);
    }
    let mut statement = db
        .prepare("SELECT topic_id, timestamp, data FROM messages ORDER BY id LIMIT ?1")
        .map_err(error)?;
    let mut query = statement
        .query([i64::try_from(messages).unwrap_or(i64::MAX)])
        .map_err(error)?;
    while let Some(row) = query.next().map_err(error)? {
        rows.messages.push([
            Value::Integer(row.get(0).map_err(error)?),
            Value::Integer(row.get(1).map_err(error)?),
            Value::Blob(row.get(2).map_err(error)?),
        ]);
    }
    Ok(rows)
}

fn temp_dir() -> Result<tempfile::TempDir, SetupError> {
    tempfile::tempdir().map_err(|e| seed_error(std::env::temp_dir(), e))
}

/// What every accepted ROS 2 recording must satisfy: [`check_recording`]'s invariants (time order,
/// finite values), counted events matching the report.
fn check_ros2_recording(recording: &Recording) {
    check_recording(recording, ROS2_STAMPS_S);
    let scans = recording
        .events
        .iter()
        .filter(|e| matches!(e, SensorEvent::Scan(_)))
        .count();
    assert_eq!(scans, recording.report.scans, "invariant: scan count");
}

/// Writes each input to `name` in a temporary folder and reads it with `read_recording`.
fn file_target(
    name: &'static str,
    what: &'static str,
    file_name: &'static str,
    seeds: Vec<Vec<u8>>,
) -> Result<FuzzTarget, SetupError> {
    let dir = temp_dir()?;
    let path = dir.path().join(file_name);
    Ok(FuzzTarget::new(
        name,
        what,
        seeds,
        false,
        Box::new(move |input| {
            let _keep = &dir;
            if let Err(e) = std::fs::write(&path, input) {
                return Verdict::Rejected(format!("cannot write the input file: {e}"));
            }
            let result = source::read_recording(&path);
            if let Ok(recording) = &result {
                check_ros2_recording(recording);
            }
            Verdict::of(&result)
        }),
    ))
}

/// Lone MCAP files, read as `evermap-agent` reads a `.mcap`.
pub fn mcap_files(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let cut = csail_cut(datasets, 2)?;
    let seeds = vec![
        write_mcap(&cut, None)?,
        write_mcap(&cut, Some(mcap::Compression::Zstd))?,
        write_mcap(&cut, Some(mcap::Compression::Lz4))?,
        read_file(&datasets.join("rosbag2/mcap_cdr_test/cdr_test_0.mcap"))?,
        read_file(&datasets.join("rosbag2/mcap_talker/talker.mcap"))?,
    ];
    let mut target = file_target(
        "rosbag2_mcap",
        "rosbag2 MCAP files (mcap crate, chunks uncompressed/zstd/lz4, CDR decoders)",
        "input.mcap",
        seeds,
    )?;
    // Chunks decompress (zstd/lz4: ~10× on laser data), and the reader lets one record be as long as
    // `mcap_storage::max_record_bytes` (at least 64 MiB) before refusing it.
    target.heap_per_input_byte = 256;
    target.base_heap_bytes = 100 << 20;
    Ok(target)
}

/// Lone sqlite3 (`.db3`) files, their bytes mutated, read as `evermap-agent` reads a `.db3`.
pub fn sqlite3_files(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let dir = temp_dir()?;
    let cut = dir.path().join("aces-cut.db3");
    aces_rows(datasets, 12)?
        .write(&cut)
        .map_err(|e| seed_error(&cut, e))?;
    let seeds = vec![
        read_file(&cut)?,
        read_file(&datasets.join("rosbag2/sqlite3_cdr_test/cdr_test_0.db3"))?,
        read_file(&datasets.join("rosbag2/sqlite3_talker/talker.db3"))?,
    ];
    file_target(
        "rosbag2_sqlite3",
        "rosbag2 sqlite3 files, bytes mutated (rusqlite on bundled SQLite, CDR decoders)",
        "input.db3",
        seeds,
    )
}

/// Valid SQLite databases with hostile rows: values of any type in any column, unknown topic ids,
/// mutated CDR blobs.
pub fn sqlite3_rows(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let dir = temp_dir()?;
    let path = dir.path().join("input.db3");
    let seeds = vec![
        aces_rows(datasets, 12)?.encode(),
        aces_rows(datasets, 3)?.encode(),
    ];
    Ok(FuzzTarget::new(
        "rosbag2_sqlite3_rows",
        "rosbag2 sqlite3 rows and blobs of any type and value (written with rusqlite, then read)",
        seeds,
        false,
        Box::new(move |input| {
            let _keep = &dir;
            if let Err(e) = Rows::decode(input).write(&path) {
                return Verdict::Rejected(format!("cannot write the input database: {e}"));
            }
            let result = source::read_recording(&path);
            if let Ok(recording) = &result {
                check_ros2_recording(recording);
            }
            Verdict::of(&result)
        }),
    ))
}

/// `metadata.yaml` (mutated) in a folder beside the storage files its seeds name, read as a folder.
pub fn metadata_files(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let dir = temp_dir()?;
    let write = |name: &str, bytes: &[u8]| {
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).map_err(|e| seed_error(path, e))
    };
    write(
        "mit-csail.mcap",
        &write_mcap(&csail_cut(datasets, 2)?, None)?,
    )?;
    let aces = dir.path().join("aces.db3");
    aces_rows(datasets, 6)?
        .write(&aces)
        .map_err(|e| seed_error(&aces, e))?;
    for (folder, file) in [
        ("rosbag2/mcap_cdr_test", "cdr_test_0.mcap"),
        ("rosbag2/sqlite3_talker", "talker.db3"),
    ] {
        write(file, &read_file(&datasets.join(folder).join(file))?)?;
    }
    let mut seeds = Vec::new();
    for folder in [
        "rosbag2-derived/mit-csail",
        "rosbag2-derived/aces",
        "rosbag2/mcap_cdr_test",
        "rosbag2/sqlite3_talker",
    ] {
        seeds.push(read_file(&datasets.join(folder).join("metadata.yaml"))?);
    }
    let metadata = dir.path().join("metadata.yaml");
    Ok(FuzzTarget::new(
        "rosbag2_metadata",
        "rosbag2 metadata.yaml, read as a folder with its storage files",
        seeds,
        true,
        Box::new(move |input| {
            if let Err(e) = std::fs::write(&metadata, input) {
                return Verdict::Rejected(format!("cannot write metadata.yaml: {e}"));
            }
            let result = source::read_recording(dir.path());
            if let Ok(recording) = &result {
                check_ros2_recording(recording);
            }
            Verdict::of(&result)
        }),
    ))
}

/// Message payloads of `messages`, tagged by type (0 scan, 1 odometry, 2 IMU, 3 TF), at most
/// `per_type` of each.
pub(super) fn tagged_payloads(messages: &[CutMessage], per_type: usize) -> Vec<Vec<u8>> {
    let mut counts = [0_usize; 4];
    let mut out = Vec::new();
    for m in messages {
        let kind: u8 = match m.type_name.as_str() {
            "sensor_msgs/msg/LaserScan" => 0,
            "nav_msgs/msg/Odometry" => 1,
            "sensor_msgs/msg/Imu" => 2,
            "tf2_msgs/msg/TFMessage" => 3,
            _ => continue,
        };
        if counts[usize::from(kind)] < per_type {
            counts[usize::from(kind)] += 1;
            let mut tagged = vec![kind];
            tagged.extend_from_slice(&m.data);
            out.push(tagged);
        }
    }
    out
}

/// The CDR decoders (`LaserScan`, `Odometry`, `Imu`, `TFMessage`) on raw payloads: the first byte picks
/// the type.
pub fn ros2_messages(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let seeds = tagged_payloads(&csail_cut(datasets, 3)?, 3);
    Ok(FuzzTarget::new(
        "ros2_messages",
        "ROS 2 CDR LaserScan / Odometry / Imu / TFMessage payloads",
        seeds,
        false,
        Box::new(|input| {
            checked_message(
                &MessageDecoders {
                    laser_scan: ros2_messages::laser_scan,
                    odometry: ros2_messages::odometry,
                    imu: ros2_messages::imu,
                    tf_message: ros2_messages::tf_message,
                    transform_bytes: Some(72),
                },
                input,
            )
        }),
    ))
}
