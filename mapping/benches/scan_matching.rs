//! Scan matching benchmark on real LLO output: a simulated store's first session run through LLO
//! (`simulator::testing::checkpoint_sessions`), each of its finished submaps matched against by the
//! scans LLO inserted into it. For each submap: the matcher built (its precomputation grids: time, memory)
//! and searched over the whole submap at every branch-and-bound depth, then per scan `match_full` (the whole submap), `match_near` (from 1 m and 0.2 rad off)
//! and the least-squares refinement (from 3 cm and 1° off), timed, with how many land within 10 cm and
//! 1° of LLO's pose. Not a test: run it with
//!
//!     cargo bench --workspace --bench scan_matching
//!
//! (a plain `main`, `harness = false`; the figures are wall-clock times on the machine that runs it).

use std::time::Instant;

use mapping::geometry::{Rigid2, Rigid2Ext as _, normalize_angle, rigid2};
use mapping::scan_matching::{
    FastCorrelativeScanMatcher, FastCorrelativeScanMatcherOptions, LeastSquaresScanMatcher,
    LeastSquaresScanMatcherOptions,
};
use simulator::testing::checkpoint_sessions::session_inputs;

/// Minimum score of the branch-and-bound searches (GLM's default acceptance is near this).
const MIN_SCORE: f32 = 0.55;

fn close(a: &Rigid2, b: &Rigid2) -> bool {
    (a.translation.vector - b.translation.vector).norm() < 0.1
        && normalize_angle(a.theta() - b.theta()).abs() < 1f64.to_radians()
}

fn main() {
    let started = Instant::now();
    let sessions = session_inputs();
    let Some(session) = sessions.first() else {
        eprintln!("no session simulated");
        return;
    };
    println!(
        "session 0: {} nodes, LLO in {:.1} s (all {} sessions)",
        session.nodes.len(),
        started.elapsed().as_secs_f64(),
        sessions.len()
    );
    let finished = session
        .nodes
        .iter()
        .flat_map(|n| n.finished_submaps.iter())
        .chain(session.active_submaps.iter());
    let (mut full_ms, mut near_ms, mut ls_us) = (Vec::new(), Vec::new(), Vec::new());
    let (mut full_ok, mut near_ok, mut ls_ok, mut ls_iterations) = (0, 0, 0, 0u64);
    let least_squares = LeastSquaresScanMatcher::new(LeastSquaresScanMatcherOptions::default());
    for (index, grid) in finished {
        // The scans LLO inserted into this submap, at their local poses (the grids are in LLO's frame).
        let scans: Vec<_> = session
            .nodes
            .iter()
            .filter(|n| n.insertion_submaps.iter().any(|(i, _)| i == index))
            .collect();
        // Timed from the matcher's construction (its precomputation grids) through its first search.
        for depth in [5, 6, 7, 8] {
            let Some(first) = scans.first() else {
                continue;
            };
            let t = Instant::now();
            let matcher = FastCorrelativeScanMatcher::new(
                grid,
                FastCorrelativeScanMatcherOptions {
                    branch_and_bound_depth: depth,
                    ..FastCorrelativeScanMatcherOptions::default()
                },
            );
            let found = matcher.match_full(&first.points, MIN_SCORE);
            let first_ms = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            let _ = matcher.match_full(&first.points, MIN_SCORE);
            println!(
                "submap {index} ({} × {} cells, {} scans), depth {depth}: built and first match_full {first_ms:.1} ms ({:.1} MB), again {:.1} ms, {}",
                grid.limits().width,
                grid.limits().height,
                scans.len(),
                matcher.memory_bytes() as f64 / 1e6,
                t.elapsed().as_secs_f64() * 1e3,
                if found.is_some_and(|m| close(&m.pose, &first.local_pose)) {
                    "right"
                } else {
                    "wrong or none"
                }
            );
        }
        let matcher =
            FastCorrelativeScanMatcher::new(grid, FastCorrelativeScanMatcherOptions::default());
        for node in &scans {
            let truth = node.local_pose;
            let t = Instant::now();
            let full = matcher.match_full(&node.points, MIN_SCORE);
            full_ms.push(t.elapsed().as_secs_f64() * 1e3);
            full_ok += usize::from(full.is_some_and(|m| close(&m.pose, &truth)));
            let off = rigid2(truth.x() + 0.7, truth.y() - 0.7, truth.theta() + 0.2);
            let t = Instant::now();
            let near = matcher.match_near(&off, &node.points, MIN_SCORE);
            near_ms.push(t.elapsed().as_secs_f64() * 1e3);
            near_ok += usize::from(near.is_some_and(|m| close(&m.pose, &truth)));
            let initial = rigid2(
                truth.x() + 0.03,
                truth.y() - 0.02,
                truth.theta() + 1f64.to_radians(),
            );
            let t = Instant::now();
            let (refined, summary) =
                least_squares.match_pose(&initial.translation.vector, &initial, &node.points, grid);
            ls_us.push(t.elapsed().as_secs_f64() * 1e6);
            ls_ok += usize::from(close(&refined, &truth));
            ls_iterations += u64::from(summary.iterations);
        }
    }
    let n = full_ms.len();
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    println!(
        "{n} scans: match_full median {:.2} ms, {full_ok} within 10 cm and 1°; match_near median {:.2} ms, {near_ok} within; least squares median {:.1} µs, {:.1} iterations per match, {ls_ok} within",
        median(&mut full_ms),
        median(&mut near_ms),
        median(&mut ls_us),
        ls_iterations as f64 / n.max(1) as f64
    );
}
