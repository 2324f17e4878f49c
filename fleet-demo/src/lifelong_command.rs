//! `evermap-demo lifelong`: the paper's month-in-a-supermarket experiment on the simulated changing store.
//!
//! Session 0 maps the store; sessions 1..N are cleaning runs on later days (goods, pallets, displays and
//! doors changed, people and carts about) that start with no prior, relocalize, localize by GLM and feed
//! the lifelong map, which trims stale submaps per the policy. Sessions are generated one at a time, so
//! memory holds one session's sensor data. Every figure is measured against the simulator's ground truth
//! in one fixed frame: `world_from_map` is the rigid alignment of session 0's trajectory to its truth, so
//! a later session is only "correctly localized" where it is correct in the map the fleet shares.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::Context as _;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use mapping::geometry::{Rigid2, Rigid2Ext as _};
use mapping::grid::ProbabilityGrid;
use mapping::lifelong::{
    ConstraintKindCounts, LifelongMap, MAP_CHANGE_TOLERANCE_M, MapChange, TrimPolicy,
    map_change_rate, render_submaps_newest,
};
use mapping::metrics::{
    MAP_WORLD_TOLERANCE_M, MapWorldAgreement, ScoringOptions, SessionScore, align_to_truth,
    map_world_agreement, pose_error, score_run, score_session, truth_at,
};
use mapping::sensor::Timestamp;
use robot_agent::lifelong_run::{
    RunResume, SessionEnd, SessionInput, SessionRecord, SessionSummary, SessionsConfig,
    resume_session_inputs, run_session_inputs,
};
use robot_agent::line_chart::{LineChart, Series};
use robot_agent::{map_image, process_stats};
use serde::Serialize;
use serde_json::json;
use simulator::{SessionOptions, Store, World};

use crate::lifelong_resume::{self, RunIdentity};

/// Arguments of `lifelong`.
#[derive(Args)]
pub struct LifelongArgs {
    /// Which world: `store` (a realistic supermarket) or `aisles` (identical shelf rows, adversarial).
    #[arg(long, value_enum, default_value_t = World::Store)]
    world: World,
    /// Number of sessions after the mapping session 0 (the paper: 25).
    #[arg(long, default_value_t = 25)]
    sessions: u32,
    /// Seed of the store layout, its change schedule and the routes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Trimming policy (clt, delete, keep, frozen); overrides the configuration's (default clt).
    #[arg(long)]
    policy: Option<TrimPolicy>,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// A TOML file overriding the default configuration (see `SessionsConfig`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Length cap of sessions 1..N, seconds (default: the simulator's, 300 s).
    #[arg(long)]
    session_duration_s: Option<f64>,
    /// Length cap of the mapping session 0, seconds (default: the whole cleaning route, ~62 min in `store`,
    /// ~54 min in `aisles`).
    #[arg(long)]
    mapping_duration_s: Option<f64>,
    /// Dock starts: each later session starts where the previous one ended (1 in 5 is carried to a random
    /// place instead), and the robot checks the last pose it had first (`SessionStart::from_dock`).
    #[arg(long)]
    dock_starts: bool,
    /// Continue the run in `--out` after its last ended session, from the resume point it wrote there
    /// (`resume/`), up to `--sessions`. Every other argument and the configuration must be the run's.
    /// `report.json` goes on with the sessions before; `trajectories.csv` holds the resumed sessions.
    #[arg(long)]
    resume: bool,
    /// With `--resume`: continue under the configuration given now although the run was started under
    /// another (every other argument still the run's): an A/B test of later sessions from one resume
    /// point. `report.json`'s `configuration_changed_at_sessions` lists the sessions from which it changed.
    #[arg(long, requires = "resume")]
    resume_under_new_config: bool,
}

/// What one session scored and did, as `report.json` lists it.
#[derive(Debug, Serialize)]
struct SessionRow {
    session: u32,
    /// The scores of what the session lived ([`SessionScore`]: MRCL from the estimate at the time of
    /// each scan and smoothed, placement error, initialization, AMS over every scan).
    #[serde(flatten)]
    score: SessionScore,
    /// Map change rate after this session: session 0's map against the map as its newest submaps
    /// describe the site now (both rendered newest-wins, tolerance [`MAP_CHANGE_TOLERANCE_M`]).
    mcr: Option<f64>,
    /// The simulator's own change rate from day 0 to this session's day, measured the same way.
    world_change_rate: f64,
    /// The map after this session (newest-wins) against this session's day of the world, over the area
    /// the last [`MAP_WORLD_SESSIONS`] sessions observed: the share of the day's occupied structure the
    /// map shows, and the share of the map's occupied cells the day's world no longer has.
    map_shows_world: Option<f64>,
    map_gone_from_world: Option<f64>,
    /// The cell counts behind those two shares.
    map_world: Option<MapWorldAgreement>,
    nodes: usize,
    submaps: usize,
    constraints: usize,
    /// Those constraints by kind (LLO's, GLM's and trees' node-to-submap, odometry, trees' others).
    constraints_by_kind: ConstraintKindCounts,
    trimmed_total: usize,
    /// Submaps of sessions that did not update the map (never placed; `frozen`), dropped so far.
    dropped_total: usize,
    pgr_ms: f64,
    /// CPU time of that refinement on its thread, milliseconds (the cost on a loaded machine).
    pgr_cpu_ms: Option<f64>,
    /// Levenberg-Marquardt steps of every optimization `pgr_ms` covers.
    pgr_iterations: usize,
    /// Values stored for the largest Cholesky factor those steps used (what a step costs grows with).
    pgr_factor_nonzeros: usize,
    peak_rss_mb: Option<f64>,
    /// Resident memory when the session ended, MB (the peak never falls; this does).
    rss_mb: Option<f64>,
    /// Scans LLO matched.
    scans: usize,
    closures: usize,
    cross_session_closures: usize,
    /// Mean score of the session's accepted GLM matches against older sessions' submaps (what the
    /// reports called AMS before it was measured over every scan).
    glm_match_score_mean: Option<f64>,
    trimmed: usize,
    /// The session's own submaps dropped at its end (it did not update the map).
    dropped: usize,
    tree_edges: usize,
    trim_kld_mean: Option<f64>,
    /// Branch-and-bound score of the session-start relocalization, when it found a pose.
    relocalization_score: Option<f32>,
    /// Why the start was refused (`ambiguous`, `not_found`), if it was.
    relocalization_refused: Option<String>,
    /// Relocalization retries while the session was unplaced.
    relocalization_retries: usize,
    /// The node count at which a retry placed the session (`null`: placed at its start, or never).
    placed_by_retry_at_node: Option<usize>,
    /// The node count at which its placement was committed (probation passed).
    committed_at_node: Option<usize>,
    /// Placements revoked (probation failed).
    revocations: usize,
    /// Whether the session ended on probation (its placement never confirmed; dropped).
    ended_on_probation: bool,
    /// Whether the session ended placed in the map with a committed placement.
    placed: bool,
    /// With `--dock-starts`: whether the session started exactly where the previous one ended (`false`:
    /// the robot was carried elsewhere).
    starts_at_previous_end: Option<bool>,
    /// With `--dock-starts`: whether the check of the robot's dock agreed (placed there); `None` where
    /// there was no dock to check (the previous session ended unplaced).
    dock_agreed: Option<bool>,
}

/// Scores each session as it ends and rewrites `report.json`, so a long run keeps what it measured.
struct Reporter<'a> {
    args: &'a LifelongArgs,
    config: &'a SessionsConfig,
    options: &'a SessionOptions,
    store: &'a Store,
    scoring: ScoringOptions,
    /// The truth of each generated session (pushed by the simulator, read as sessions end).
    truths: &'a Mutex<Vec<Vec<(Timestamp, Rigid2)>>>,
    /// With `--dock-starts`, per generated session: whether it starts where the previous one ended.
    starts_at_previous_end: &'a Mutex<Vec<bool>>,
    /// Session 0's map aligned to its truth, once session 0 has ended.
    world_from_map: Option<Rigid2>,
    /// Day 0's layout as a map would see it.
    truth_day_zero: ProbabilityGrid,
    rows: Vec<SessionRow>,
    details: Vec<SessionSummary>,
    /// The latest map change (after the last session that ended), for the picture.
    last_change: Option<(MapChange, ProbabilityGrid)>,
    started: Instant,
    /// What the run was started with, kept with its resume points.
    identity: RunIdentity,
    /// The rows and details of the sessions before a resumed run, as its report had them.
    earlier_rows: Vec<serde_json::Value>,
    earlier_details: Vec<serde_json::Value>,
    /// The sessions from which a resumed run went on under another configuration
    /// (`--resume-under-new-config`), earlier resumes' first.
    configuration_changed_at: Vec<u32>,
}

impl Reporter<'_> {
    fn session_ended(&mut self, end: &SessionEnd<'_>) -> anyhow::Result<()> {
        let k = end.summary.session;
        let truth = self
            .truths
            .lock()
            .map_err(|_| anyhow::anyhow!("the truth lock is poisoned"))?
            .get(k as usize)
            .cloned()
            .with_context(|| format!("no truth for session {k}"))?;
        // The fixed frame: session 0's end-of-session trajectory aligned to its truth.
        let world_from_map = *self
            .world_from_map
            .get_or_insert_with(|| align_to_truth(&end.record.smoothed, &truth));
        let score = score_session(&end.record.track(&truth), &world_from_map, &self.scoring);
        let resolution = self.config.local.submaps.resolution;
        let change = map_change(end.map, resolution);
        let world_today = self.store.occupancy(k, resolution).surface_grid();
        let world_change_rate =
            map_change_rate(&self.truth_day_zero, &world_today, MAP_CHANGE_TOLERANCE_M).rate;
        let map_world = change.as_ref().and_then(|(_, map_now)| {
            let recent = k.saturating_sub(MAP_WORLD_SESSIONS - 1);
            let area = render_submaps_newest(
                end.map
                    .placed_submaps_by_id()
                    .filter(|(id, _)| id.trajectory >= recent)
                    .map(|(_, g)| g),
                resolution,
            )?;
            Some(map_world_agreement(
                map_now,
                &world_today,
                &world_from_map,
                &area,
                MAP_WORLD_TOLERANCE_M,
            ))
        });
        let s = end.summary;
        let counts = s.counts;
        let starts_at_previous_end = self
            .starts_at_previous_end
            .lock()
            .map_err(|_| anyhow::anyhow!("the dock-start lock is poisoned"))?
            .get(k as usize)
            .copied();
        self.rows.push(SessionRow {
            session: k,
            score,
            mcr: change.as_ref().map(|(c, _)| c.rate),
            world_change_rate,
            map_shows_world: map_world.and_then(|a| a.shown()),
            map_gone_from_world: map_world.and_then(|a| a.gone()),
            map_world,
            nodes: counts.nodes,
            submaps: counts.submaps,
            constraints: counts.constraints,
            constraints_by_kind: counts.constraints_by_kind,
            trimmed_total: counts.trimmed_total,
            dropped_total: counts.dropped_total,
            pgr_ms: s.finish_ms,
            pgr_cpu_ms: s.finish_cpu_ms,
            pgr_iterations: s.finish_iterations(),
            pgr_factor_nonzeros: s.finish_factor_nonzeros(),
            peak_rss_mb: s.peak_rss_mb,
            rss_mb: s.rss_mb,
            scans: end.record.smoothed.len(),
            closures: s.closures,
            cross_session_closures: s.cross_session_closures,
            glm_match_score_mean: if k == 0 {
                (s.closures > 0).then_some(s.ams)
            } else {
                s.cross_session_ams
            },
            trimmed: s.trimmed,
            dropped: s.dropped,
            tree_edges: s.tree_edges,
            trim_kld_mean: s.trim_kld_mean,
            relocalization_score: s.relocalization_score,
            relocalization_refused: s.relocalization_refused.clone(),
            relocalization_retries: s.relocalization_retries,
            placed_by_retry_at_node: s.placed_by_retry_at_node,
            committed_at_node: s.committed_at_node,
            revocations: s.revoked.len(),
            ended_on_probation: s.ended_on_probation,
            placed: k == 0 || s.placed,
            starts_at_previous_end,
            dock_agreed: s.dock_check.as_ref().map(|d| d.agreed),
        });
        let mut details = s.clone();
        // Each session-start search's best candidate against the truth (for calibrating its tests).
        for (search, best) in details
            .searches
            .iter_mut()
            .zip(&end.record.start.search_bests)
        {
            search.best_error_m = best.as_ref().and_then(|b| {
                let truth = truth_at(&truth, b.time)?;
                Some(pose_error(&world_from_map, &b.map_from_base, &truth).0)
            });
        }
        self.details.push(details);
        self.last_change = change;
        eprintln!(
            "session {k:>2}: init {:<5} placed {} committed {} placement {} mrcl {:.3} (smoothed {:.3}) wrong {:.3} ams {} ate {:.3} m | mcr {} world {:.3} | map shows {} of the world, {} gone | nodes {} submaps {} constraints {} | pgr {:.0} ms, {} ms cpu ({} LM steps)",
            if k == 0 {
                "-".to_string()
            } else {
                score.initialized.to_string()
            },
            score
                .placed_after_s
                .map_or("-".to_string(), |s| format!("{s:.1} s")),
            score
                .committed_after_s
                .map_or("-".to_string(), |s| format!("{s:.1} s")),
            score
                .placement_error_m
                .map_or("-".to_string(), |m| format!("{m:.2} m")),
            score.mrcl,
            score.mrcl_smoothed,
            score.mrwl,
            score.ams.map_or("-".to_string(), |a| format!("{a:.3}")),
            score.ate_rms_m,
            self.rows
                .last()
                .and_then(|r| r.mcr)
                .map_or("-".to_string(), |m| format!("{m:.3}")),
            world_change_rate,
            share(map_world.and_then(|a| a.shown())),
            share(map_world.and_then(|a| a.gone())),
            counts.nodes,
            counts.submaps,
            counts.constraints,
            s.finish_ms,
            s.finish_cpu_ms
                .map_or("-".to_string(), |ms| format!("{ms:.0}")),
            s.finish_iterations()
        );
        // The report first: a resume point never names a session the report does not hold.
        self.write_report(false, None)?;
        lifelong_resume::write(
            &self.args.out,
            &self.identity,
            k,
            end.map,
            &world_from_map,
            end.dock.as_ref(),
        )
    }

    /// Every session's row so far, the resumed run's earlier ones first.
    fn all_rows(&self) -> anyhow::Result<Vec<serde_json::Value>> {
        let mut rows = self.earlier_rows.clone();
        for row in &self.rows {
            rows.push(serde_json::to_value(row)?);
        }
        Ok(rows)
    }

    /// The report of the sessions ended so far; `complete` once the run is over.
    fn report(
        &self,
        complete: bool,
        data_duration_s: Option<f64>,
    ) -> anyhow::Result<serde_json::Value> {
        let rows = self.all_rows()?;
        let mut later: Vec<SessionScore> = Vec::new();
        for row in &rows {
            if row["session"].as_u64().is_some_and(|k| k > 0) {
                later.push(
                    serde_json::from_value(row.clone())
                        .context("a session row of the report holds no session score")?,
                );
            }
        }
        let run = score_run(&later);
        let mut details = self.earlier_details.clone();
        for d in &self.details {
            details.push(serde_json::to_value(d)?);
        }
        let last = self.rows.last();
        Ok(json!({
            "world": self.args.world.name(),
            "seed": self.args.seed,
            "policy": self.config.lifelong.policy.name(),
            "complete": complete,
            "configuration_changed_at_sessions": self.configuration_changed_at,
            "session_options": self.options,
            "scoring": self.scoring,
            "map_change_tolerance_m": MAP_CHANGE_TOLERANCE_M,
            "mcr_detail": self.last_change.as_ref().map(|(c, _)| json!({
                "rate": c.rate, "unchanged": c.unchanged, "removed": c.removed, "added": c.added,
            })),
            "summary": {
                "sessions_ended": rows.len(),
                "score": run,
                // The figures the reports quote, at the top level.
                "cri": run.cri,
                "cri_committed": run.cri_committed,
                "mrcl": run.mrcl,
                "mrcl_smoothed": run.mrcl_smoothed,
                "mrcl_ceiling": run.mrcl_ceiling,
                "ams_mean": run.ams_mean,
                "ams_min": run.ams_min,
                "wrong_placements": run.wrong_placements,
                "mrwl": run.mrwl,
                "wrong_estimate_sessions": run.wrong_estimate_sessions,
                "mcr": last.and_then(|r| r.mcr),
                "world_change_rate": last.map(|r| r.world_change_rate),
                "map_shows_world": last.and_then(|r| r.map_shows_world),
                "map_gone_from_world": last.and_then(|r| r.map_gone_from_world),
                "map_world_sessions": MAP_WORLD_SESSIONS,
                "map_world_tolerance_m": MAP_WORLD_TOLERANCE_M,
                "final": last.map(|r| json!({
                    "nodes": r.nodes, "submaps": r.submaps, "constraints": r.constraints,
                    "trimmed_total": r.trimmed_total, "dropped_total": r.dropped_total,
                })),
                "dock_starts": self.options.dock_starts.then(|| {
                    let later = rows.iter().filter(|r| r["session"].as_u64().is_some_and(|k| k > 0));
                    let at_end = |r: &serde_json::Value| r["starts_at_previous_end"].as_bool();
                    let at_dock = |r: &serde_json::Value| r["dock_agreed"].as_bool() == Some(true);
                    let count = |keep: &dyn Fn(&serde_json::Value) -> bool| later.clone().filter(|r| keep(r)).count();
                    json!({
                        "at_previous_end": count(&|r| at_end(r) == Some(true)),
                        "at_previous_end_placed_at_dock": count(&|r| at_end(r) == Some(true) && at_dock(r)),
                        "carried": count(&|r| at_end(r) == Some(false)),
                        "carried_placed_at_dock": count(&|r| at_end(r) == Some(false) && at_dock(r)),
                    })
                }),
                "wall_time_s": self.started.elapsed().as_secs_f64(),
                "data_duration_s": data_duration_s,
                "peak_rss_mb": process_stats::peak_rss_mb(),
            },
            "sessions": rows,
            "session_details": details,
        }))
    }

    fn write_report(&self, complete: bool, data_duration_s: Option<f64>) -> anyhow::Result<()> {
        let report = self.report(complete, data_duration_s)?;
        let path = self.args.out.join("report.json");
        let temporary = self.args.out.join("report.json.partial");
        std::fs::write(&temporary, serde_json::to_string_pretty(&report)? + "\n")
            .with_context(|| format!("cannot write {}", temporary.display()))?;
        std::fs::rename(&temporary, &path)
            .with_context(|| format!("cannot write {}", path.display()))
    }
}

/// The map against the world is judged over the area this many of the latest sessions observed (the
/// ground a robot cleans today, not corners nobody has seen for weeks).
const MAP_WORLD_SESSIONS: u32 = 5;

/// A share as `0.912`, or `-`.
fn share(value: Option<f64>) -> String {
    value.map_or("-".to_string(), |v| format!("{v:.3}"))
}

/// MCR: session 0's map against the map as its newest submaps describe the site now (both rendered
/// newest-wins, so that an unchanged site compares equal), and that newest map.
fn map_change(map: &LifelongMap, resolution: f64) -> Option<(MapChange, ProbabilityGrid)> {
    let before = render_submaps_newest(
        map.placed_submaps_by_id()
            .filter(|(id, _)| id.trajectory == 0)
            .map(|(_, g)| g),
        resolution,
    )?;
    let after = render_submaps_newest(map.placed_submaps_by_id().map(|(_, g)| g), resolution)?;
    Some((
        map_change_rate(&before, &after, MAP_CHANGE_TOLERANCE_M),
        after,
    ))
}

/// Runs the command.
pub fn run(args: &LifelongArgs) -> anyhow::Result<()> {
    let config = SessionsConfig::load(args.config.as_deref(), args.policy)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut options = SessionOptions::default();
    if let Some(t) = args.session_duration_s {
        options.max_duration_s = t;
    }
    if let Some(t) = args.mapping_duration_s {
        options.mapping_max_duration_s = t;
    }
    options.dock_starts = args.dock_starts;
    options.validate()?;
    let start = Instant::now();
    let store = Store::generate(args.world.options(), args.seed)?;
    let identity = RunIdentity {
        world: args.world.name().to_string(),
        seed: args.seed,
        policy: config.lifelong.policy.name().to_string(),
        session_duration_s: args.session_duration_s,
        mapping_duration_s: args.mapping_duration_s,
        dock_starts: args.dock_starts,
        config_fingerprint: crc32fast::hash(format!("{config:?}").as_bytes()),
    };
    let resume = if args.resume {
        let point = lifelong_resume::read(
            &args.out,
            &identity,
            config.lifelong.clone(),
            args.resume_under_new_config,
        )?;
        if point.next_session > args.sessions {
            anyhow::bail!(
                "the run in {} has already ended session {}: nothing to resume up to --sessions {}",
                args.out.display(),
                point.next_session - 1,
                args.sessions
            );
        }
        eprintln!(
            "resuming {} at session {}",
            args.out.display(),
            point.next_session
        );
        if point.config_fingerprint != identity.config_fingerprint {
            eprintln!(
                "under another configuration from session {} on (fingerprint {:#010x}, the run's was {:#010x})",
                point.next_session, identity.config_fingerprint, point.config_fingerprint
            );
        }
        Some(point)
    } else {
        None
    };
    let first_session = resume.as_ref().map_or(0, |r| r.next_session);

    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} {msg} [{bar:30}] {pos}/{len} scans ({per_sec})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    // Indexed by session: a resumed run's earlier sessions are not simulated again.
    let truths: Mutex<Vec<Vec<(Timestamp, Rigid2)>>> =
        Mutex::new(vec![Vec::new(); first_session as usize]);
    let failure: RefCell<Option<anyhow::Error>> = RefCell::new(None);
    let starts_at_previous_end: Mutex<Vec<bool>> = Mutex::new(vec![false; first_session as usize]);
    let inputs = (first_session..=args.sessions).map_while(|k| {
        bar.set_message(format!("simulating session {k}/{}", args.sessions));
        match store.session(k, &options) {
            Ok(session) => {
                bar.inc_length(session.ground_truth.len() as u64);
                let message = format!(
                    "session {k}/{} ({:.0} s, {:.0} m)",
                    args.sessions, session.duration_s, session.distance_m
                );
                if bar.is_hidden() {
                    // No terminal (CI, a log file): one line per session instead of a bar.
                    eprintln!("[{:>6.0} s] {message}", start.elapsed().as_secs_f64());
                }
                bar.set_message(message);
                if let Ok(mut truths) = truths.lock() {
                    truths.push(session.ground_truth);
                }
                if options.dock_starts
                    && let Ok(mut starts) = starts_at_previous_end.lock()
                {
                    starts.push(session.starts_at_previous_end);
                }
                Some(SessionInput {
                    events: session.events,
                    base_from_laser: session.base_from_laser,
                    from_dock: options.dock_starts,
                })
            }
            Err(e) => {
                *failure.borrow_mut() = Some(e.into());
                None
            }
        }
    });
    let resolution = config.local.submaps.resolution;
    let mut reporter = Reporter {
        args,
        config: &config,
        options: &options,
        store: &store,
        scoring: config.scoring,
        truths: &truths,
        starts_at_previous_end: &starts_at_previous_end,
        world_from_map: resume.as_ref().map(|r| r.world_from_map),
        truth_day_zero: store.occupancy(0, resolution).surface_grid(),
        rows: Vec::new(),
        details: Vec::new(),
        last_change: None,
        started: start,
        identity,
        earlier_rows: Vec::new(),
        earlier_details: Vec::new(),
        configuration_changed_at: Vec::new(),
    };
    if let Some(point) = &resume {
        let earlier = earlier_report(&args.out, first_session)?;
        (reporter.earlier_rows, reporter.earlier_details) = (earlier.rows, earlier.details);
        reporter.configuration_changed_at = earlier.configuration_changed_at;
        if point.config_fingerprint != reporter.identity.config_fingerprint {
            reporter.configuration_changed_at.push(first_session);
        }
    }
    let mut report_failure: Option<anyhow::Error> = None;
    let mut progress = |done: usize| bar.set_position(done as u64);
    let mut on_end = |end: &SessionEnd<'_>| {
        if let Err(e) = reporter.session_ended(end) {
            report_failure.get_or_insert(e);
        }
    };
    let run = match resume {
        Some(point) => resume_session_inputs(
            RunResume {
                map: point.map,
                first_session,
                dock: point.dock,
            },
            inputs,
            &config,
            &mut progress,
            &mut on_end,
        )?,
        None => run_session_inputs(inputs, &config, &[], &mut progress, &mut on_end)?,
    };
    bar.finish_and_clear();
    if let Some(e) = failure.into_inner() {
        return Err(e.context("the simulator failed"));
    }
    if let Some(e) = report_failure {
        return Err(e.context("scoring a session failed"));
    }
    reporter.write_report(true, Some(run.data_duration_s))?;
    if let Some((change, after)) = &reporter.last_change {
        let (w, h, pixels) = map_image::map_change_to_rgb(change);
        map_image::write_rgb_png(&args.out.join("map_change.png"), w, h, &pixels)?;
        let (w, h, pixels) = map_image::grid_to_gray(after);
        map_image::write_gray_png(&args.out.join("map.png"), w, h, &pixels)?;
    }
    write_charts(&args.out, &reporter.all_rows()?)?;
    let truths = truths
        .lock()
        .map_err(|_| anyhow::anyhow!("the truth lock is poisoned"))?
        .clone();
    write_trajectories(
        &args.out.join("trajectories.csv"),
        &run.records,
        &truths,
        &reporter.world_from_map.unwrap_or_else(Rigid2::identity),
    )?;
    let report = reporter.report(true, Some(run.data_duration_s))?;
    println!(
        "{}",
        json!({"policy": config.lifelong.policy.name(), "summary": report["summary"]})
    );
    Ok(())
}

/// The rows and details of sessions before `first_session` in the report of the run in `out`.
/// What a resumed run carries on from its earlier report.
struct EarlierReport {
    rows: Vec<serde_json::Value>,
    details: Vec<serde_json::Value>,
    /// The sessions from which an earlier resume went on under another configuration, before the resume
    /// point.
    configuration_changed_at: Vec<u32>,
}

fn earlier_report(out: &Path, first_session: u32) -> anyhow::Result<EarlierReport> {
    let path = out.join("report.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    let report: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{} is not JSON", path.display()))?;
    let earlier = |key: &str| -> anyhow::Result<Vec<serde_json::Value>> {
        let rows = report[key]
            .as_array()
            .with_context(|| format!("{} has no `{key}`", path.display()))?;
        let rows: Vec<serde_json::Value> = rows
            .iter()
            .filter(|r| {
                r["session"]
                    .as_u64()
                    .is_some_and(|k| k < u64::from(first_session))
            })
            .cloned()
            .collect();
        if rows.len() != first_session as usize {
            anyhow::bail!(
                "{} holds {} of the {first_session} sessions before the resume point in `{key}`",
                path.display(),
                rows.len()
            );
        }
        Ok(rows)
    };
    let configuration_changed_at = report["configuration_changed_at_sessions"]
        .as_array()
        .map(|sessions| {
            sessions
                .iter()
                .filter_map(|k| k.as_u64().and_then(|k| u32::try_from(k).ok()))
                .filter(|&k| k < first_session)
                .collect()
        })
        .unwrap_or_default();
    Ok(EarlierReport {
        rows: earlier("sessions")?,
        details: earlier("session_details")?,
        configuration_changed_at,
    })
}

/// Writes every scan's pose smoothed at its session's end (in the truth's frame, through
/// `world_from_map`) beside its truth and the error of the robot's estimate at the time of the scan:
/// `session,time_s,x,y,theta,true_x,true_y,true_theta,error_m,online_error_m` (m, rad; `online_error_m`
/// empty while the session was not placed), for plotting where a session lost its way.
fn write_trajectories(
    path: &Path,
    records: &[SessionRecord],
    truths: &[Vec<(Timestamp, Rigid2)>],
    world_from_map: &Rigid2,
) -> anyhow::Result<()> {
    use std::fmt::Write as _;
    let mut csv =
        String::from("session,time_s,x,y,theta,true_x,true_y,true_theta,error_m,online_error_m\n");
    for record in records {
        let Some(truth) = truths.get(record.session as usize) else {
            continue;
        };
        let truth: BTreeMap<Timestamp, Rigid2> = truth.iter().copied().collect();
        let online: BTreeMap<Timestamp, Rigid2> = record.online.iter().copied().collect();
        for (time, map_from_base) in &record.smoothed {
            let Some(world) = truth.get(time) else {
                continue;
            };
            let e = world_from_map * map_from_base;
            let (error, _) = pose_error(world_from_map, map_from_base, world);
            let online_error = online.get(time).map_or(String::new(), |p| {
                format!("{:.4}", pose_error(world_from_map, p, world).0)
            });
            let _ = writeln!(
                csv,
                "{},{:.3},{:.4},{:.4},{:.5},{:.4},{:.4},{:.5},{error:.4},{online_error}",
                record.session,
                time.as_secs_f64(),
                e.translation.x,
                e.translation.y,
                e.theta(),
                world.translation.x,
                world.translation.y,
                world.theta(),
            );
        }
    }
    std::fs::write(path, csv).with_context(|| format!("cannot write {}", path.display()))
}

/// The charts of every session's row (`report.json`'s `sessions`).
fn write_charts(out: &Path, rows: &[serde_json::Value]) -> anyhow::Result<()> {
    let series = |name: &str, color: [u8; 3], field: &str, scale: f64| Series {
        name: name.to_string(),
        color,
        points: rows
            .iter()
            .filter_map(|r| Some((r["session"].as_f64()?, scale * r[field].as_f64()?)))
            .collect(),
    };
    let graph = LineChart {
        title: "graph size after each session".into(),
        x_label: "session".into(),
        y_label: "count".into(),
        series: vec![
            series("nodes", [30, 90, 200], "nodes", 1.0),
            series("submaps x10", [0, 150, 0], "submaps", 10.0),
            series("constraints", [200, 40, 40], "constraints", 1.0),
        ],
        y_min: Some(0.0),
    };
    let (w, h, pixels) = graph.render(720, 420);
    map_image::write_rgb_png(&out.join("graph_size.png"), w, h, &pixels)?;
    let ams = LineChart {
        title: "matching score and localization per session".into(),
        x_label: "session".into(),
        y_label: "score / rate".into(),
        series: vec![
            series("AMS", [30, 90, 200], "ams", 1.0),
            series("MRCL", [0, 150, 0], "mrcl", 1.0),
            series("MCR", [200, 40, 40], "mcr", 1.0),
            series("world change", [150, 150, 150], "world_change_rate", 1.0),
        ],
        y_min: Some(0.0),
    };
    let (w, h, pixels) = ams.render(720, 420);
    map_image::write_rgb_png(&out.join("ams.png"), w, h, &pixels)?;
    Ok(())
}
