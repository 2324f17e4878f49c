//! The same recording read from ROS1 and from rosbag2 gives the same trajectory: the first 60 s of MIT
//! CSAIL (about 280 scans, with loop closures) from the ROS1 bag and from its MCAP copy
//! (`../shared/datasets/rosbag2-derived/`) through the offline pipeline with the default configuration.
//! The full recordings run in release in docs/BENCHMARK-HISTORY.md (session "rosbag2").

use mapping::sensor::SensorEvent;
use robot_agent::offline_slam::{SlamConfig, run_offline};
use robot_agent::source::{Recording, read_recording};
use tests::datasets_dir;

/// The recording's first `seconds`.
fn first(recording: &Recording, seconds: f64) -> Recording {
    let start = recording.events[0].time();
    Recording {
        events: recording
            .events
            .iter()
            .filter(|e| e.time().seconds_since(start) <= seconds)
            .cloned()
            .collect(),
        base_from_laser: recording.base_from_laser,
        report: recording.report.clone(),
    }
}

#[test]
fn csail_from_ros1_and_from_rosbag2_gives_the_same_trajectory() -> anyhow::Result<()> {
    let ros1 = first(
        &read_recording(&datasets_dir().join("rosbag1/mit-csail.orig.bag"))?,
        60.0,
    );
    let ros2 = first(
        &read_recording(&datasets_dir().join("rosbag2-derived/mit-csail"))?,
        60.0,
    );
    let scans = ros1
        .events
        .iter()
        .filter(|e| matches!(e, SensorEvent::Scan(_)))
        .count();
    assert!(scans > 200, "{scans} scans in the first 60 s");
    let config = SlamConfig::default();
    let a = run_offline(&ros1, &config, &mut |_| {})?;
    let b = run_offline(&ros2, &config, &mut |_| {})?;
    assert_eq!(a.scan_poses.len(), b.scan_poses.len());
    assert!(a.scan_poses.len() > 200, "{} poses", a.scan_poses.len());
    let mut worst = 0.0f64;
    for ((ta, pa), (tb, pb)) in a.scan_poses.iter().zip(&b.scan_poses) {
        assert_eq!(ta, tb);
        let d = pa.inverse() * pb;
        worst = worst
            .max(d.translation.vector.norm())
            .max(d.rotation.angle().abs());
    }
    // The same events in the same order through a deterministic pipeline: the same poses.
    assert!(worst < 1e-9, "trajectories differ by up to {worst}");
    eprintln!(
        "{} poses, {} loop closures, largest difference {worst:e}",
        a.scan_poses.len(),
        a.global.accepted_loop_closures().len()
    );
    Ok(())
}
