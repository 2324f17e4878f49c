//! CDR alignment on rosbag2's own test recordings (`test_msgs/msg/BasicTypes` and `Arrays`, from
//! rosbag2's test suite, in `../shared/datasets/rosbag2/`): every field of every message is decoded
//! with [`CdrReader`] and compared with the values the messages' definitions give them (the `*_default`
//! arrays and `test_msgs/msg/Defaults`), and each payload must be consumed to its last byte. A reader that
//! aligned from the start of the buffer instead of the end of the encapsulation header, or that forgot
//! the padding before a nested struct's 8-byte field, fails here.

use std::path::PathBuf;

use super::*;
use crate::source::cdr_reader::CdrReader;
use crate::source::ros_messages::DecodeError;

fn dataset(rel: &str) -> PathBuf {
    test_support::datasets_dir().join(rel)
}

/// Keeps every raw message with its topic's type.
#[derive(Default)]
struct Raw {
    types: BTreeMap<String, String>,
    messages: Vec<(String, Vec<u8>)>,
}

impl Visitor for Raw {
    fn topic(&mut self, topic: &StoredTopic<'_>) -> Result<RosKind, SourceError> {
        assert_eq!(topic.serialization, "cdr");
        self.types
            .insert(topic.name.to_string(), topic.type_name.to_string());
        Ok(RosKind::Other)
    }
    fn message(&mut self, _kind: RosKind, topic: &str, _log_time_ns: u64, data: &[u8]) {
        self.messages
            .push((self.types[topic].clone(), data.to_vec()));
    }
    fn unknown_topic(&mut self, topic_id: i64, _log_time_ns: i64) {
        panic!("unknown topic id {topic_id}");
    }
}

/// `test_msgs/msg/BasicTypes` (and `Defaults`, the same fields), as the values' bit patterns.
#[derive(Debug, PartialEq)]
#[allow(
    clippy::struct_field_names,
    reason = "the field names of test_msgs/msg/BasicTypes"
)]
struct Basic {
    bool_value: bool,
    byte_value: u8,
    char_value: u8,
    float32_value: f32,
    float64_value: f64,
    int8_value: i8,
    uint8_value: u8,
    int16_value: i16,
    uint16_value: u16,
    int32_value: i32,
    uint32_value: u32,
    int64_value: i64,
    uint64_value: u64,
}

fn basic(r: &mut CdrReader<'_>) -> Result<Basic, DecodeError> {
    Ok(Basic {
        bool_value: r.bool("bool")?,
        byte_value: r.u8("byte")?,
        char_value: r.u8("char")?,
        float32_value: r.f32("float32")?,
        float64_value: r.f64("float64")?,
        int8_value: r.i8("int8")?,
        uint8_value: r.u8("uint8")?,
        int16_value: r.i16("int16")?,
        uint16_value: r.u16("uint16")?,
        int32_value: r.i32("int32")?,
        uint32_value: r.u32("uint32")?,
        int64_value: r.i64("int64")?,
        uint64_value: r.u64("uint64")?,
    })
}

/// The values `test_msgs/msg/Defaults` declares.
const DEFAULTS: Basic = Basic {
    bool_value: true,
    byte_value: 50,
    char_value: 100,
    float32_value: 1.125,
    float64_value: 1.125,
    int8_value: -50,
    uint8_value: 200,
    int16_value: -1000,
    uint16_value: 2000,
    int32_value: -30000,
    uint32_value: 60000,
    int64_value: -40000000,
    uint64_value: 50000000,
};

fn three<T>(
    r: &mut CdrReader<'_>,
    read: impl Fn(&mut CdrReader<'_>) -> Result<T, DecodeError>,
) -> Result<Vec<T>, DecodeError> {
    (0..3).map(|_| read(r)).collect()
}

/// The `*_default` arrays of `test_msgs/msg/Arrays`, checked against their declared values.
fn check_default_arrays(r: &mut CdrReader<'_>) -> Result<(), DecodeError> {
    assert_eq!(three(r, |r| r.bool("b"))?, [false, true, false]);
    assert_eq!(three(r, |r| r.u8("byte"))?, [0, 1, 255]);
    assert_eq!(three(r, |r| r.u8("char"))?, [0, 1, 127]);
    assert_eq!(three(r, |r| r.f32("f32"))?, [1.125, 0.0, -1.125]);
    #[allow(
        clippy::approx_constant,
        reason = "the value test_msgs/msg/Arrays declares, not pi"
    )]
    let declared = [3.1415, 0.0, -3.1415];
    assert_eq!(three(r, |r| r.f64("f64"))?, declared);
    assert_eq!(three(r, |r| r.i8("i8"))?, [0, 127, -128]);
    assert_eq!(three(r, |r| r.u8("u8"))?, [0, 1, 255]);
    assert_eq!(three(r, |r| r.i16("i16"))?, [0, i16::MAX, i16::MIN]);
    assert_eq!(three(r, |r| r.u16("u16"))?, [0, 1, u16::MAX]);
    assert_eq!(three(r, |r| r.i32("i32"))?, [0, i32::MAX, i32::MIN]);
    assert_eq!(three(r, |r| r.u32("u32"))?, [0, 1, u32::MAX]);
    assert_eq!(three(r, |r| r.i64("i64"))?, [0, i64::MAX, i64::MIN]);
    assert_eq!(three(r, |r| r.u64("u64"))?, [0, 1, u64::MAX]);
    assert_eq!(
        three(r, |r| r.string("string"))?,
        ["", "max value", "min value"]
    );
    Ok(())
}

/// Decodes one `test_msgs/msg/Arrays` field by field.
fn check_arrays(payload: &[u8]) -> Result<(), DecodeError> {
    let mut r = CdrReader::new(payload)?;
    assert!(r.is_little_endian());
    assert_eq!(
        three(&mut r, |r| r.bool("bool_values"))?,
        [true, false, true]
    );
    // byte .. uint64 arrays: zero in these recordings; read with their alignment.
    for (size, what) in [
        (1, "byte"),
        (1, "char"),
        (4, "float32"),
        (8, "float64"),
        (1, "int8"),
        (1, "uint8"),
        (2, "int16"),
        (2, "uint16"),
        (4, "int32"),
        (4, "uint32"),
        (8, "int64"),
        (8, "uint64"),
    ] {
        r.skip(size, 3, what)?;
    }
    assert_eq!(
        three(&mut r, |r| r.string("string_values"))?,
        ["Complex Hello1", "Complex Hello2", "Complex Hello3"]
    );
    let zero = Basic {
        bool_value: false,
        byte_value: 0,
        char_value: 0,
        float32_value: 0.0,
        float64_value: 0.0,
        int8_value: 0,
        uint8_value: 0,
        int16_value: 0,
        uint16_value: 0,
        int32_value: 0,
        uint32_value: 0,
        int64_value: 0,
        uint64_value: 0,
    };
    for b in three(&mut r, basic)? {
        assert_eq!(b, zero, "basic_types_values");
    }
    // Constants has only constants: IDL gives it one uint8 member.
    three(&mut r, |r| r.u8("constants_values"))?;
    for b in three(&mut r, basic)? {
        assert_eq!(b, DEFAULTS, "defaults_values");
    }
    check_default_arrays(&mut r)?;
    let _alignment_check = r.i32("alignment_check")?;
    assert!(r.remaining() < 4, "{} bytes left over", r.remaining());
    Ok(())
}

fn read_raw(storage: Storage, rel: &str) -> Raw {
    let mut raw = Raw::default();
    read_file(storage, &dataset(rel), &mut raw).unwrap();
    raw
}

#[test]
fn cdr_test_recordings_decode_field_by_field() {
    for (storage, rel) in [
        (Storage::Mcap, "rosbag2/mcap_cdr_test/cdr_test_0.mcap"),
        (Storage::Sqlite3, "rosbag2/sqlite3_cdr_test/cdr_test_0.db3"),
    ] {
        let raw = read_raw(storage, rel);
        let mut counts = (0, 0);
        for (type_name, payload) in &raw.messages {
            match type_name.as_str() {
                "test_msgs/msg/BasicTypes" => {
                    let mut r = CdrReader::new(payload).unwrap();
                    let b = basic(&mut r).unwrap();
                    assert_eq!(b.int32_value, 123, "{rel}: {b:?}");
                    assert!(r.remaining() < 8, "{rel}: {} bytes left", r.remaining());
                    counts.0 += 1;
                }
                "test_msgs/msg/Arrays" => {
                    check_arrays(payload).unwrap_or_else(|e| panic!("{rel}: {e:?}"));
                    counts.1 += 1;
                }
                other => panic!("{rel}: unexpected type {other}"),
            }
        }
        // metadata.yaml: 3 BasicTypes and 4 Arrays.
        assert_eq!(counts, (3, 4), "{rel}");
    }
}

#[test]
fn talker_recordings_hold_std_msgs_strings() {
    for (storage, rel) in [
        (Storage::Mcap, "rosbag2/mcap_talker/talker.mcap"),
        (Storage::Sqlite3, "rosbag2/sqlite3_talker/talker.db3"),
    ] {
        let raw = read_raw(storage, rel);
        let strings: Vec<String> = raw
            .messages
            .iter()
            .filter(|(t, _)| t == "std_msgs/msg/String")
            .map(|(_, p)| CdrReader::new(p).unwrap().string("data").unwrap())
            .collect();
        assert!(!strings.is_empty(), "{rel}");
        assert!(
            strings.iter().all(|s| s.starts_with("Hello, world! ")),
            "{rel}: {strings:?}"
        );
    }
    // As a recording: nothing evermap reads, no error.
    let r = read(&dataset("rosbag2/mcap_talker")).unwrap();
    assert_eq!(r.report.scans, 0);
    assert!(r.report.skipped_other > 0);
}

/// Regression (found reading the reader for the fuzz harness's `rosbag2_metadata` target): a
/// metadata.yaml naming `/dev/zero` as its storage file made the MCAP reader read it until memory ran
/// out; a storage file must be a regular file.
#[test]
fn storage_files_must_be_regular_files() {
    let dir = tempfile::tempdir().unwrap();
    for (storage, file) in [
        ("mcap", "/dev/zero"),
        ("sqlite3", "/dev/null"),
        ("mcap", "."),
    ] {
        let text = format!(
            "rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: {storage}\n  \
             relative_file_paths:\n  - {file}\n"
        );
        std::fs::write(dir.path().join("metadata.yaml"), text).unwrap();
        let error = read(dir.path()).unwrap_err().to_string();
        assert!(error.contains("not a regular file"), "{file}: {error}");
    }
}
