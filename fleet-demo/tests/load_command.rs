//! `evermap-demo load` on a tiny budget: one site, two robots, 2 minutes of robot time each as two
//! 60 s sessions back to back, replayed 8× faster than real time (15 s of streaming), after one maturing session per robot. Checks that the
//! benchmark runs end to end and that its report is consistent (everything acknowledged, the offline
//! robot's catch-up smaller than the whole map, a row per minute of robot time with its memory — the
//! resident set, the live heap and what holds it — and latency, and the chart); the figures themselves are measured in BENCHMARKS.md.

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
            "120",
            "--session-s",
            "60",
            "--speed",
            "8",
        ])
        .args(["--mapping-duration-s", "60", "--mature-sessions", "1"])
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
    // The mapping session, each robot's maturing session and its two cleaning sessions.
    assert_eq!(report["sessions_per_robot"].as_u64(), Some(2));
    assert_eq!(report["mature_sessions_per_robot"].as_u64(), Some(1));
    assert_eq!(
        report["sites_final"]["store-1"]["sessions"].as_u64(),
        Some(7)
    );
    // The maturing phase's growth: a sample each time the site's session count went up, and one at its
    // end (the mapping session and both robots' maturing sessions).
    let growth = report["maturing_growth"].as_array().expect("growth");
    let last = growth.last().expect("a sample at the end of maturing");
    assert_eq!(last["sessions"].as_u64(), Some(3), "{growth:?}");
    assert!(last["nodes"].as_u64().expect("nodes") > 0, "{last}");
    assert!(
        last["store_disk_mb"].as_f64().expect("disk") > 0.0,
        "{last}"
    );
    assert!(last["version"].as_u64().expect("version") > 0, "{last}");
    // A robot last seen when the site had half its sessions catches up in one delta no larger than the
    // whole map by more than the ids of what was trimmed since (issue 34: at most 1.2×).
    let catch_up = &report["catch_up_after_half_the_sites_life"];
    assert!(
        catch_up["sessions_missed"].as_u64().expect("missed") >= 4,
        "{catch_up}"
    );
    assert!(
        catch_up["submaps_added"].as_u64().expect("added") > 0,
        "{catch_up}"
    );
    let ratio = catch_up["bytes_per_whole_map"].as_f64().expect("ratio");
    assert!(ratio > 0.0 && ratio <= 1.2, "{catch_up}");
    // A row per minute of robot time, each with the memory at its end and the batches of that minute.
    let minutes = report["per_minute_of_robot_time"]["minutes"]
        .as_array()
        .expect("minutes");
    assert_eq!(minutes.len(), 2, "{minutes:?}");
    for minute in minutes {
        assert!(minute["rss_mb"].as_f64().expect("rss") > 10.0, "{minute}");
        // The live heap is counted, and below the resident set; the site's graph and map are sized.
        let memory = &minute["memory"];
        let heap = memory["live_heap_mb"].as_f64().expect("live heap");
        assert!(
            heap > 10.0 && heap < minute["rss_mb"].as_f64().expect("rss"),
            "{minute}"
        );
        let site = &memory["sites"][0];
        assert!(site["nodes"].as_u64().expect("nodes") > 0, "{minute}");
        assert!(
            site["map_grids_mb"].as_f64().expect("map grids") > 0.0,
            "{minute}"
        );
        assert!(
            site["history_grids_mb"].as_f64() >= site["map_grids_mb"].as_f64(),
            "{minute}"
        );
        assert!(
            memory["store_disk_mb"].as_f64().expect("store") > 0.0,
            "{minute}"
        );
        assert!(
            memory["robot_cache_submaps"].as_u64().expect("cache") > 0,
            "{minute}"
        );
        assert!(
            minute["batches"].as_u64().expect("batches") >= 1,
            "{minute}"
        );
        assert!(
            minute["uplink_bytes"].as_u64().expect("bytes") > 0,
            "{minute}"
        );
    }
    let batches: u64 = minutes.iter().filter_map(|m| m["batches"].as_u64()).sum();
    assert!(batches <= report["batches"].as_u64().expect("batches"));
    // One line per finished submap, as many as the report's latencies count, each with its latencies.
    let latencies = std::fs::read_to_string(out.join("submap_latencies.csv")).expect("latencies");
    let mut lines = latencies.lines();
    assert_eq!(
        lines.next(),
        Some("finished_s,site,version,to_ack_s,to_every_robot_s")
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(
        rows.len() as u64,
        report["submap_latency_s"]["submaps"]
            .as_u64()
            .expect("submaps")
    );
    for row in &rows {
        assert_eq!(row.len(), 5, "{row:?}");
        assert!(row[1].starts_with("store-"), "{row:?}");
        let to_ack: f64 = row[3].parse().expect("to ack");
        assert!(to_ack >= 0.0, "{row:?}");
        if row[4] != "undelivered" {
            let to_every: f64 = row[4].parse().expect("to every robot");
            assert!(to_every >= 0.0, "{row:?}");
        }
    }
    let chart = std::fs::read(out.join("minutes.png")).expect("chart");
    assert_eq!(&chart[1..4], b"PNG");
    let resync = &report["resync_after_offline"];
    assert!(
        resync["bytes"].as_u64().expect("bytes") < resync["whole_map_bytes"].as_u64().expect("all"),
        "{resync}"
    );
    assert!(resync["to_version"].as_u64() > resync["from_version"].as_u64());
    assert!(report["server_process"]["cpu_s"].as_f64().expect("cpu") > 0.0);
}
