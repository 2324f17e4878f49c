//! Recordings: ROS1 bags (whole files through `read_recording`, as the agent reads them), the ROS1 message
//! decoders on their own (faster, so more inputs reach the field decoding) and CARMEN logs.

use std::io::{BufRead as _, BufReader, Cursor};
use std::path::{Path, PathBuf};

use mapping::geometry::{Rigid2, Rigid2Ext as _};
use mapping::sensor::{ImuReading, LaserScan, OdometryReading, SensorEvent};
use robot_agent::source::ros_messages::{DecodeError, PlanarTransform};
use robot_agent::source::{self, Recording, ros_messages};

use super::super::fuzz_target::{FuzzTarget, Verdict};
use super::{SetupError, read_file};

/// Events of the first `scans` scans of the CSAIL bag (and the odometry among them), with an IMU yaw rate
/// after every odometry reading, to write small bags that hold every message type we decode.
fn csail_events(datasets: &Path, scans: usize) -> Result<Recording, SetupError> {
    let path = datasets.join("rosbag1/mit-csail.orig.bag");
    let recording = source::read_recording(&path).map_err(|e| SetupError::Seed {
        path: path.clone(),
        reason: e.to_string(),
    })?;
    let mut events = Vec::new();
    let mut seen = 0;
    for event in &recording.events {
        if let SensorEvent::Scan(_) = event {
            seen += 1;
            if seen > scans {
                break;
            }
        }
        events.push(event.clone());
        if let SensorEvent::Odometry(o) = event {
            events.push(SensorEvent::Imu(ImuReading {
                time: o.time,
                yaw_rate: 0.1,
            }));
        }
    }
    Ok(Recording {
        events,
        ..recording
    })
}

fn written_bag(recording: &Recording) -> Result<Vec<u8>, SetupError> {
    let mut out = Cursor::new(Vec::new());
    source::write_bag(&mut out, &recording.events, &recording.base_from_laser).map_err(|e| {
        SetupError::Seed {
            path: PathBuf::from("<written bag>"),
            reason: e.to_string(),
        }
    })?;
    Ok(out.into_inner())
}

/// A message decoder: payload bytes to one message.
pub(super) type Decoder<T> = fn(&[u8]) -> Result<T, DecodeError>;

/// One encoding's message decoders (ROS1 or ROS 2 CDR), as the message targets run them.
pub(super) struct MessageDecoders {
    pub laser_scan: Decoder<(LaserScan, String)>,
    pub odometry: Decoder<OdometryReading>,
    pub imu: Decoder<ImuReading>,
    pub tf_message: Decoder<Vec<PlanarTransform>>,
    /// The fewest bytes one transform takes in this encoding, if fixed: an accepted message cannot
    /// hold more transforms than its bytes allow.
    pub transform_bytes: Option<usize>,
}

/// Decodes a message payload (`input`'s first byte picks the type) and checks what an accepted one
/// holds: finite geometry, poses and rates, no more elements than bytes.
pub(super) fn checked_message(decoders: &MessageDecoders, input: &[u8]) -> Verdict {
    let Some((&kind, data)) = input.split_first() else {
        return Verdict::Rejected("empty".into());
    };
    match kind % 4 {
        0 => {
            let result = (decoders.laser_scan)(data);
            if let Ok((scan, _)) = &result {
                assert!(
                    scan.angle_min.is_finite()
                        && scan.angle_increment.is_finite()
                        && scan.range_max.is_finite()
                        && scan.range_min.is_finite(),
                    "invariant: non-finite scan geometry"
                );
                assert!(
                    scan.ranges.len() * 4 <= data.len(),
                    "invariant: more ranges than bytes"
                );
            }
            Verdict::of(&result.map_err(|e| e.0))
        }
        1 => {
            let result = (decoders.odometry)(data);
            if let Ok(o) = &result {
                assert!(finite(&o.pose), "invariant: non-finite odometry");
            }
            Verdict::of(&result.map_err(|e| e.0))
        }
        2 => {
            let result = (decoders.imu)(data);
            if let Ok(i) = &result {
                assert!(i.yaw_rate.is_finite(), "invariant: non-finite yaw rate");
            }
            Verdict::of(&result.map_err(|e| e.0))
        }
        _ => {
            let result = (decoders.tf_message)(data);
            if let Ok(transforms) = &result {
                assert!(
                    transforms.iter().all(|t| finite(&t.parent_from_child)),
                    "invariant: non-finite transform"
                );
                if let Some(bytes) = decoders.transform_bytes {
                    assert!(
                        transforms.len() * bytes <= data.len(),
                        "invariant: more transforms than bytes"
                    );
                }
            }
            Verdict::of(&result.map_err(|e| e.0))
        }
    }
}

pub(super) fn finite(pose: &Rigid2) -> bool {
    pose.x().is_finite() && pose.y().is_finite() && pose.theta().is_finite()
}

/// The stamps a ROS1 header (and a CARMEN time) can give, seconds.
pub(super) const ROS1_STAMPS_S: (f64, f64) = (0.0, 4_294_967_296.0);

/// What every accepted recording must satisfy: time order, stamps within `stamps_s` (seconds, the
/// format's range), finite poses and scan geometry.
pub(super) fn check_recording(recording: &Recording, stamps_s: (f64, f64)) {
    assert!(
        finite(&recording.base_from_laser),
        "invariant: non-finite base_from_laser {:?}",
        recording.base_from_laser
    );
    for pair in recording.events.windows(2) {
        assert!(
            pair[0].time() <= pair[1].time(),
            "invariant: events out of time order"
        );
    }
    for event in &recording.events {
        let t = event.time().as_secs_f64();
        assert!(
            (stamps_s.0..=stamps_s.1).contains(&t),
            "invariant: stamp {t} s outside the format's time range"
        );
        match event {
            SensorEvent::Scan(scan) => assert!(
                scan.angle_min.is_finite()
                    && scan.angle_increment.is_finite()
                    && scan.range_max.is_finite()
                    && scan.range_min.is_finite(),
                "invariant: non-finite scan geometry at {}",
                scan.time
            ),
            SensorEvent::Odometry(o) => assert!(
                finite(&o.pose),
                "invariant: non-finite odometry pose {:?} at {}",
                o.pose,
                o.time
            ),
            SensorEvent::Imu(i) => assert!(
                i.yaw_rate.is_finite(),
                "invariant: non-finite yaw rate at {}",
                i.time
            ),
        }
    }
}

/// Whole ROS1 bags, read from a file as `evermap-agent` reads them (the `rosbag` crate maps the file).
pub fn ros1_bag(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    // Small bags first: their header and chunk fields are a larger share of the bytes mutations hit.
    let mut seeds = vec![
        written_bag(&csail_events(datasets, 1)?)?,
        written_bag(&csail_events(datasets, 3)?)?,
        written_bag(&csail_events(datasets, 12)?)?,
    ];
    for name in [
        "rosbag1/mit-csail.orig.bag",
        "rosbag1/laser_scan_matcher_demo_2022.bag",
        "rosbag1/laser_scan_matcher_demo_2012_nonstd_index.bag",
        "rosbag1/laser_scan_sparsifier_demo_rosrecord_v1.2.bag",
    ] {
        seeds.push(read_file(&datasets.join(name))?);
    }
    let dir = tempfile::tempdir().map_err(|e| SetupError::Seed {
        path: std::env::temp_dir(),
        reason: e.to_string(),
    })?;
    let path = dir.path().join("input.bag");
    let mut target = FuzzTarget::new(
        "ros1_bag",
        "ROS1 bag files (rosbag crate + our prescan and message decoders)",
        seeds,
        false,
        Box::new(move |input| {
            let _keep = &dir;
            if let Err(e) = std::fs::write(&path, input) {
                return Verdict::Rejected(format!("cannot write the input file: {e}"));
            }
            let result = source::read_recording(&path);
            if let Ok(recording) = &result {
                check_recording(recording, ROS1_STAMPS_S);
            }
            Verdict::of(&result)
        }),
    );
    // Chunks decompress (bz2: ~5× on laser data), and `rosbag` reserves a chunk's declared size, which
    // the reader caps at `MAX_CHUNK_BYTES` (256 MiB): allow that, never gigabytes.
    target.heap_per_input_byte = 256;
    target.base_heap_bytes = 300 << 20;
    Ok(target)
}

/// Message payloads of the first messages of each type in a bag, tagged by type (0 scan, 1 odometry,
/// 2 IMU, 3 TF).
fn bag_messages(bag: &Path, per_type: usize) -> Result<Vec<Vec<u8>>, SetupError> {
    use rosbag::{ChunkRecord, MessageRecord, RosBag};
    let seed_error = |reason: String| SetupError::Seed {
        path: bag.to_path_buf(),
        reason,
    };
    let bag_file = RosBag::new(bag).map_err(|e| seed_error(e.to_string()))?;
    let mut kinds = std::collections::BTreeMap::new();
    let mut counts = [0_usize; 4];
    let mut out = Vec::new();
    for record in bag_file.chunk_records() {
        let ChunkRecord::Chunk(chunk) = record.map_err(|e| seed_error(e.to_string()))? else {
            continue;
        };
        for message in chunk.messages() {
            match message.map_err(|e| seed_error(e.to_string()))? {
                MessageRecord::Connection(c) => {
                    let kind: Option<u8> = match c.tp {
                        "sensor_msgs/LaserScan" => Some(0),
                        "nav_msgs/Odometry" => Some(1),
                        "sensor_msgs/Imu" => Some(2),
                        "tf2_msgs/TFMessage" | "tf/tfMessage" => Some(3),
                        _ => None,
                    };
                    if let Some(kind) = kind {
                        kinds.insert(c.id, kind);
                    }
                }
                MessageRecord::MessageData(m) => {
                    if let Some(&kind) = kinds.get(&m.conn_id)
                        && counts[usize::from(kind)] < per_type
                    {
                        counts[usize::from(kind)] += 1;
                        let mut tagged = vec![kind];
                        tagged.extend_from_slice(m.data);
                        out.push(tagged);
                    }
                }
            }
        }
        if counts.iter().all(|&c| c >= per_type) {
            break;
        }
    }
    Ok(out)
}

/// The ROS1 message decoders (`LaserScan`, `Odometry`, `Imu`, `TFMessage`) on raw payloads: the first byte
/// picks the type.
pub fn ros1_messages(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let mut seeds = bag_messages(&datasets.join("rosbag1/mit-csail.orig.bag"), 3)?;
    let dir = tempfile::tempdir().map_err(|e| SetupError::Seed {
        path: std::env::temp_dir(),
        reason: e.to_string(),
    })?;
    let small = dir.path().join("small.bag");
    std::fs::write(&small, written_bag(&csail_events(datasets, 3)?)?).map_err(|e| {
        SetupError::Seed {
            path: small.clone(),
            reason: e.to_string(),
        }
    })?;
    seeds.extend(bag_messages(&small, 2)?);
    Ok(FuzzTarget::new(
        "ros1_messages",
        "ROS1 LaserScan / Odometry / Imu / TFMessage payloads",
        seeds,
        false,
        Box::new(|input| {
            checked_message(
                &MessageDecoders {
                    laser_scan: ros_messages::laser_scan,
                    odometry: ros_messages::odometry,
                    imu: ros_messages::imu,
                    tf_message: ros_messages::tf_message,
                    transform_bytes: None,
                },
                input,
            )
        }),
    ))
}

/// The first `lines` lines of a text file (gzip-compressed when it ends in `.gz`).
fn head_lines(path: &Path, lines: usize) -> Result<Vec<u8>, SetupError> {
    let bytes = read_file(path)?;
    let reader: Box<dyn std::io::BufRead> = if path.extension().is_some_and(|e| e == "gz") {
        Box::new(BufReader::new(flate2::read::MultiGzDecoder::new(
            Cursor::new(bytes),
        )))
    } else {
        Box::new(BufReader::new(Cursor::new(bytes)))
    };
    let mut out = Vec::new();
    for line in reader.lines().take(lines) {
        let line = line.map_err(|e| SetupError::Seed {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        out.extend_from_slice(line.as_bytes());
        out.push(b'\n');
    }
    Ok(out)
}

/// A ROBOTLASER1 line (none of the shared logs has one): 5 beams, 1 remission value.
const ROBOTLASER1_SEED: &str = "ROBOTLASER1 0 -1.5708 3.1416 0.7854 80.0 0.01 0 5 1.0 2.0 3.0 2.0 1.0 \
    1 0.5 0.1 0.0 0.0 1.0 2.0 0.3 0.0 0.0 0.0 0.0 0.0 1000.5 host 1000.5\nODOM 1.0 2.0 0.3 0 0 0 1000.6\n";

/// CARMEN logs (FLASER, ROBOTLASER1, ODOM lines).
pub fn carmen(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let mut seeds = vec![
        head_lines(&datasets.join("carmen/mit-csail.clf"), 24)?,
        ROBOTLASER1_SEED.as_bytes().to_vec(),
    ];
    for name in ["intel", "orebro", "aces"] {
        seeds.push(head_lines(
            &datasets.join(format!("carmen-corrected/{name}-corrected.log.gz")),
            40,
        )?);
    }
    Ok(FuzzTarget::new(
        "carmen",
        "CARMEN logs (FLASER / ROBOTLASER1 / ODOM)",
        seeds,
        true,
        Box::new(|input| {
            let result = source::read_carmen(input, Path::new("fuzz.clf"));
            if let Ok(recording) = &result {
                check_recording(recording, ROS1_STAMPS_S);
            }
            Verdict::of(&result)
        }),
    ))
}
