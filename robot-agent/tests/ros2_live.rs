//! Live ROS 2 over zenoh against an independent robot: `scripts/ros2_live_robot.py` (Python, `rosbags` +
//! `eclipse-zenoh`, no evermap code) replays an excerpt of the MIT CSAIL recording (rosbag2) live under
//! rmw_zenoh's key expressions on 127.0.0.1 (multicast scouting off), and decodes what the agent sends
//! back. The agent maps it through the same SLAM driver as a file, and the live trajectory must equal
//! the file run's on the same excerpt; nothing may be dropped; the map, the pose and `map -> odom` must
//! reach the robot and decode there, and a late query for the map must get it.
//!
//! The Python environment is `target/ros2-venv` (`bash scripts/ros2_venv.sh`; this test runs it when the venv is missing);
//! `EVERMAP_ROS2_PYTHON` names another interpreter.

#![allow(
    clippy::unwrap_used,
    reason = "test helpers: a failure to read or write is the test's failure"
)]

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use mapping::sensor::Timestamp;
use robot_agent::offline_slam::{SlamConfig, run_offline, run_slam};
use robot_agent::ros2_publisher::{Ros2Publisher, Ros2PublisherOptions, Ros2SlamPublisher};
use robot_agent::source::{LiveRos2Source, Recording, Ros2LiveOptions, StreamEnd, read_recording};
use robot_agent::uplink::ZenohLinkOptions;
use test_support::free_port;

/// Seconds of the recording replayed, and how much faster than real time.
const EXCERPT_S: f64 = 30.0;
const SPEED: f64 = 5.0;

fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `../shared/datasets/<rel>` next to the repository root (worktrees sit at other depths).
fn dataset(rel: &str) -> PathBuf {
    test_support::datasets_dir().join(rel)
}

fn python() -> PathBuf {
    if let Some(path) = std::env::var_os("EVERMAP_ROS2_PYTHON") {
        return PathBuf::from(path);
    }
    let path = workspace().join("target/ros2-venv/bin/python");
    if !path.exists() {
        // The README's test command alone must work on a fresh clone: install the independent robot's
        // packages (pinned, from PyPI) once, as `.ci/run` does.
        let status = std::process::Command::new("bash")
            .arg(workspace().join("scripts/ros2_venv.sh"))
            .current_dir(workspace())
            .stdout(std::process::Stdio::null())
            .status()
            .expect("cannot run scripts/ros2_venv.sh");
        assert!(
            status.success(),
            "scripts/ros2_venv.sh failed ({status}): the live ROS 2 test needs python3 with venv and \
             PyPI reachable"
        );
    }
    assert!(
        path.exists(),
        "{} is missing after scripts/ros2_venv.sh",
        path.display()
    );
    path
}

/// The events of `recording` stamped no later than `until` (the file run on the live excerpt).
fn excerpt(recording: &Recording, until: Timestamp) -> Recording {
    Recording {
        events: recording
            .events
            .iter()
            .filter(|e| e.time() <= until)
            .cloned()
            .collect(),
        base_from_laser: recording.base_from_laser,
        report: recording.report.clone(),
    }
}

#[test]
fn a_live_ros2_robot_is_mapped_as_its_recording_and_gets_its_map_and_pose() {
    let python = python();
    let bag = dataset("rosbag2-derived/mit-csail");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let options = Ros2LiveOptions {
        zenoh: ZenohLinkOptions {
            listen: vec![endpoint.clone()],
            ..ZenohLinkOptions::default()
        },
        ..Ros2LiveOptions::default()
    };
    let end = StreamEnd {
        until_idle_s: 2.0,
        start_timeout_s: 60.0,
    };
    let mut live = LiveRos2Source::open(&options, end).unwrap();
    let publish = Ros2PublisherOptions {
        map_republish_s: 1.0,
        ..Ros2PublisherOptions::default()
    };
    let mut observer =
        Ros2SlamPublisher::new(Ros2Publisher::open(live.session(), 0, &publish).unwrap());

    let out = tempfile::tempdir().unwrap();
    let summary_path = out.path().join("robot.json");
    let mut robot = Command::new(&python)
        .arg(workspace().join("scripts/ros2_live_robot.py"))
        .args(["--bag", bag.to_str().unwrap(), "--connect", &endpoint])
        .args([
            "--speed",
            &SPEED.to_string(),
            "--duration-s",
            &EXCERPT_S.to_string(),
        ])
        .args(["--wait-s", "30", "--linger-s", "40", "--quiet-s", "5"])
        .args(["--summary", summary_path.to_str().unwrap()])
        .spawn()
        .unwrap();

    let config = SlamConfig::default();
    let run = run_slam(&mut live, &config, &mut |_| {}, &mut observer);
    // Keep the agent (its publisher and map queryable) up until the robot has asked and written.
    let deadline = Instant::now() + Duration::from_secs(90);
    let status = loop {
        if let Some(status) = robot.try_wait().unwrap() {
            break Some(status);
        }
        if Instant::now() > deadline {
            let _ = robot.kill();
            break None;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let run = run.unwrap();
    assert!(
        status.is_some_and(|s| s.success()),
        "the Python robot failed: {status:?}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary_path).unwrap()).unwrap();
    let stats = live.stats();
    let published = observer.publisher_mut().stats();
    eprintln!("live stats: {stats:?}\npublished: {published:?}\nrobot: {summary:#}");

    // Nothing dropped: every scan the robot sent reached SLAM.
    let sent_scans = summary["sent"]["/scan"].as_u64().unwrap();
    assert!(sent_scans > 100, "the excerpt has {sent_scans} scans");
    assert_eq!(stats.dropped(), 0, "{stats:?}");
    assert_eq!(stats.topics["/scan"].received, sent_scans);
    assert_eq!(stats.topics["/scan"].decoded, sent_scans);
    assert_eq!(
        stats.topics["/odom"].decoded,
        summary["sent"]["/odom"].as_u64().unwrap()
    );
    assert_eq!(stats.scans_out, sent_scans);
    assert_eq!(stats.topics["/scan"].attachment_invalid, 0);
    assert!(
        stats.extrinsic_source.starts_with("tf "),
        "{}",
        stats.extrinsic_source
    );
    assert_eq!(run.scans as u64, sent_scans);

    // The same trajectory as the file run on the same excerpt (up to the newest stamp the live stream
    // handed on; the robot cut its replay by log time, so a message at the very edge may differ).
    let recording = read_recording(&bag).unwrap();
    let newest = Timestamp(stats.newest_stamp_ns.unwrap());
    let file = run_offline(&excerpt(&recording, newest), &config, &mut |_| {}).unwrap();
    let file_poses: std::collections::BTreeMap<Timestamp, _> =
        file.scan_poses.iter().copied().collect();
    let mut worst = (0.0f64, 0.0f64);
    let mut missing = 0;
    for (t, a) in &run.scan_poses {
        let Some(b) = file_poses.get(t) else {
            missing += 1;
            continue;
        };
        worst.0 = worst
            .0
            .max((a.translation.vector - b.translation.vector).norm());
        worst.1 = worst.1.max((a.rotation.angle() - b.rotation.angle()).abs());
    }
    eprintln!(
        "live {} scans, file {} scans, {missing} live scans not in the file run, worst difference {worst:?}",
        run.scan_poses.len(),
        file.scan_poses.len()
    );
    assert!(missing <= 2 && file.scan_poses.len() <= run.scan_poses.len() + 2);
    assert!(
        worst.0 < 0.02 && worst.1 < 0.01,
        "live and file trajectories differ by {worst:?} (m, rad)"
    );

    // The robot got the map, the pose and map -> odom, and decoded them.
    assert_eq!(summary["undecodable"].as_array().unwrap().len(), 0);
    let map = &summary["last_map"];
    assert_eq!(map["frame_id"], "map");
    assert!((map["resolution"].as_f64().unwrap() - 0.05).abs() < 1e-6);
    assert_eq!(
        map["cells"].as_u64().unwrap(),
        map["width"].as_u64().unwrap() * map["height"].as_u64().unwrap()
    );
    assert!(map["occupied"].as_u64().unwrap() > 200, "{map}");
    assert!(
        map["free"].as_u64().unwrap() > 5 * map["occupied"].as_u64().unwrap(),
        "{map}"
    );
    assert!(summary["maps_received"].as_u64().unwrap() >= 1);
    assert_eq!(summary["map_attachments_valid"], summary["maps_received"]);
    assert_eq!(summary["queried_map"]["cells"], map["cells"]);
    let poses = summary["poses_received"].as_u64().unwrap();
    assert!(poses as usize + 5 >= run.scan_poses.len(), "{poses} poses");
    assert!(summary["map_odom_received"].as_u64().unwrap() >= poses);
    let pose = &summary["last_pose"];
    assert_eq!(pose["frame_id"], "map");
    let (_, last) = run.scan_poses.last().unwrap();
    let dx = pose["x"].as_f64().unwrap() - last.translation.x;
    let dy = pose["y"].as_f64().unwrap() - last.translation.y;
    assert!(dx.hypot(dy) < 0.5, "last pose {pose} vs the run's {last:?}");
    assert!(published.map_versions >= 1);
    assert!(summary["maps_received"].as_u64().unwrap() >= published.map_versions);
}
