//! `evermap-demo load` on a tiny budget: one site, two robots, 15 s at real time. Checks that the
//! benchmark runs end to end and that its report is consistent (everything acknowledged, the offline
//! robot's catch-up smaller than the whole map); the figures themselves are measured in BENCHMARKS.md.

use std::process::Command;

#[test]
fn the_load_benchmark_streams_everything_and_reports_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("load");
    let status = Command::new(env!("CARGO_BIN_EXE_evermap-demo"))
        .args([
            "load",
            "--agents",
            "2",
            "--sites",
            "1",
            "--duration-s",
            "15",
        ])
        .args(["--mapping-duration-s", "60"])
        .arg("--out")
        .arg(&out)
        .status()
        .expect("run the load benchmark");
    assert!(status.success(), "{status:?}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report"))
            .expect("json");
    eprintln!("{report:#}");
    assert_eq!(report["left_in_outboxes"].as_u64(), Some(0));
    assert_eq!(report["failed_flushes"].as_u64(), Some(0));
    assert!(report["batches"].as_u64().expect("batches") >= 4);
    let per_second = report["uplink_bytes_per_robot_second"]
        .as_f64()
        .expect("bytes");
    assert!(per_second > 100.0, "{per_second}");
    // Mapping session and the two cleaning sessions.
    assert_eq!(
        report["sites_final"]["store-1"]["sessions"].as_u64(),
        Some(3)
    );
    let resync = &report["resync_after_offline"];
    assert!(
        resync["bytes"].as_u64().expect("bytes") < resync["whole_map_bytes"].as_u64().expect("all"),
        "{resync}"
    );
    assert!(resync["to_version"].as_u64() > resync["from_version"].as_u64());
    assert!(report["server_process"]["cpu_s"].as_f64().expect("cpu") > 0.0);
}
