//! Real-data reader tests on the shared benchmark recordings.

use std::path::PathBuf;

use mapping::sensor::SensorEvent;
use robot_agent::source::{SourceError, read_recording};

/// `../shared/datasets/<rel>` next to the repository root, found by walking up (the main checkout and
/// worktrees sit at different depths).
fn dataset(rel: &str) -> PathBuf {
    test_support::datasets_dir().join(rel)
}

#[test]
fn benchmark_bags_have_the_documented_counts() {
    for (file, scans, beams, odometry) in [
        ("rosbag1/intel.orig.bag", 13631, 180, 26915),
        ("rosbag1/aces.orig.bag", 7374, 180, 7375),
        ("rosbag1/mit-csail.orig.bag", 1988, 361, 1988),
    ] {
        let r = read_recording(&dataset(file)).unwrap();
        let report = &r.report;
        assert_eq!(report.scans, scans, "{file}: {report:?}");
        assert_eq!(
            report.odometry + report.same_stamp_dropped + report.duplicates_dropped,
            odometry,
            "{file}: {report:?}"
        );
        let SensorEvent::Scan(first) = r
            .events
            .iter()
            .find(|e| matches!(e, SensorEvent::Scan(_)))
            .unwrap()
        else {
            unreachable!()
        };
        assert_eq!(first.ranges.len(), beams, "{file}");
        assert!(
            r.events.windows(2).all(|w| w[0].time() <= w[1].time()),
            "{file}: not sorted"
        );
    }
}

#[test]
fn csail_log_and_bag_give_the_same_events() {
    let bag = read_recording(&dataset("rosbag1/mit-csail.orig.bag")).unwrap();
    let clf = read_recording(&dataset("carmen/mit-csail.clf")).unwrap();
    let scans = |r: &robot_agent::source::Recording| -> Vec<mapping::sensor::LaserScan> {
        r.events
            .iter()
            .filter_map(|e| {
                if let SensorEvent::Scan(s) = e {
                    Some(s.clone())
                } else {
                    None
                }
            })
            .collect()
    };
    let (a, b) = (scans(&bag), scans(&clf));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert!(
            (x.time.0 - y.time.0).abs() <= 5_000,
            "{} vs {}",
            x.time,
            y.time
        );
        assert_eq!(x.ranges.len(), y.ranges.len());
        assert!(
            x.ranges
                .iter()
                .zip(&y.ranges)
                .all(|(p, q)| (p - q).abs() < 1e-4)
        );
        assert!(
            (x.angle_min - y.angle_min).abs() < 1e-6
                && (x.angle_increment - y.angle_increment).abs() < 1e-7
        );
        assert!(
            (x.range_max - y.range_max).abs() < 1e-6 && (x.range_min - y.range_min).abs() < 1e-6
        );
    }
    let odom = |r: &robot_agent::source::Recording| -> Vec<mapping::sensor::OdometryReading> {
        r.events
            .iter()
            .filter_map(|e| {
                if let SensorEvent::Odometry(o) = e {
                    Some(o.clone())
                } else {
                    None
                }
            })
            .collect()
    };
    let (a, b) = (odom(&bag), odom(&clf));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert!((x.time.0 - y.time.0).abs() <= 5_000);
        assert!((x.pose.translation.vector - y.pose.translation.vector).norm() < 1e-4);
        assert!((x.pose.rotation.angle() - y.pose.rotation.angle()).abs() < 1e-4);
    }
    let d = bag.base_from_laser.inverse() * clf.base_from_laser;
    assert!(
        d.translation.vector.norm() < 1e-4 && d.rotation.angle().abs() < 1e-4,
        "{:?} vs {:?}",
        bag.base_from_laser,
        clf.base_from_laser
    );
}

#[test]
fn robustness_bags() {
    let ok = read_recording(&dataset("rosbag1/laser_scan_matcher_demo_2022.bag")).unwrap();
    assert_eq!(ok.report.scans, 360);
    let SensorEvent::Scan(s) = &ok.events[0] else {
        panic!("first event is not a scan")
    };
    assert_eq!(s.ranges.len(), 681);
    // Its index record declares 20 bytes per entry where format 2.0 has 12, so nothing after it can be
    // located: refused with an error that says so (the issue allows reading or a clear refusal).
    let nonstd = read_recording(&dataset(
        "rosbag1/laser_scan_matcher_demo_2012_nonstd_index.bag",
    ))
    .unwrap_err();
    assert!(
        nonstd.to_string().contains("non-standard index record"),
        "{nonstd}"
    );
    let legacy = read_recording(&dataset(
        "rosbag1/laser_scan_sparsifier_demo_rosrecord_v1.2.bag",
    ))
    .unwrap_err();
    assert!(matches!(legacy, SourceError::Unsupported { .. }));
    assert!(legacy.to_string().contains("ROSRECORD V1.2"), "{legacy}");
}

#[test]
fn truncated_bag_is_an_error_not_a_panic() {
    let bytes = std::fs::read(dataset("rosbag1/mit-csail.orig.bag")).unwrap();
    let dir = std::env::temp_dir().join(format!("evermap-trunc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for cut in [20, 4_000, bytes.len() / 2] {
        let path = dir.join(format!("cut{cut}.bag"));
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let err = read_recording(&path).unwrap_err();
        assert!(
            matches!(err, SourceError::Malformed { .. }),
            "cut {cut}: {err}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn corrected_carmen_logs_parse() {
    for f in [
        "intel-corrected.log.gz",
        "aces-corrected.log.gz",
        "csail-corrected.log.gz",
    ] {
        let r = read_recording(&dataset(&format!("carmen-corrected/{f}"))).unwrap();
        // Stamps are printed with ~6 significant digits, so many scans share a stamp and are dropped.
        let lines = r.report.scans + r.report.same_stamp_dropped + r.report.duplicates_dropped;
        assert!(lines > 800, "{f}: {:?}", r.report);
        assert_eq!(
            r.report.skipped_malformed, 0,
            "{f}: {:?}",
            r.report.problems
        );
    }
}
