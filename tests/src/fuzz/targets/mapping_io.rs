//! The `mapping::io` readers: g2o / TORO pose graphs and benchmark relation files. (`mapping::io::tum`
//! only writes; there is no TUM reader to fuzz.)

use std::path::Path;

use mapping::geometry::Rigid2Ext as _;
use mapping::io::{g2o, relations};

use super::super::fuzz_target::{FuzzTarget, Verdict};
use super::{SetupError, read_file};

/// The first `lines` lines of a text file.
fn head(path: &Path, lines: usize) -> Result<Vec<u8>, SetupError> {
    let bytes = read_file(path)?;
    let end = bytes
        .iter()
        .enumerate()
        .filter(|(_, b)| **b == b'\n')
        .nth(lines.saturating_sub(1))
        .map_or(bytes.len(), |(i, _)| i + 1);
    Ok(bytes[..end].to_vec())
}

/// g2o and TORO files: parsed, checked, written back and read again.
pub fn pose_graphs(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let mut seeds = Vec::new();
    for name in [
        "ring.g2o",
        "CSAIL.g2o",
        "intel_sesync1728.g2o",
        "M3500.g2o",
        "city10000.g2o",
        "input_INTEL_g2o.g2o",
        "M3500a_toro.graph",
    ] {
        seeds.push(head(&datasets.join("posegraphs").join(name), 80)?);
    }
    // Edges only, past the vertices (initialised from the odometry chain and breadth-first search).
    let ring = read_file(&datasets.join("posegraphs/ring.g2o"))?;
    let edges: Vec<u8> = String::from_utf8_lossy(&ring)
        .lines()
        .filter(|l| l.starts_with("EDGE"))
        .take(60)
        .flat_map(|l| format!("{l}\n").into_bytes())
        .collect();
    seeds.push(edges);
    seeds.push(
        b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nFIX 0\n".to_vec(),
    );
    Ok(FuzzTarget::new(
        "g2o",
        "g2o / TORO pose-graph files (read, write, read back)",
        seeds,
        true,
        Box::new(|input| {
            let result = g2o::read_pose_graph(input);
            if let Ok(parsed) = &result {
                for (id, pose, _) in parsed.graph.variables() {
                    assert!(
                        pose.x().is_finite() && pose.y().is_finite() && pose.theta().is_finite(),
                        "invariant: non-finite initial pose {pose:?} of {id:?}"
                    );
                }
                let chi2 = parsed.graph.chi2();
                assert!(!chi2.is_nan(), "invariant: chi2 is NaN");
                let mut written = Vec::new();
                g2o::write_pose_graph(&parsed.graph, &mut written)
                    .unwrap_or_else(|e| panic!("invariant: cannot write what was read: {e}"));
                let back = g2o::read_pose_graph(written.as_slice())
                    .unwrap_or_else(|e| panic!("invariant: cannot read what was written: {e}"));
                assert_eq!(
                    (back.graph.num_variables(), back.graph.num_constraints()),
                    (parsed.graph.num_variables(), parsed.graph.num_constraints()),
                    "invariant: the written graph reads back different"
                );
            }
            Verdict::of(&result)
        }),
    ))
}

/// Freiburg benchmark relation files.
pub fn relation_files(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let mut seeds = Vec::new();
    for name in ["mit-csail", "intel", "aces"] {
        seeds.push(head(
            &datasets.join(format!("relations/{name}.relations")),
            40,
        )?);
    }
    seeds.push(b"# t1 t2 x y z roll pitch yaw\n10.5 11.0 1 2 0 0 0 0.5\n".to_vec());
    Ok(FuzzTarget::new(
        "relations",
        "Freiburg benchmark relation files",
        seeds,
        true,
        Box::new(|input| {
            let result = relations::read_relations(input);
            if let Ok(relations) = &result {
                for r in relations {
                    for t in [r.t1, r.t2] {
                        assert!(
                            (0.0..=4_294_967_296.0).contains(&t.as_secs_f64()),
                            "invariant: stamp {t} outside ROS1's time range"
                        );
                    }
                    assert!(
                        r.delta.x().is_finite()
                            && r.delta.y().is_finite()
                            && r.delta.theta().is_finite(),
                        "invariant: non-finite relation"
                    );
                }
            }
            Verdict::of(&result)
        }),
    ))
}
