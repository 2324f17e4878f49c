//! `evermap-demo demo` end to end on a small budget: the server on sled, two robots over loopback zenoh
//! (the default) or gRPC, a short mapping session and one cleaning session each. Bounded by the demo's own timeouts (every wait
//! in it is capped) and by nextest's slow-test timeout (`.config/nextest.toml`: terminated after 20
//! minutes).

use std::process::Command;

#[test]
fn the_demo_maps_relocalizes_and_reaches_every_robot_over_zenoh() {
    demo_reaches_every_robot("zenoh");
}

#[test]
fn the_demo_maps_relocalizes_and_reaches_every_robot_over_grpc() {
    demo_reaches_every_robot("grpc");
}

fn demo_reaches_every_robot(transport: &str) {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("demo");
    let status = Command::new(env!("CARGO_BIN_EXE_evermap-demo"))
        .args(["demo", "--agents", "2", "--sessions-per-agent", "1"])
        .args(["--transport", transport])
        .args(["--session-duration-s", "20", "--mapping-duration-s", "120"])
        .arg("--out")
        .arg(&out)
        .status()
        .expect("run the demo");
    assert!(status.success(), "{status:?}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report"))
            .expect("json");
    eprintln!("{report:#}");
    assert_eq!(report["transport"].as_str(), Some(transport));
    let version = report["final_version"].as_u64().expect("version");
    assert!(version > 10, "{version}");
    // Every robot's cache caught up with the final version through Watch + deltas.
    for at in report["agents_at_version"].as_array().expect("agents") {
        assert_eq!(at.as_u64(), Some(version));
    }
    assert_eq!(report["counts"]["sessions"].as_u64(), Some(3));
    // Nothing left undelivered, and every later session placed by its robot within the initialization
    // window, correctly: the robot navigates with its tentative placement while probation decides whether
    // its submaps join the map (issue 14 §3). On this 2-minute map a 20 s session may end unconfirmed (then
    // dropped from the map), so commits are not required here (measured: robot 1's session placed 0.04 m
    // off got no confirming match; robot 2's committed after 12.9 s; the release demo: every session placed
    // 0.02–0.03 m off within 2.3 s, committed within 14.3 s).
    let mut later = 0;
    let mut initialized = 0;
    for session in report["sessions"].as_array().expect("sessions") {
        assert_eq!(session["left_in_outbox"].as_u64(), Some(0), "{session}");
        if session["session"].as_u64() != Some(0) {
            assert!(
                session["placed_tentatively"].as_bool().expect("bool"),
                "{session}"
            );
            later += 1;
            initialized += usize::from(session["score"]["initialized"].as_bool().expect("bool"));
        }
    }
    assert_eq!(initialized, later, "{report:#}");
    assert_eq!(report["wrong_placements"].as_u64(), Some(0));
    // The robots' own estimates at the time of each node (the scoring module's MRCL): measured 0.888,
    // the held-back nodes before the start is decided count as lost.
    let mrcl = report["mrcl"].as_f64().expect("f64");
    assert!(mrcl > 0.8, "MRCL {mrcl}");
    assert!(out.join("map.png").exists() && out.join("map_change.png").exists());
    assert!(
        std::fs::read_dir(out.join("maps")).expect("maps").count() >= 1,
        "a map picture per (throttled) version"
    );
}
