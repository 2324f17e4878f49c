//! What links what (ARCHITECTURE.md's crate table, STYLE.md §1), read from `cargo metadata`: each crate's
//! closure over normal dependencies (what its binary or library links; dev- and build-dependencies left
//! out). The server links no robot code and no simulator; the robot agent no simulator and no server; the
//! algorithm core and the simulator no I/O shell.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;

use serde_json::Value;

/// Every package's normal dependencies, by package name, as cargo resolved them.
fn normal_dependencies() -> BTreeMap<String, BTreeSet<String>> {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".to_owned());
    // Resolved for this machine only: what a binary built here links, and no download of the packages
    // other platforms would need (`--offline` finds only what the build fetched).
    let version = Command::new(&cargo)
        .arg("-vV")
        .output()
        .expect("cargo -vV runs");
    let version = String::from_utf8_lossy(&version.stdout);
    let host = version
        .lines()
        .find_map(|line| line.strip_prefix("host: "))
        .expect("cargo -vV names the host");
    let output = Command::new(&cargo)
        .args(["metadata", "--format-version", "1", "--offline", "--locked"])
        .args(["--filter-platform", host])
        .arg("--manifest-path")
        .arg(&manifest)
        .output()
        .expect("cargo metadata runs");
    assert!(
        output.status.success(),
        "cargo metadata failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let metadata: Value = serde_json::from_slice(&output.stdout).expect("cargo metadata's JSON");
    let names: BTreeMap<&str, &str> = metadata["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .map(|p| {
            (
                p["id"].as_str().expect("id"),
                p["name"].as_str().expect("name"),
            )
        })
        .collect();
    let mut graph = BTreeMap::new();
    for node in metadata["resolve"]["nodes"].as_array().expect("resolve") {
        let deps = node["deps"]
            .as_array()
            .expect("deps")
            .iter()
            .filter(|d| {
                d["dep_kinds"]
                    .as_array()
                    .is_some_and(|kinds| kinds.iter().any(|k| k["kind"].is_null()))
            })
            .map(|d| names[d["pkg"].as_str().expect("pkg")].to_owned())
            .collect();
        graph.insert(names[node["id"].as_str().expect("id")].to_owned(), deps);
    }
    graph
}

/// `package` and everything it links.
fn links(graph: &BTreeMap<String, BTreeSet<String>>, package: &str) -> BTreeSet<String> {
    let mut seen = BTreeSet::from([package.to_owned()]);
    let mut stack = vec![package.to_owned()];
    while let Some(name) = stack.pop() {
        for dep in graph.get(&name).into_iter().flatten() {
            if seen.insert(dep.clone()) {
                stack.push(dep.clone());
            }
        }
    }
    seen
}

#[track_caller]
fn assert_links_none(graph: &BTreeMap<String, BTreeSet<String>>, package: &str, banned: &[&str]) {
    let linked = links(graph, package);
    // Not vacuous: the package was found and links the algorithm core (or is it).
    assert!(
        linked.contains("mapping"),
        "{package} not found or links no mapping: {linked:?}"
    );
    for name in banned {
        assert!(!linked.contains(*name), "{package} links {name}");
    }
}

#[test]
fn each_binary_links_only_what_it_runs() {
    let graph = normal_dependencies();
    assert_links_none(
        &graph,
        "server",
        &["robot-agent", "simulator", "fleet-demo"],
    );
    assert_links_none(
        &graph,
        "robot-agent",
        &["simulator", "server", "fleet-demo"],
    );
    let shells = [
        "tokio",
        "tonic",
        "zenoh",
        "sled",
        "proto",
        "storage",
        "robot-agent",
        "server",
    ];
    assert_links_none(&graph, "mapping", &shells);
    assert_links_none(&graph, "simulator", &shells);
    // The simulations link what they simulate.
    let demo = links(&graph, "fleet-demo");
    for name in ["simulator", "robot-agent", "server"] {
        assert!(demo.contains(name), "fleet-demo links no {name}");
    }
}
