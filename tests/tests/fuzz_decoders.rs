//! The CI slice of the decoder fuzz harness (`tests::fuzz`): every target's seeds and a few hundred mutated
//! inputs (a fixed generator seed, so a failure reproduces), with heap measured per input. Any panic,
//! broken invariant or heap above the target's budget fails the test and prints the smallest reproducer.
//! The long runs are `evermap-fuzz` (see BENCHMARKS.md).

use peak_alloc::PeakAlloc;
use tests::fuzz::{FuzzOptions, fuzz, target};

#[global_allocator]
static HEAP: PeakAlloc = PeakAlloc;

fn slice(name: &str, inputs: u64) {
    let mut target = target(name, &tests::datasets_dir())
        .unwrap_or_else(|e| panic!("cannot set up the {name} target: {e}"));
    assert!(
        !target.seeds.is_empty(),
        "{name}: no seeds, the test would prove nothing"
    );
    let options = FuzzOptions {
        inputs,
        ..FuzzOptions::default()
    };
    let report = fuzz(&mut target, &options);
    assert!(report.heap_measured, "heap was not measured");
    assert_eq!(report.inputs, inputs + target.seeds.len() as u64);
    let described: Vec<String> = report
        .findings
        .iter()
        .map(|f| {
            format!(
                "{:?} at {}: {} (reproducer: {} bytes, {}; starts {:?})",
                f.kind,
                f.key,
                f.message,
                f.input.len(),
                f.recipe,
                String::from_utf8_lossy(&f.input[..f.input.len().min(200)])
            )
        })
        .collect();
    assert!(described.is_empty(), "{name}: {described:#?}");
    // A target that accepts nothing, or refuses nothing, is not exercising its decoder.
    assert!(report.accepted > 0, "{name}: nothing was accepted");
    assert!(report.rejected > 0, "{name}: nothing was refused");
}

#[test]
fn fuzz_ros1_bag() {
    slice("ros1_bag", 100);
}

#[test]
fn fuzz_ros1_messages() {
    slice("ros1_messages", 3000);
}

#[test]
fn fuzz_rosbag2_mcap() {
    slice("rosbag2_mcap", 600);
}

#[test]
fn fuzz_rosbag2_sqlite3() {
    slice("rosbag2_sqlite3", 300);
}

#[test]
fn fuzz_rosbag2_sqlite3_rows() {
    slice("rosbag2_sqlite3_rows", 300);
}

#[test]
fn fuzz_rosbag2_metadata() {
    slice("rosbag2_metadata", 600);
}

#[test]
fn fuzz_ros2_messages() {
    slice("ros2_messages", 3000);
}

#[test]
fn fuzz_ros2_live() {
    slice("ros2_live", 1000);
}

#[test]
fn fuzz_carmen() {
    slice("carmen", 2000);
}

#[test]
fn fuzz_g2o() {
    slice("g2o", 2000);
}

#[test]
fn fuzz_relations() {
    slice("relations", 2000);
}

#[test]
fn fuzz_server_config() {
    slice("server_config", 1000);
}

#[test]
fn fuzz_slam_config() {
    slice("slam_config", 600);
}

#[test]
fn fuzz_sessions_config() {
    slice("sessions_config", 600);
}

#[test]
fn fuzz_agent_config() {
    slice("agent_config", 600);
}

#[test]
fn fuzz_protobuf() {
    slice("protobuf", 3000);
}

#[test]
fn fuzz_zenoh_request() {
    slice("zenoh_request", 1500);
}

#[test]
fn fuzz_zenoh_upload() {
    slice("zenoh_upload", 600);
}

#[test]
fn fuzz_site_archive() {
    slice("site_archive", 1500);
}
