//! `evermap-agent relocalize`: how well and how fast a robot finds itself on a map with no prior.
//!
//! The map shows the first 60 % of the recording (by time); scans sampled from the remaining 40 %
//! are placed on the whole map with no prior by the session-start search of the lifelong map
//! ([`StartSearch`]: branch and bound over every position and rotation, the best distinct candidates
//! refined and compared). With `--stack-s T`, what is placed is not the sampled scan alone but the local
//! map LLO builds from the T seconds of driving that start at it ([`run_llo`], the nodes merged into one
//! cloud in the first node's frame, as a lifelong session's held-back first nodes are); the pose scored is
//! the first node's, the sampled scan's (or the first scan after it LLO could match). The search may refuse
//! (ambiguous or no good fit); the report counts right answers, wrong answers and refusals apart.
//!
//! Truth (`--truth`): by default (`own`) the map and the truth come from one `offline` run of the whole
//! recording: the map is that run's nodes before the cut, re-inserted at their optimized poses, and a
//! sampled scan's truth is that run's pose of it, so a relocalization is scored against exactly the frame
//! the map was drawn in. With `aligned` (the earlier definition) the map is a separate run of the first
//! 60 % and the truth is the full run's pose re-aligned locally to it ([`align_near`]): the two runs' maps
//! differ by decimetres in places, and that disagreement lands in the score. With `--relations`, every
//! sample is also checked against the benchmark's manually verified relations that tie a scan near it to
//! a scan in the map ([`relations_truth`]), a truth independent of both runs' optimizations.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use clap::{Args, ValueEnum};
use mapping::geometry::Rigid2;
use mapping::geometry::{Rigid2Ext as _, normalize_angle};
use mapping::io::relations::{Relation, read_relations};
use mapping::lifelong::{RelocalizationOutcome, SearchEvidence, StartSearch};
use mapping::metrics::{PoseTolerance, pose_error};
use mapping::sensor::{SensorEvent, Timestamp};
use nalgebra::Point2;
use proto::UploadItem;
use rand::SeedableRng as _;
use rand::seq::index::sample;
use rand_pcg::Pcg64;
use robot_agent::offline_slam::SlamConfig;
use robot_agent::source::{self, Recording};
use robot_agent::uplink::run_llo;
use serde_json::json;

mod reference;

use self::reference::{LOCAL_ALIGNMENT_RADIUS_M, Reference, prepare_aligned, prepare_own};

/// Scans to relocalize: `(local_from_tracking, points)`, first scan first.
type Stack = Vec<(Rigid2, Vec<Point2<f32>>)>;

/// Arguments of `relocalize`.
#[derive(Args)]
pub struct RelocalizeArgs {
    /// The recording: a ROS1 bag, a ROS 2 recording (rosbag2 folder, `metadata.yaml`, `.mcap` or `.db3`)
    /// or a CARMEN log.
    #[arg(long)]
    input: PathBuf,
    /// How many scans of the last 40 % to relocalize.
    #[arg(long, default_value_t = 100)]
    samples: usize,
    /// Seed of the scan sampling.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// A TOML file overriding the default SLAM configuration.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Relocalize the local map LLO builds from this many seconds of driving, starting at each sampled
    /// scan, instead of the scan alone (0: the scan alone).
    #[arg(long, default_value_t = 0.0)]
    stack_s: f64,
    /// While the search refuses, grow the stack by `--grow-step-s` seconds of driving and search again,
    /// up to this many seconds (as a session start keeps searching while it drives); the report gives the
    /// stack each answer needed. Off (no growth) unless given.
    #[arg(long)]
    grow_to_s: Option<f64>,
    /// Seconds of driving each growth step adds (with `--grow-to-s`).
    #[arg(long, default_value_t = 5.0)]
    grow_step_s: f64,
    /// With `--grow-to-s`, search every stack length even after an answer (for studying the decision on
    /// longer stacks; the outcome is still the first answer's, and only its time is counted).
    #[arg(long)]
    every_step: bool,
    /// What the answers are scored against (see the module docs).
    #[arg(long, value_enum, default_value_t = Truth::Own)]
    truth: Truth,
    /// A file holding the map and the truth (written by a first run, read by later ones): the mapping
    /// runs are the same for every search setting of one recording and `--truth`, and take most of the
    /// time. The caller keeps files of different recordings, truths or SLAM configurations apart.
    #[arg(long)]
    reference: Option<PathBuf>,
    /// The benchmark's relations file (`t1 t2 x y z roll pitch yaw`) to check every sample against too.
    #[arg(long)]
    relations: Option<PathBuf>,
}

/// Where the map and the truth come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Truth {
    /// One run of the whole recording: the map is its nodes before the cut, the truth its poses.
    Own,
    /// The map is a run of the first 60 %; the truth is a full run's pose re-aligned within 8 m.
    Aligned,
}

/// A relocalization counts as correct within 0.15 m and 3° of the truth.
const SUCCESS: PoseTolerance = PoseTolerance {
    translation_m: 0.15,
    rotation_deg: 3.0,
};

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// Runs the command.
pub fn run(args: &RelocalizeArgs) -> anyhow::Result<()> {
    let config = SlamConfig::load(args.config.as_deref())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let recording = source::read_recording(&args.input)?;
    let (Some(first), Some(last)) = (recording.events.first(), recording.events.last()) else {
        anyhow::bail!("{} has no sensor data", args.input.display());
    };
    let cut = first
        .time()
        .offset_by(0.6 * last.time().seconds_since(first.time()));
    let relations = match &args.relations {
        Some(path) => {
            let file = std::fs::File::open(path)
                .with_context(|| format!("cannot open {}", path.display()))?;
            read_relations(std::io::BufReader::new(file))
                .with_context(|| format!("invalid relations file {}", path.display()))?
        }
        None => Vec::new(),
    };
    let reference = match &args.reference {
        Some(path) if path.exists() => Reference::read(path)?,
        cache => {
            let reference = match args.truth {
                Truth::Own => prepare_own(&recording, &config, cut)?,
                Truth::Aligned => prepare_aligned(&recording, &config, cut)?,
            };
            if let Some(path) = cache {
                reference.write(path)?;
            }
            reference
        }
    };
    config
        .relocalization
        .validate()
        .context("invalid relocalization options")?;
    let lengths = stack_lengths(args)?;
    // LLO runs to the longest stack (`--grow-to-s`, at least `--stack-s`) once per sample.
    let grow_to_s = args.grow_to_s.unwrap_or(args.stack_s).max(args.stack_s);
    let build_start = Instant::now();
    let search = StartSearch::new(&reference.map, &config.relocalization);
    let precompute_ms = build_start.elapsed().as_secs_f64() * 1e3;

    let candidates: Vec<Timestamp> = recording
        .events
        .iter()
        .filter_map(|e| match e {
            SensorEvent::Scan(s) if reference.truth.contains_key(&s.time) => Some(s.time),
            _ => None,
        })
        .collect();
    anyhow::ensure!(
        !candidates.is_empty(),
        "no scans with a ground-truth pose after the 60 % cut"
    );
    let n = args.samples.min(candidates.len());
    let mut rng = Pcg64::seed_from_u64(args.seed);
    let mut picks = sample(&mut rng, candidates.len(), n).into_vec();
    picks.sort_unstable();

    let judge = Judge {
        search: &search,
        reference: &reference,
        relations: &relations,
    };
    let mut times_ms = Vec::with_capacity(n);
    let mut results = Vec::with_capacity(n);
    let mut tally = Tally::default();
    for &k in &picks {
        let sampled = candidates[k];
        let llo_start = Instant::now();
        let nodes = local_map(&recording, sampled, grow_to_s, &config.local);
        let llo_ms = llo_start.elapsed().as_secs_f64() * 1e3;
        let Some((scored_time, first_local)) = nodes.first().map(|(t, pose, _)| (*t, *pose)) else {
            tally.refused += 1;
            results.push(json!({"time": sampled.to_string(), "answer": "no_scan"}));
            continue;
        };
        let truth_pose = reference.truth.get(&scored_time).copied();
        let stack = StackSearch {
            sampled,
            first_local,
            truth_pose,
            nodes: &nodes,
        };
        let decided = stack.search(&search, &lengths, args.every_step);
        times_ms.push(decided.ms);
        let Some(truth_pose) = truth_pose else {
            tally.refused += 1;
            results.push(json!({"time": sampled.to_string(), "answer": "no_truth"}));
            continue;
        };
        let sample = JudgedSample {
            sampled,
            scored_time,
            first_local,
            truth_pose,
            nodes: &nodes,
            llo_ms,
        };
        results.push(judge.judge(&sample, decided, &mut tally));
    }
    let report = summary_report(
        args,
        n,
        &tally,
        &times_ms,
        &results,
        precompute_ms,
        &reference,
    );
    let path = args.out.join("report.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", path.display()))?;
    println!(
        "{}",
        json!({"samples": n, "stack_s": args.stack_s, "success_rate": report["success_rate"],
            "precision": report["precision"], "answered_rate": report["answered_rate"],
            "wrong": report["wrong"], "refused": report["refused"],
            "answers_checked_by_relations": report["answers_checked_by_relations"],
            "answers_off_by_relations": report["answers_off_by_relations"],
            "median_ms": report["median_ms"], "p95_ms": report["p95_ms"],
            "on_observed_ground": report["on_observed_ground"]})
    );
    Ok(())
}

/// The stack lengths tried, seconds: `--stack-s`, then one growth step more each time up to `--grow-to-s`.
fn stack_lengths(args: &RelocalizeArgs) -> anyhow::Result<Vec<f64>> {
    anyhow::ensure!(
        args.stack_s.is_finite() && args.stack_s >= 0.0,
        "--stack-s must be a non-negative number of seconds"
    );
    anyhow::ensure!(
        args.grow_step_s.is_finite() && args.grow_step_s > 0.0,
        "--grow-step-s must be a positive number of seconds"
    );
    let grow_to_s = args.grow_to_s.unwrap_or(args.stack_s).max(args.stack_s);
    anyhow::ensure!(grow_to_s.is_finite(), "--grow-to-s must be finite");
    let mut lengths = vec![args.stack_s];
    while let Some(&last) = lengths.last()
        && last + args.grow_step_s <= grow_to_s + 1e-9
    {
        lengths.push(last + args.grow_step_s);
    }
    Ok(lengths)
}

/// One sample's stack: the nodes LLO made from its sampled scan on, and the truth of its first node.
struct StackSearch<'a> {
    sampled: Timestamp,
    /// `local_from_tracking` of the first node (the pose scored).
    first_local: Rigid2,
    truth_pose: Option<Rigid2>,
    nodes: &'a [(Timestamp, Rigid2, Vec<Point2<f32>>)],
}

/// What the stack searches decided: the stack that answered (or the last), its evidence and outcome, its
/// length, the time of every search until the answer, and every attempt for the report.
struct Decided {
    scans: Stack,
    evidence: Option<SearchEvidence>,
    outcome: RelocalizationOutcome,
    stack_s: f64,
    ms: f64,
    attempts: Vec<serde_json::Value>,
}

impl StackSearch<'_> {
    /// Searches ever longer stacks (`lengths`) until the decision answers; with `every_step`, every
    /// length is searched and reported, the outcome still the first answer's.
    fn search(&self, search: &StartSearch, lengths: &[f64], every_step: bool) -> Decided {
        // The scans' local frame at the truth: what the search should find.
        let truth_global_from_local = self.truth_pose.map(|t| t * self.first_local.inverse());
        let attempt_error = |global_from_local: &Rigid2| {
            self.truth_pose.map(|t| {
                let p = global_from_local * self.first_local;
                (p.translation.vector - t.translation.vector).norm()
            })
        };
        let mut ms = 0.0;
        let mut attempts = Vec::new();
        let mut decided: Option<(Stack, Option<SearchEvidence>, RelocalizationOutcome, f64)> = None;
        for (k, &length) in lengths.iter().enumerate() {
            let end = self.sampled.offset_by(length);
            let scans: Stack = self
                .nodes
                .iter()
                .enumerate()
                .filter(|(k, (t, _, _))| *k == 0 || *t <= end)
                .map(|(_, (_, pose, points))| (*pose, points.clone()))
                .collect();
            let start = Instant::now();
            let evidence = search.evidence(&scans);
            let outcome = search.decide(evidence.as_ref());
            let attempt_ms = start.elapsed().as_secs_f64() * 1e3;
            attempts.push(json!({
                "stack_s": length,
                "scans": scans.len(),
                "answer": match outcome {
                    RelocalizationOutcome::Found(_) => "found",
                    RelocalizationOutcome::Ambiguous { .. } => "ambiguous",
                    RelocalizationOutcome::NotFound => "not_found",
                },
                "translation_error_m": evidence.as_ref().and_then(|e| attempt_error(&e.global_from_local)),
                "first_scan_error_m": evidence.as_ref().and_then(|e| attempt_error(&e.first_scan_global_from_local)),
                "sharp_score": evidence.as_ref().map(|e| e.sharp_score),
                "runner_up_score": evidence.as_ref().and_then(|e| e.runner_up.map(|r| r.0)),
                "weakest_z": evidence.as_ref().and_then(|e| e.weakest.map(|w| w.0)),
                "distinct_candidates": evidence.as_ref().map(|e| e.distinct_candidates),
                "first_scan_shift_m": evidence.as_ref().map(|e| e.first_scan_shift_m),
                "truth_fit": truth_global_from_local.and_then(|g| search.fit(&scans, &g)).map(|f| f.sharp_score),
                "ms": attempt_ms,
            }));
            let answered = matches!(outcome, RelocalizationOutcome::Found(_));
            if decided.is_none() {
                ms += attempt_ms;
                if answered || k + 1 == lengths.len() {
                    decided = Some((scans, evidence, outcome, length));
                }
            }
            if decided.is_some() && !every_step {
                break;
            }
        }
        let Some((scans, evidence, outcome, stack_s)) = decided else {
            unreachable!("the last length always decides");
        };
        Decided {
            scans,
            evidence,
            outcome,
            stack_s,
            ms,
            attempts,
        }
    }
}

/// A sample whose first node has a truth, as [`Judge::judge`] scores it.
struct JudgedSample<'a> {
    sampled: Timestamp,
    /// The first node's time: the scan scored.
    scored_time: Timestamp,
    first_local: Rigid2,
    truth_pose: Rigid2,
    nodes: &'a [(Timestamp, Rigid2, Vec<Point2<f32>>)],
    llo_ms: f64,
}

/// What an answer is judged against: the search (for the fit at the truth), the reference and the
/// relations.
struct Judge<'a> {
    search: &'a StartSearch,
    reference: &'a Reference,
    relations: &'a [Relation],
}

impl Judge<'_> {
    /// Scores one sample's decision into `tally` and returns its line of the report.
    fn judge(
        &self,
        sample: &JudgedSample<'_>,
        decided: Decided,
        tally: &mut Tally,
    ) -> serde_json::Value {
        let JudgedSample {
            sampled,
            scored_time,
            first_local,
            truth_pose,
            nodes,
            llo_ms,
        } = *sample;
        let Decided {
            scans,
            evidence,
            outcome,
            stack_s: stack_s_used,
            ms,
            attempts,
        } = decided;
        let reference = self.reference;
        let truth_global_from_local = truth_pose * first_local.inverse();
        // How the cloud fits at the truth: the best any search could find.
        let truth_fit = self.search.fit(&scans, &truth_global_from_local);
        // How far the scan is from where the map's run went: far means its area may not be mapped.
        let nearest_mapped_m = reference
            .map_poses
            .iter()
            .map(|(_, h)| (h.translation.vector - truth_pose.translation.vector).norm())
            .fold(f64::INFINITY, f64::min);
        // The relations' truths of this scan, and how far the scored truth lies from them.
        let relation_truths = relations_truth(
            self.relations,
            &reference.map_poses,
            &reference.full_poses,
            scored_time,
        );
        let truth_vs_relations_m = median(
            relation_truths
                .iter()
                .map(|r| (r.translation.vector - truth_pose.translation.vector).norm())
                .collect(),
        );
        // The evidence's best pose is reported even when refused, to show what a refusal avoided.
        let error =
            |global_from_local: &Rigid2| pose_error(global_from_local, &first_local, &truth_pose);
        let best_error = evidence.as_ref().map(|e| error(&e.global_from_local));
        // The error in the scan's own frame (x ahead, y left): along a corridor or across it.
        let error_in_scan_frame = |global_from_local: &Rigid2| {
            let d = truth_pose.inverse() * (global_from_local * first_local);
            [d.translation.x, d.translation.y, d.theta().to_degrees()]
        };
        let relations_error = |global_from_local: &Rigid2| {
            let p = global_from_local * first_local;
            median(
                relation_truths
                    .iter()
                    .map(|r| (r.translation.vector - p.translation.vector).norm())
                    .collect(),
            )
        };
        let best_relations_error_m = evidence
            .as_ref()
            .and_then(|e| relations_error(&e.global_from_local));
        let answer = match &outcome {
            RelocalizationOutcome::Found(found) => {
                if let Some(e) = relations_error(&found.global_from_local) {
                    tally.relations_checked += 1;
                    if e > SUCCESS.translation_m {
                        tally.relations_wrong += 1;
                    }
                }
                let (dt, dth) = error(&found.global_from_local);
                if SUCCESS.accepts(dt, dth) {
                    tally.right += 1;
                    "right"
                } else {
                    tally.wrong_errors_m.push(dt);
                    "wrong"
                }
            }
            RelocalizationOutcome::Ambiguous { .. } => {
                tally.refused += 1;
                "ambiguous"
            }
            RelocalizationOutcome::NotFound => {
                tally.refused += 1;
                "not_found"
            }
        };
        // The newest stacked node (the scored node itself for one scan): its local pose and its truth.
        let stack_end = sampled.offset_by(stack_s_used);
        let newest = nodes
            .iter()
            .rfind(|(t, _, _)| *t <= stack_end)
            .and_then(|(t, local, _)| Some((*local, *reference.truth.get(t)?)));
        // The stack's own shape: the newest node's offset from the first as LLO made it minus the truth's,
        // in the first node's frame (x ahead, y left, degrees), and the true distance between them. LLO's
        // first seconds, matched against a submap that has seen its free space once or twice, come out
        // short (docs/BENCHMARK-HISTORY.md "Session 43").
        let stack_shape_error =
            newest
                .filter(|_| scans.len() > 1)
                .map(|(newest_local, truth_newest)| {
                    let estimated = first_local.inverse() * newest_local;
                    let true_offset = truth_pose.inverse() * truth_newest;
                    [
                        estimated.translation.x - true_offset.translation.x,
                        estimated.translation.y - true_offset.translation.y,
                        normalize_angle(estimated.theta() - true_offset.theta()).to_degrees(),
                        true_offset.translation.vector.norm(),
                    ]
                });
        // The answer judged where the robot is when it arrives, at the newest stacked node, by the same
        // tolerances: the scored first node carries LLO's start of the stack, the newest one is the pose
        // the robot goes on with.
        let newest_node_error = match (&outcome, newest) {
            (RelocalizationOutcome::Found(found), Some((newest_local, truth_newest))) => Some(
                pose_error(&found.global_from_local, &newest_local, &truth_newest),
            ),
            _ => None,
        };
        json!({
            "time": sampled.to_string(),
            "scored_time": scored_time.to_string(),
            "stack_shape_error": stack_shape_error,
            "newest_node_error_m": newest_node_error.map(|e| e.0),
            "newest_node_answer": newest_node_error.map(|(dt, dth)| {
                if SUCCESS.accepts(dt, dth) { "right" } else { "wrong" }
            }),
            "answer": answer,
            "success": answer == "right",
            "translation_error_m": best_error.map(|e| e.0),
            "error_in_scan_frame": evidence.as_ref().map(|e| error_in_scan_frame(&e.global_from_local)),
            "first_scan_error_in_scan_frame": evidence.as_ref().map(|e| error_in_scan_frame(&e.first_scan_global_from_local)),
            "rotation_error_deg": best_error.map(|e| e.1),
            "score": evidence.as_ref().map(|e| e.score),
            "sharp_score": evidence.as_ref().map(|e| e.sharp_score),
            "runner_up_score": evidence.as_ref().and_then(|e| e.runner_up.map(|r| r.0)),
            "runner_up_from_best": evidence.as_ref().and_then(|e| e.runner_up.map(|r| r.1)),
            "weakest_z": evidence.as_ref().and_then(|e| e.weakest.map(|w| w.0)),
            "weakest_score": evidence.as_ref().and_then(|e| e.weakest.map(|w| w.1)),
            "distinct_candidates": evidence.as_ref().map(|e| e.distinct_candidates),
            "first_scan_shift_m": evidence.as_ref().map(|e| e.first_scan_shift_m),
            "cloud_points": evidence.as_ref().map(|e| e.cloud_points),
            "scans_stacked": scans.len(),
            "stack_s_used": stack_s_used,
            "attempts": attempts,
            "truth_sharp_score": truth_fit.map(|f| f.sharp_score),
            "truth_known_fraction": truth_fit.map(|f| f.known_fraction),
            "truth_hit_fraction": truth_fit.map(|f| f.hit_fraction),
            "ms": ms,
            "llo_ms": llo_ms,
            "nearest_mapped_m": nearest_mapped_m,
            "relations": relation_truths.len(),
            "truth_vs_relations_m": truth_vs_relations_m,
            "relations_error_m": best_relations_error_m,
        })
    }
}

/// The report: the tallies of the `n` samples, their search times, and `results`, one line each.
fn summary_report(
    args: &RelocalizeArgs,
    n: usize,
    tally: &Tally,
    times_ms: &[f64],
    results: &[serde_json::Value],
    precompute_ms: f64,
    reference: &Reference,
) -> serde_json::Value {
    let mut sorted = times_ms.to_vec();
    sorted.sort_by(f64::total_cmp);
    let answered = tally.right + tally.wrong_errors_m.len();
    let mut wrong_sorted = tally.wrong_errors_m.clone();
    wrong_sorted.sort_by(f64::total_cmp);
    let map = &reference.map;
    json!({
        "input": args.input.display().to_string(),
        "stack_s": args.stack_s,
        "grow_to_s": args.grow_to_s,
        "grow_step_s": args.grow_to_s.map(|_| args.grow_step_s),
        "samples": n,
        "success_rate": tally.right as f64 / n as f64,
        "precision": precision(tally.right, wrong_sorted.len()),
        "answered_rate": answered as f64 / n as f64,
        "right": tally.right,
        "wrong": wrong_sorted.len(),
        "refused": tally.refused,
        "wrong_over_1m": wrong_sorted.iter().filter(|&&d| d > 1.0).count(),
        "wrong_median_m": (!wrong_sorted.is_empty()).then(|| percentile(&wrong_sorted, 0.5)),
        "wrong_max_m": wrong_sorted.last(),
        "timed": "StartSearch::evidence + decide: merging, thinning, whole-map search, refinement and acceptance tests (not LLO nor the map precomputation)",
        "median_ms": percentile(&sorted, 0.5),
        "p95_ms": percentile(&sorted, 0.95),
        "precompute_ms": precompute_ms,
        "map_cells": [map.limits().width, map.limits().height],
        "truth": format!("{:?}", args.truth).to_lowercase(),
        "truth_alignment_radius_m": (args.truth == Truth::Aligned).then_some(LOCAL_ALIGNMENT_RADIUS_M),
        "answers_checked_by_relations": tally.relations_checked,
        "answers_off_by_relations": tally.relations_wrong,
        "success_translation_m": SUCCESS.translation_m,
        "success_rotation_deg": SUCCESS.rotation_deg,
        "on_observed_ground": observed_ground_summary(results),
        "stack_shape_along_error_m": stack_shape_summary(results),
        "results": results,
    })
}

/// Largest gap between a relation's stamp and a pose of a run for the pose to stand for it, seconds (the
/// reference tool's).
const RELATION_STAMP_GAP_S: f64 = 0.1;

/// Longest stretch of driving (seconds) from a relation's stamp after the cut to a sampled scan over which
/// the full run's relative motion carries a relation's truth to it.
const RELATION_BRIDGE_S: f64 = 2.0;

/// The pose nearest in time to `t` within [`RELATION_STAMP_GAP_S`] in `poses` (time-ordered).
fn pose_at(poses: &[(Timestamp, Rigid2)], t: Timestamp) -> Option<Rigid2> {
    let i = poses.partition_point(|(s, _)| *s < t);
    [i.checked_sub(1), Some(i)]
        .into_iter()
        .flatten()
        .filter_map(|k| poses.get(k))
        .min_by(|a, b| {
            a.0.seconds_since(t)
                .abs()
                .total_cmp(&b.0.seconds_since(t).abs())
        })
        .filter(|(s, _)| s.seconds_since(t).abs() <= RELATION_STAMP_GAP_S)
        .map(|(_, p)| *p)
}

/// The truths of the scan at `t` in the map's frame that the relations give: for each relation between a
/// scan drawn into the map (in `map_poses`) and a scan at most [`RELATION_BRIDGE_S`] from `t` not in the
/// map, the map's pose of the first composed with the relation, then carried to `t` by the full run's
/// relative motion. The relations were built from manually checked scan matches, so these truths depend
/// on neither run's loop closures, only on where the map itself drew the related scan.
fn relations_truth(
    relations: &[Relation],
    map_poses: &[(Timestamp, Rigid2)],
    full_poses: &[(Timestamp, Rigid2)],
    t: Timestamp,
) -> Vec<Rigid2> {
    let Some(full_at_t) = pose_at(full_poses, t) else {
        return Vec::new();
    };
    let map_end = map_poses.last().map(|(s, _)| *s);
    let in_map = |s: Timestamp| map_end.is_some_and(|end| s <= end);
    let mut out = Vec::new();
    for r in relations {
        // `mapped_from_near`: the relative pose from the mapped scan to the one near `t`.
        let (mapped, near, mapped_from_near) = if in_map(r.t1) && !in_map(r.t2) {
            (r.t1, r.t2, r.delta)
        } else if in_map(r.t2) && !in_map(r.t1) {
            (r.t2, r.t1, r.delta.inverse())
        } else {
            continue;
        };
        if near.seconds_since(t).abs() > RELATION_BRIDGE_S {
            continue;
        }
        let (Some(map_from_mapped), Some(full_from_near)) =
            (pose_at(map_poses, mapped), pose_at(full_poses, near))
        else {
            continue;
        };
        out.push(map_from_mapped * mapped_from_near * full_from_near.inverse() * full_at_t);
    }
    out
}

/// The median of `values` (`None` if empty).
fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    (!values.is_empty()).then(|| percentile(&values, 0.5))
}

/// Quantiles (p10, median, p90, metres) and count of the stacks' along-track shape error
/// (`stack_shape_error[0]`: the newest node's offset from the first as LLO made it, ahead of the truth's
/// when positive); `None` without stacks.
fn stack_shape_summary(results: &[serde_json::Value]) -> Option<serde_json::Value> {
    let mut along: Vec<f64> = results
        .iter()
        .filter_map(|r| r["stack_shape_error"][0].as_f64())
        .collect();
    if along.is_empty() {
        return None;
    }
    along.sort_by(f64::total_cmp);
    Some(json!({
        "stacks": along.len(),
        "p10": percentile(&along, 0.1),
        "median": percentile(&along, 0.5),
        "p90": percentile(&along, 0.9),
    }))
}

/// The share of answers that were right (1 with no answer: nothing wrong was said).
fn precision(right: usize, wrong: usize) -> f64 {
    if right + wrong > 0 {
        right as f64 / (right + wrong) as f64
    } else {
        1.0
    }
}

/// A sample is on observed ground when at least this share of its cloud's points, placed at the truth,
/// fall on cells the map observed: a search can only be asked to place what the map shows.
const OBSERVED_GROUND_SHARE: f64 = 0.8;

/// Success, precision and time over the samples on observed ground (see [`OBSERVED_GROUND_SHARE`]),
/// from the per-sample results (`answer`, `truth_known_fraction`, `ms`). Samples without a truth pose
/// cannot be judged and are left out.
fn observed_ground_summary(results: &[serde_json::Value]) -> serde_json::Value {
    let observed: Vec<&serde_json::Value> = results
        .iter()
        .filter(|r| {
            r["truth_known_fraction"]
                .as_f64()
                .is_some_and(|f| f >= OBSERVED_GROUND_SHARE)
        })
        .collect();
    let count = |answer: &str| observed.iter().filter(|r| r["answer"] == answer).count();
    let (right, wrong) = (count("right"), count("wrong"));
    let n = observed.len();
    let mut ms: Vec<f64> = observed.iter().filter_map(|r| r["ms"].as_f64()).collect();
    ms.sort_by(f64::total_cmp);
    let newest = |answer: &str| {
        observed
            .iter()
            .filter(|r| r["newest_node_answer"] == answer)
            .count()
    };
    let (newest_right, newest_wrong) = (newest("right"), newest("wrong"));
    json!({
        "min_known_share": OBSERVED_GROUND_SHARE,
        "samples": n,
        "right": right,
        "wrong": wrong,
        "refused": n - right - wrong,
        "success_rate": (n > 0).then(|| right as f64 / n as f64),
        "precision": precision(right, wrong),
        "median_ms": (!ms.is_empty()).then(|| percentile(&ms, 0.5)),
        // The same answers judged at the newest stacked node (where the robot is when it arrives).
        "newest_node": {
            "right": newest_right,
            "wrong": newest_wrong,
            "success_rate": (n > 0).then(|| newest_right as f64 / n as f64),
            "precision": precision(newest_right, newest_wrong),
        },
    })
}

/// How the answers went: right, wrong (and how far off), refused.
#[derive(Default)]
struct Tally {
    right: usize,
    refused: usize,
    wrong_errors_m: Vec<f64>,
    /// Answers with at least one relation's truth.
    relations_checked: usize,
    /// … of which more than the success distance from the relations' (median) truth.
    relations_wrong: usize,
}

/// The nodes `(time, local_from_tracking, filtered points)` LLO makes from `stack_s` seconds of `recording`
/// starting at the scan at `start` (only that scan's node when `stack_s` is 0), first node first: the local
/// map a session start would relocalize.
fn local_map(
    recording: &Recording,
    start: Timestamp,
    stack_s: f64,
    options: &mapping::local_slam::LocalTrajectoryBuilderOptions,
) -> Vec<(Timestamp, Rigid2, Vec<Point2<f32>>)> {
    let end = start.offset_by(stack_s);
    // Odometry from a moment before the first scan, so that LLO can interpolate at it.
    let lead_in = start.offset_by(-ODOMETRY_LEAD_IN_S);
    let window = Recording {
        events: recording
            .events
            .iter()
            .filter(|e| match e {
                SensorEvent::Scan(s) => s.time >= start && s.time <= end,
                other => other.time() >= lead_in && other.time() <= end,
            })
            .cloned()
            .collect(),
        base_from_laser: recording.base_from_laser,
        report: recording.report.clone(),
    };
    let mut nodes = Vec::new();
    run_llo(&window, options, 0.0, None, &mut |items| {
        nodes.extend(items.into_iter().filter_map(|item| match item {
            UploadItem::NodeAdded(node) => Some((node.time, node.local_pose, node.points)),
            _ => None,
        }));
        true
    });
    nodes
}

/// Seconds of odometry before a stack's first scan given to LLO.
const ODOMETRY_LEAD_IN_S: f64 = 0.5;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_observed_ground_summary_judges_only_samples_the_map_shows() {
        let results = [
            json!({"answer": "right", "truth_known_fraction": 0.95, "ms": 300.0, "newest_node_answer": "wrong"}),
            json!({"answer": "wrong", "truth_known_fraction": 0.85, "ms": 500.0, "newest_node_answer": "right"}),
            json!({"answer": "ambiguous", "truth_known_fraction": 0.9, "ms": 900.0}),
            // Off the map's observed ground, or with no truth: not judged here.
            json!({"answer": "wrong", "truth_known_fraction": 0.4, "ms": 100.0}),
            json!({"answer": "no_truth"}),
        ];
        let summary = observed_ground_summary(&results);
        assert_eq!(summary["samples"], 3);
        assert_eq!(summary["right"], 1);
        assert_eq!(summary["wrong"], 1);
        assert_eq!(summary["refused"], 1);
        assert_eq!(summary["precision"], 0.5);
        assert_eq!(summary["median_ms"], 500.0);
        assert_eq!(summary["newest_node"]["right"], 1);
        assert_eq!(summary["newest_node"]["wrong"], 1);
        assert_eq!(
            observed_ground_summary(&[])["success_rate"],
            serde_json::Value::Null
        );
    }

    #[test]
    fn the_stack_shape_summary_counts_only_stacks() {
        let results = [
            json!({"stack_shape_error": [-0.3, 0.01, 0.2, 2.5]}),
            json!({"stack_shape_error": [0.02, 0.0, 0.0, 2.0]}),
            json!({"stack_shape_error": [-0.01, 0.0, 0.0, 1.0]}),
            // A single scan, or a stack without the truth of its newest node.
            json!({"stack_shape_error": null}),
            json!({"answer": "no_scan"}),
        ];
        let summary = stack_shape_summary(&results).expect("three stacks");
        assert_eq!(summary["stacks"], 3);
        assert_eq!(summary["median"], -0.01);
        assert_eq!(summary["p10"], -0.3);
        assert_eq!(summary["p90"], 0.02);
        assert_eq!(stack_shape_summary(&results[3..]), None);
    }
}
