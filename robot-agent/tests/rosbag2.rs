//! ROS 2 recordings (rosbag2): the shared Freiburg recordings converted to MCAP (zstd chunks) and sqlite3
//! (`../shared/datasets/rosbag2-derived/`, see its README) give exactly the events of their ROS1
//! originals; MCAP chunks uncompressed, zstd or lz4 read the same; bad input gets an error that says
//! what is wrong, never a panic.

#![allow(
    clippy::unwrap_used,
    reason = "test helpers: a failure to read or write is the test's failure"
)]

use std::path::{Path, PathBuf};

use mapping::sensor::SensorEvent;
use robot_agent::source::{Recording, SourceError, read_recording};

/// `../shared/datasets/<rel>` next to the repository root, found by walking up (the main checkout and
/// worktrees sit at different depths).
fn dataset(rel: &str) -> PathBuf {
    test_support::datasets_dir().join(rel)
}

/// The events with equal stamps put in one order (scan, odometry, IMU). Readers keep file order among
/// equal stamps, and the converter wrote ACES's scan, odometry and TF of one instant in another order than
/// the ROS1 bag holds them; the pipeline does not depend on it (LLO takes a scan once odometry at or
/// after its stamp has arrived, and the full runs give the same trajectory file: BENCHMARKS.md).
fn canonical(recording: &Recording) -> Vec<&SensorEvent> {
    let mut events: Vec<&SensorEvent> = recording.events.iter().collect();
    events.sort_by_key(|e| {
        let stream = match e {
            SensorEvent::Scan(_) => 0,
            SensorEvent::Odometry(_) => 1,
            SensorEvent::Imu(_) => 2,
        };
        (e.time(), stream)
    });
    events
}

/// Every event equal, ranges bit for bit (NaN included), each stream in the same order, and the same
/// extrinsic and counts.
fn assert_same(ros1: &Recording, ros2: &Recording, name: &str) {
    assert!(ros1.report.scans > 1000, "{name}: {:?}", ros1.report);
    assert_eq!(ros1.events.len(), ros2.events.len(), "{name}: event count");
    let (events1, events2) = (canonical(ros1), canonical(ros2));
    for (i, (&a, &b)) in events1.iter().zip(&events2).enumerate() {
        match (a, b) {
            (SensorEvent::Scan(a), SensorEvent::Scan(b)) => {
                assert_eq!(a.time, b.time, "{name}: scan {i}");
                assert_eq!(
                    (a.angle_min, a.angle_increment, a.time_increment),
                    (b.angle_min, b.angle_increment, b.time_increment),
                    "{name}: scan {i}"
                );
                assert_eq!(
                    (a.range_min, a.range_max),
                    (b.range_min, b.range_max),
                    "{name}: scan {i}"
                );
                let bits = |s: &[f32]| s.iter().map(|r| r.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&a.ranges), bits(&b.ranges), "{name}: scan {i} ranges");
            }
            (SensorEvent::Odometry(a), SensorEvent::Odometry(b)) => {
                assert_eq!(a, b, "{name}: event {i}");
            }
            (SensorEvent::Imu(a), SensorEvent::Imu(b)) => assert_eq!(a, b, "{name}: event {i}"),
            _ => panic!("{name}: event {i} differs in kind: {a:?} vs {b:?}"),
        }
    }
    assert_eq!(ros1.base_from_laser, ros2.base_from_laser, "{name}");
    assert_eq!(
        ros1.report.extrinsic_source, ros2.report.extrinsic_source,
        "{name}"
    );
    let counts = |r: &Recording| {
        let p = &r.report;
        (
            p.scans,
            p.odometry,
            p.imu,
            p.tf,
            p.skipped_malformed,
            p.duplicates_dropped,
            p.same_stamp_dropped,
        )
    };
    assert_eq!(counts(ros1), counts(ros2), "{name}");
}

#[test]
fn rosbag2_copies_give_the_events_of_their_ros1_originals() {
    for (name, ros2) in [
        ("mit-csail", "rosbag2-derived/mit-csail"),
        ("intel", "rosbag2-derived/intel/metadata.yaml"),
        ("aces", "rosbag2-derived/aces"),
    ] {
        let ros1 = read_recording(&dataset(&format!("rosbag1/{name}.orig.bag"))).unwrap();
        let ros2 = read_recording(&dataset(ros2)).unwrap();
        assert_same(&ros1, &ros2, name);
    }
}

#[test]
fn a_storage_file_reads_on_its_own() {
    for (name, file) in [
        ("mit-csail", "rosbag2-derived/mit-csail/mit-csail.mcap"),
        ("aces", "rosbag2-derived/aces/aces.db3"),
    ] {
        let ros1 = read_recording(&dataset(&format!("rosbag1/{name}.orig.bag"))).unwrap();
        let ros2 = read_recording(&dataset(file)).unwrap();
        assert_same(&ros1, &ros2, file);
    }
}

/// Rewrites an MCAP file's messages with another chunk compression.
fn rewrite_mcap(from: &Path, to: &Path, compression: Option<mcap::Compression>) {
    let bytes = std::fs::read(from).unwrap();
    let mut writer = mcap::WriteOptions::new()
        .compression(compression)
        .profile("ros2")
        .create(std::io::BufWriter::new(std::fs::File::create(to).unwrap()))
        .unwrap();
    let mut channels = std::collections::BTreeMap::new();
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        let message = message.unwrap();
        let channel = *channels.entry(message.channel.id).or_insert_with(|| {
            let schema = message
                .channel
                .schema
                .as_ref()
                .map(|s| writer.add_schema(&s.name, &s.encoding, &s.data).unwrap());
            writer
                .add_channel(
                    schema.unwrap_or(0),
                    &message.channel.topic,
                    &message.channel.message_encoding,
                    &message.channel.metadata,
                )
                .unwrap()
        });
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: message.sequence,
                    log_time: message.log_time,
                    publish_time: message.publish_time,
                },
                &message.data,
            )
            .unwrap();
    }
    writer.finish().unwrap();
}

#[test]
fn mcap_chunks_uncompressed_zstd_or_lz4_read_the_same() {
    let original = dataset("rosbag2-derived/mit-csail/mit-csail.mcap");
    let zstd = read_recording(&original).unwrap();
    let dir = tempfile::tempdir().unwrap();
    for (file, compression) in [
        ("lz4.mcap", Some(mcap::Compression::Lz4)),
        ("none.mcap", None),
    ] {
        let path = dir.path().join(file);
        rewrite_mcap(&original, &path, compression);
        let copy = read_recording(&path).unwrap();
        assert_same(&zstd, &copy, file);
    }
}

/// The error's text, checked to contain every one of `needles`.
fn error_of(path: &Path, needles: &[&str]) -> SourceError {
    let error = match read_recording(path) {
        Ok(r) => panic!("{} read: {:?}", path.display(), r.report),
        Err(e) => e,
    };
    let text = error.to_string();
    for needle in needles {
        assert!(text.contains(needle), "{needle:?} not in: {text}");
    }
    error
}

/// A copy of a rosbag2 folder in a fresh temporary folder, with `metadata.yaml` edited by `edit`.
fn copy_folder(rel: &str, edit: impl Fn(String) -> String) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(dataset(rel)).unwrap() {
        let entry = entry.unwrap();
        let to = dir.path().join(entry.file_name());
        if entry.file_name() == "metadata.yaml" {
            let text = std::fs::read_to_string(entry.path()).unwrap();
            std::fs::write(&to, edit(text)).unwrap();
        } else {
            // Read and write rather than copy: the shared data is read-only and a copy keeps that.
            std::fs::write(&to, std::fs::read(entry.path()).unwrap()).unwrap();
        }
    }
    dir
}

#[test]
fn bad_rosbag2_input_gets_a_clear_error() {
    // A folder without metadata.yaml.
    let dir = copy_folder("rosbag2-derived/mit-csail", |t| t);
    std::fs::remove_file(dir.path().join("metadata.yaml")).unwrap();
    error_of(dir.path(), &["no metadata.yaml", "not a rosbag2 recording"]);

    // A metadata.yaml that is not rosbag2's.
    let dir = copy_folder("rosbag2-derived/mit-csail", |_| "version: 9\n".into());
    let error = error_of(
        dir.path(),
        &["metadata.yaml", "rosbag2_bagfile_information"],
    );
    // Reference: issue 35 item 6 — the YAML reader's error stays the source.
    let source = std::error::Error::source(&error).expect("the YAML reader's error");
    assert!(source.is::<serde_yaml::Error>(), "{source:?}");

    // A truncated MCAP, alone and through its folder.
    let dir = copy_folder("rosbag2-derived/mit-csail", |t| t);
    let mcap = dir.path().join("mit-csail.mcap");
    let bytes = std::fs::read(&mcap).unwrap();
    std::fs::write(&mcap, &bytes[..bytes.len() / 2]).unwrap();
    error_of(&mcap, &["MCAP", "truncated"]);
    error_of(dir.path(), &["MCAP", "truncated"]);
    std::fs::write(&mcap, &bytes[..5]).unwrap();
    error_of(&mcap, &["not an MCAP file"]);

    // An MCAP chunk compressed with something unknown (the chunks' `zstd` renamed `zzzz`).
    let dir = copy_folder("rosbag2-derived/mit-csail", |t| t);
    let mcap = dir.path().join("mit-csail.mcap");
    let renamed = replace_all(&bytes, b"\x04\x00\x00\x00zstd", b"\x04\x00\x00\x00zzzz");
    assert_ne!(renamed, bytes);
    std::fs::write(&mcap, &renamed).unwrap();
    error_of(&mcap, &["compressed with `zzzz`", "zstd or lz4"]);

    // rosbag2's own compression: unknown, and zstd (not read; said so).
    let dir = copy_folder("rosbag2-derived/mit-csail", |t| {
        t.replace("compression_format: ''", "compression_format: brotli")
            .replace("compression_mode: ''", "compression_mode: FILE")
    });
    error_of(dir.path(), &["unknown rosbag2 compression format `brotli`"]);
    let dir = copy_folder("rosbag2-derived/mit-csail", |t| {
        t.replace("compression_format: ''", "compression_format: zstd")
            .replace("compression_mode: ''", "compression_mode: MESSAGE")
    });
    error_of(dir.path(), &["ros2 bag decompress"]);

    // An unknown storage plugin.
    let dir = copy_folder("rosbag2-derived/mit-csail", |t| {
        t.replace("storage_identifier: mcap", "storage_identifier: hdf5")
    });
    error_of(dir.path(), &["storage `hdf5`"]);

    // metadata.yaml and the storage disagree on a topic's type.
    let dir = copy_folder("rosbag2-derived/mit-csail", |t| {
        t.replace(
            "type: sensor_msgs/msg/LaserScan",
            "type: sensor_msgs/msg/PointCloud2",
        )
    });
    error_of(
        dir.path(),
        &[
            "/scan",
            "sensor_msgs/msg/LaserScan",
            "sensor_msgs/msg/PointCloud2",
            "metadata.yaml",
        ],
    );

    // A conventional topic with another type than evermap reads there.
    let dir = copy_folder("rosbag2-derived/aces", |t| {
        t.replace("type: nav_msgs/msg/Odometry", "type: std_msgs/msg/String")
    });
    let db3 = dir.path().join("aces.db3");
    let db = rusqlite::Connection::open(&db3).unwrap();
    db.execute(
        "UPDATE topics SET type = 'std_msgs/msg/String' WHERE name = '/odom'",
        [],
    )
    .unwrap();
    drop(db);
    let error = error_of(
        &db3,
        &["/odom", "std_msgs/msg/String", "nav_msgs/msg/Odometry"],
    );
    assert!(matches!(error, SourceError::TopicType { .. }), "{error:?}");
    error_of(dir.path(), &["/odom", "std_msgs/msg/String"]);

    // A .db3 that is not SQLite, and one that is SQLite but not rosbag2.
    let dir = tempfile::tempdir().unwrap();
    let fake = dir.path().join("fake.db3");
    std::fs::write(&fake, "this is not a database\n").unwrap();
    error_of(&fake, &["not an SQLite database"]);
    let empty = dir.path().join("empty.db3");
    rusqlite::Connection::open(&empty)
        .unwrap()
        .execute("CREATE TABLE t (x INTEGER)", [])
        .unwrap();
    error_of(&empty, &["topics", "rosbag2"]);
}

fn replace_all(bytes: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    let mut out = bytes.to_vec();
    let mut i = 0;
    while i + from.len() <= out.len() {
        if &out[i..i + from.len()] == from {
            out[i..i + from.len()].copy_from_slice(to);
            i += from.len();
        } else {
            i += 1;
        }
    }
    out
}
