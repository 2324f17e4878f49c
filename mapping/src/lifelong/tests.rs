//! The lifelong map on a small synthetic site: the same loop driven in every session, submaps as fully
//! known boxes around their nodes, and a fake GLM that answers every search job with the true relative
//! pose plus noise. Checks the policies' graph sizes, that the first session is never trimmed, and that
//! Chow–Liu loses less information than deletion.

use nalgebra::{Point2, Vector2};
use rand::{Rng as _, SeedableRng as _};
use rand_pcg::Pcg64;

use super::*;
use crate::geometry::{Rigid2, rigid2};
use crate::global_slam::{LoopClosure, SearchJob};
use crate::grid::{CellIndex, MapLimits, ProbabilityGrid};
use crate::local_slam::LloNode;
use crate::pose_graph::SubmapId;
use crate::sensor::Timestamp;

/// Nodes per lap.
const LAP: usize = 32;
/// Nodes per submap; consecutive submaps share half of them.
const SUBMAP_NODES: usize = 8;

/// True pose of the robot `k` nodes into the loop: a 8 m × 4 m rectangle driven counter-clockwise.
fn route(k: usize) -> Rigid2 {
    let perimeter = 24.0;
    let s = (k % LAP) as f64 / LAP as f64 * perimeter;
    let (x, y, theta) = if s < 8.0 {
        (s, 0.0, 0.0)
    } else if s < 12.0 {
        (8.0, s - 8.0, std::f64::consts::FRAC_PI_2)
    } else if s < 20.0 {
        (8.0 - (s - 12.0), 4.0, std::f64::consts::PI)
    } else {
        (0.0, 4.0 - (s - 20.0), -std::f64::consts::FRAC_PI_2)
    };
    rigid2(x, y, theta)
}

/// A fully known box (free, with an occupied rim) around the local positions of a submap's nodes.
fn submap_grid(local_poses: &[Rigid2]) -> ProbabilityGrid {
    let mut min = Vector2::repeat(f64::INFINITY);
    let mut max = Vector2::repeat(f64::NEG_INFINITY);
    for p in local_poses {
        min = min.inf(&p.translation.vector);
        max = max.sup(&p.translation.vector);
    }
    let margin = 1.5;
    let r = 0.1;
    let origin = min - Vector2::repeat(margin);
    let width = ((max.x - min.x + 2.0 * margin) / r).ceil() as i32;
    let height = ((max.y - min.y + 2.0 * margin) / r).ceil() as i32;
    let mut grid = ProbabilityGrid::new(MapLimits::new(r, origin, width, height));
    for iy in 0..height {
        for ix in 0..width {
            let rim = ix == 0 || iy == 0 || ix == width - 1 || iy == height - 1;
            grid.set_probability(&CellIndex::new(ix, iy), if rim { 0.9 } else { 0.2 });
        }
    }
    grid
}

struct Site {
    map: LifelongMap,
    rng: Pcg64,
    /// True `world_from_local` per session.
    starts: Vec<Rigid2>,
    /// Counts after each session.
    counts: Vec<GraphCounts>,
    trims: Vec<(SubmapId, usize, Option<f64>)>,
    /// Optimizations of each session's end, and whether it trimmed anything.
    session_ends: Vec<(usize, bool)>,
}

impl Site {
    fn new(options: LifelongOptions) -> Self {
        Self {
            map: LifelongMap::new(options).unwrap(),
            rng: Pcg64::seed_from_u64(11),
            starts: Vec::new(),
            counts: Vec::new(),
            trims: Vec::new(),
            session_ends: Vec::new(),
        }
    }

    fn true_pose(&self, job: &SearchJob) -> Option<LoopClosure> {
        let start = self.starts[job.node.trajectory as usize];
        let node_local = self.map.global().nodes().get(&job.node)?.local_pose;
        let submap_start = self.starts[job.submap.trajectory as usize];
        let submap_local = self.map.global().submaps().get(&job.submap)?.local_pose;
        Some(LoopClosure {
            submap: job.submap,
            node: job.node,
            submap_from_node: (submap_start * submap_local).inverse() * (start * node_local),
            score: 0.7,
            runner_up_score: None,
            information: None,
        })
    }

    fn answer(&mut self) {
        let jobs = self.map.take_search_jobs();
        let truths: Vec<LoopClosure> = jobs.iter().filter_map(|j| self.true_pose(j)).collect();
        let results: Vec<LoopClosure> = truths
            .into_iter()
            .map(|mut c| {
                let noise = rigid2(
                    self.rng.random_range(-0.02..0.02),
                    self.rng.random_range(-0.02..0.02),
                    self.rng.random_range(-0.005..0.005),
                );
                c.submap_from_node *= noise;
                c
            })
            .collect();
        let events = self.map.add_search_results(results);
        self.record(events);
    }

    fn record(&mut self, events: Vec<LifelongEvent>) {
        for event in events {
            if let LifelongEvent::SubmapTrimmed {
                submap,
                removed_nodes,
                kld,
                ..
            } = event
            {
                self.trims.push((submap, removed_nodes.len(), kld));
            }
        }
    }

    /// Drives one lap as session `session`, starting `offset` nodes into the loop.
    fn run_session(&mut self, session: u32, offset: usize, prior: bool) {
        let start = route(offset);
        self.starts.push(start);
        let prior = prior.then(|| start * rigid2(0.05, -0.05, 0.01));
        self.map.start_session(session, prior).unwrap();
        let mut local_poses = Vec::new();
        for i in 0..LAP {
            let local_pose = start.inverse() * route(offset + i);
            local_poses.push(local_pose);
            // Node i lies in submaps i/4 − 1 and i/4 (each submap holds 8 nodes).
            let half = SUBMAP_NODES / 2;
            let newest = i / half;
            let insertion: Vec<(usize, Rigid2)> = [newest.checked_sub(1), Some(newest)]
                .into_iter()
                .flatten()
                .map(|k| (k, local_poses[k * half]))
                .collect();
            let finished: Vec<(usize, ProbabilityGrid)> =
                if i % half == half - 1 && i + 1 >= SUBMAP_NODES {
                    let k = newest - 1;
                    vec![(k, submap_grid(&local_poses[k * half..=i]))]
                } else {
                    Vec::new()
                };
            let time = Timestamp(i64::from(session) * 1_000_000_000_000 + i as i64 * 100_000_000);
            let points = vec![Point2::new(1.0f32, 0.0); 10];
            let node = LloNode {
                time,
                local_pose,
                points,
                insertion_submaps: insertion,
                finished_submaps: finished,
                recovered: false,
            };
            let (_, events) = self.map.add_node(session, node).unwrap();
            self.record(events);
            self.answer();
        }
        // LLO's last submap, still active at the end of the lap.
        let last = LAP / (SUBMAP_NODES / 2) - 1;
        let grid = submap_grid(&local_poses[last * SUBMAP_NODES / 2..]);
        let events = self
            .map
            .finish_submaps(session, vec![(last, grid)])
            .unwrap();
        self.record(events);
        let events = self.map.finish_session(session).unwrap();
        let optimizations = events
            .iter()
            .filter(|e| matches!(e, LifelongEvent::Optimized(_)))
            .count();
        let trimmed = events
            .iter()
            .any(|e| matches!(e, LifelongEvent::SubmapTrimmed { dropped: false, .. }));
        self.session_ends.push((optimizations, trimmed));
        self.record(events);
        self.counts.push(self.map.counts());
    }
}

fn options(policy: TrimPolicy) -> LifelongOptions {
    let mut options = LifelongOptions {
        policy,
        ..LifelongOptions::default()
    };
    options.global.constraint_builder.sampling_ratio = 0.3;
    options.global.unanchored_search_every_n_nodes = 1;
    options
}

fn run(policy: TrimPolicy, sessions: u32) -> Site {
    let mut site = Site::new(options(policy));
    for s in 0..sessions {
        // Session 1 starts with no prior (placed by a full-submap match); the others are relocalized.
        site.run_session(s, 3 * s as usize, s != 1);
    }
    site
}

fn session_submaps(site: &Site, session: u32) -> usize {
    site.map
        .submaps()
        .filter(|(id, _, _)| id.trajectory == session)
        .count()
}

#[test]
fn keep_grows_while_clt_and_delete_stay_bounded_and_session_zero_survives() {
    let keep = run(TrimPolicy::Keep, 5);
    let clt = run(TrimPolicy::Clt, 5);
    let delete = run(TrimPolicy::Delete, 5);
    let first = keep.counts[0];
    assert!(first.submaps >= 6, "{first:?}");
    // keep: every session adds its lap.
    assert!(keep.counts[4].nodes >= 5 * LAP, "{:?}", keep.counts);
    assert!(
        keep.counts[4].submaps >= 5 * first.submaps - 2,
        "{:?}",
        keep.counts
    );
    assert_eq!(keep.counts[4].trimmed_total, 0);
    for site in [&clt, &delete] {
        let last = site.counts[4];
        // Session 0 plus (at most) the latest session and a few stragglers.
        assert!(last.nodes <= 2 * LAP + LAP / 2, "{:?}", site.counts);
        assert!(last.submaps <= 2 * first.submaps + 2, "{:?}", site.counts);
        assert!(
            last.trimmed_total >= 3 * (first.submaps - 2),
            "{:?}",
            site.counts
        );
        // Bounded: no growth from session 2 on.
        assert!(
            last.nodes <= site.counts[2].nodes + LAP / 4,
            "{:?}",
            site.counts
        );
        assert_eq!(
            session_submaps(site, 0),
            first.submaps,
            "session 0 was trimmed"
        );
        assert!(site.trims.iter().all(|(id, _, _)| id.trajectory != 0));
        // The latest session was not trimmed (nothing fresher).
        assert!(site.trims.iter().all(|(id, _, _)| id.trajectory != 4));
    }
    // clt keeps what it removed as tree constraints: more constraints than delete for the same variables.
    assert!(clt.counts[4].constraints > delete.counts[4].constraints);
    // Every session was localized onto the same map: the final node estimates are near the truth.
    for site in [&keep, &clt, &delete] {
        for (id, _, pose) in site.map.node_poses() {
            let record = &site.map.global().nodes()[&id];
            let truth = site.starts[id.trajectory as usize] * record.local_pose;
            let error = (pose.translation.vector - truth.translation.vector).norm();
            assert!(error < 0.15, "node {id:?} off by {error} m");
        }
    }
}

#[test]
fn trims_are_re_optimized_only_when_asked() {
    // Default: the session's final optimization only, trims or not.
    let never = run(TrimPolicy::Clt, 5);
    assert!(never.session_ends.iter().any(|&(_, trimmed)| trimmed));
    assert!(
        never.session_ends.iter().all(|&(n, _)| n == 1),
        "{:?}",
        never.session_ends
    );
    // Every sparsification: a second optimization after each batch of trims.
    let mut site = Site::new(LifelongOptions {
        optimize_every_n_sparsifications: 1,
        ..options(TrimPolicy::Clt)
    });
    for s in 0..5 {
        site.run_session(s, 3 * s as usize, s != 1);
    }
    for &(n, trimmed) in &site.session_ends {
        assert_eq!(n, if trimmed { 2 } else { 1 }, "{:?}", site.session_ends);
    }
}

#[test]
fn frozen_keeps_only_the_first_session_and_holds_it_still() {
    let site = run(TrimPolicy::Frozen, 3);
    let first = site.counts[0];
    for counts in &site.counts {
        assert_eq!(counts.nodes, first.nodes);
        assert_eq!(counts.submaps, first.submaps);
    }
    assert!(site.trims.iter().all(|(id, _, _)| id.trajectory != 0));
    assert_eq!(site.trims.len(), 2 * first.submaps);
    // Later sessions' own submaps were dropped with them; nothing stale was trimmed.
    let last = site.counts[2];
    assert_eq!(
        (last.trimmed_total, last.dropped_total),
        (0, 2 * first.submaps)
    );
    // Session 0's poses were held fixed while later sessions localized against them.
    let start_map = run(TrimPolicy::Frozen, 1);
    for ((a, _, pa), (b, _, pb)) in site.map.node_poses().zip(start_map.map.node_poses()) {
        assert_eq!(a, b);
        assert!((pa.translation.vector - pb.translation.vector).norm() < 1e-12);
    }
}

/// Each trimmed submap's KLD (whole remaining graph against the exact marginal) under `clt` is below
/// `delete`'s. With few loop closures per node (sampling 0.05, as on real data where most searches fail),
/// as here. Known weakness, measured with this site: when every node has many closures to many submaps
/// (sampling 0.3), the blanket's marginal is a dense clique that the rest of the graph already pins down,
/// and the KL-optimal tree for the blanket alone is over-confident there: its whole-graph KLD then
/// exceeds deletion's (e.g. 3.9 vs 0.7 nats for one submap).
#[test]
fn clt_loses_less_information_than_delete() {
    let sum = |policy| {
        let mut options = options(policy);
        options.whole_graph_kld = true;
        options.global.constraint_builder.sampling_ratio = 0.05;
        let mut site = Site::new(options);
        for s in 0..3 {
            site.run_session(s, 3 * s as usize, true);
        }
        let klds: Vec<f64> = site.trims.iter().filter_map(|t| t.2).collect();
        assert!(!klds.is_empty());
        assert_eq!(klds.len(), site.trims.len());
        klds.iter().sum::<f64>()
    };
    let clt = sum(TrimPolicy::Clt);
    let delete = sum(TrimPolicy::Delete);
    eprintln!("whole-graph KLD: clt {clt:.3}, delete {delete:.3}");
    assert!(clt.is_finite() && delete > 0.0);
    // Measured: clt 3.42, delete 5.08 nats over the trims (with the trees' means matching the
    // gradient instead, `TreeMean::MatchGradient`: 1.29 against 3.88 — it keeps an optimum's pull, and
    // costs the store's graph its conditioning, see `TreeMean`).
    assert!(clt < 0.8 * delete, "clt {clt} vs delete {delete}");
}

#[test]
fn sessions_are_checked() {
    let mut map = LifelongMap::new(LifelongOptions::default()).unwrap();
    assert!(matches!(
        map.finish_session(0),
        Err(LifelongError::UnknownSession(0))
    ));
    map.start_session(0, None).unwrap();
    assert!(matches!(
        map.start_session(0, None),
        Err(LifelongError::SessionExists(0))
    ));
    map.finish_session(0).unwrap();
    assert!(matches!(
        map.add_node(
            0,
            LloNode {
                time: Timestamp(0),
                local_pose: Rigid2::identity(),
                points: Vec::new(),
                insertion_submaps: Vec::new(),
                finished_submaps: Vec::new(),
                recovered: false,
            }
        ),
        Err(LifelongError::SessionFinished(0))
    ));
    assert_eq!(map.counts(), GraphCounts::default());
}

#[test]
fn no_trimming_before_enough_fresh_submaps_or_without_enough_coverage() {
    let mut few = options(TrimPolicy::Clt);
    // Each session finishes 8 submaps.
    few.trimmer.min_fresh_submaps_before_trimming = 9;
    let mut site = Site::new(few);
    for s in 0..3 {
        site.run_session(s, 3 * s as usize, true);
    }
    assert_eq!(site.map.counts().trimmed_total, 0);
    // K = 2 fresher submaps per cell: one later session covers each cell about twice (its submaps
    // overlap by half), so trimming still happens; K = 4 is never reached after one fresher session.
    for (k, expect_trims) in [(2, true), (4, false)] {
        let mut options = options(TrimPolicy::Clt);
        options.trimmer.min_fresher_submaps = k;
        let mut site = Site::new(options);
        for s in 0..3 {
            site.run_session(s, 3 * s as usize, true);
        }
        assert_eq!(
            site.map.counts().trimmed_total > 0,
            expect_trims,
            "K = {k}: {:?}",
            site.counts
        );
    }
}

#[test]
fn constraints_are_counted_by_kind() {
    use crate::lifelong::ConstraintKindCounts;
    use crate::pose_graph::{Constraint, ConstraintKind, PoseGraph, RobustLoss, VariableId};
    let node = |index| {
        VariableId::Node(crate::pose_graph::NodeId {
            trajectory: 0,
            index,
        })
    };
    let mut graph = PoseGraph::new();
    for index in 0..3 {
        graph
            .add_variable(node(index), rigid2(0.0, 0.0, 0.0))
            .unwrap();
    }
    for (kind, from, to) in [
        (ConstraintKind::Odometry, 0, 1),
        (ConstraintKind::Odometry, 1, 2),
        (ConstraintKind::NodeToNode, 0, 2),
    ] {
        graph
            .add_constraint(Constraint {
                kind,
                from: node(from),
                to: node(to),
                from_from_to: rigid2(1.0, 0.0, 0.0),
                information: nalgebra::Matrix3::identity(),
                loss: RobustLoss::Trivial,
            })
            .unwrap();
    }
    assert_eq!(
        ConstraintKindCounts::of(&graph),
        ConstraintKindCounts {
            odometry: 2,
            node_to_node: 1,
            ..Default::default()
        }
    );
}
