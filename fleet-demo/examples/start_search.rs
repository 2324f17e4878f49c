//! Session-start benchmark on the simulated store: how fast and how right does a session that starts with
//! no prior place itself?
//!
//! The map is the store's day-0 layout as a map would see it (the simulator's truth surfaces, in the world
//! frame, so a placement's error is its distance from the truth with no alignment); each session 1..N of
//! that store (goods, pallets, displays and doors changed, people and carts about) runs LLO from its first
//! scan and feeds its nodes to the same [`SessionStart`] every shell obeys, until it places the session
//! (tentatively, as a robot would navigate with it) or the session's first `--max-duration-s` end. Probation
//! is not run (it needs GLM against the lifelong map): this measures the whole-map searches alone — the
//! wall time of each, the first placement's time and error, and wrong placements. One JSON line per
//! session, then a summary line.
//!
//!     cargo run --release --example start_search -- [--world store|aisles] [--seed S] [--sessions N]
//!         [--max-duration-s T] [--config LIFELONG.toml]
//!
//! `--config` takes the `lifelong` command's configuration file (its `[lifelong.relocalization]` and
//! `[lifelong.session_start]` sections).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use clap::Parser;
use mapping::geometry::Rigid2;
use mapping::lifelong::{SessionStart, SessionStartEvent, StartSearch};
use mapping::local_slam::LloDriver;
use mapping::metrics::{pose_error, truth_at};
use mapping::sensor::{SensorEvent, Timestamp};
use robot_agent::lifelong_run::SessionsConfig;
use robot_agent::process_stats::thread_cpu_ms;
use serde_json::json;
use simulator::World;
use simulator::{SessionOptions, Store};

#[derive(Parser)]
struct Args {
    /// Which world.
    #[arg(long, value_enum, default_value_t = World::Store)]
    world: World,
    /// Seed of the store layout, its change schedule and the routes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Sessions 1..=N are started.
    #[arg(long, default_value_t = 25)]
    sessions: u32,
    /// Each session's data used, seconds (the lifelong scores count a session initialized within 30 s).
    #[arg(long, default_value_t = 30.0)]
    max_duration_s: f64,
    /// A `lifelong` configuration file.
    #[arg(long)]
    config: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let config = SessionsConfig::load(args.config.as_deref(), None)?;
    let relocalization = &config.lifelong.relocalization;
    let store = Store::generate(args.world.options(), args.seed)?;
    let map = store.occupancy(0, relocalization.resolution).surface_grid();
    let mut prepare_ms: Vec<f64> = Vec::new();
    let options = SessionOptions {
        max_duration_s: args.max_duration_s,
        ..SessionOptions::default()
    };
    let scoring = config.scoring;
    let (mut placed, mut correct, mut wrong) = (0usize, 0usize, 0usize);
    let mut first_ms: Vec<f64> = Vec::new();
    let mut all_ms: Vec<f64> = Vec::new();
    let mut first_cpu_ms: Vec<f64> = Vec::new();
    let mut all_cpu_ms: Vec<f64> = Vec::new();
    for k in 1..=args.sessions {
        let session = store.session(k, &options)?;
        let mut start = SessionStart::new(config.lifelong.session_start.clone(), None)?;
        let prepared = Instant::now();
        start.set_search(StartSearch::new(&map, relocalization));
        prepare_ms.push(prepared.elapsed().as_secs_f64() * 1e3);
        let mut llo = LloDriver::new(config.local.clone());
        let first_time = session.events.first().map(SensorEvent::time);
        let mut node_times: Vec<Timestamp> = Vec::new();
        let mut node_poses: Vec<Rigid2> = Vec::new();
        let mut searches_ms: Vec<f64> = Vec::new();
        let mut searches_cpu_ms: Vec<f64> = Vec::new();
        let mut outcome = json!(null);
        let mut refusals = 0usize;
        'events: for event in mapping::sensor::collate_for_llo(&session.events) {
            let Some((result, insertion)) =
                llo.add_event(event, &session.base_from_laser).into_node()
            else {
                continue;
            };
            node_times.push(result.time);
            node_poses.push(result.local_pose);
            let searches = start.searches();
            let began = Instant::now();
            let cpu_before = thread_cpu_ms();
            let events = start.add_node(result.local_pose, insertion.node.filtered_points);
            if start.searches() > searches {
                searches_ms.push(began.elapsed().as_secs_f64() * 1e3);
                if let (Some(before), Some(after)) = (cpu_before, thread_cpu_ms()) {
                    searches_cpu_ms.push(after - before);
                }
            }
            for event in events {
                match event {
                    SessionStartEvent::Refused { .. } => refusals += 1,
                    SessionStartEvent::Placed(placement) => {
                        let node = placement.node;
                        let time = node_times[node];
                        let truth = truth_at(&session.ground_truth, time)
                            .context("no truth for the placed node")?;
                        let (error_m, error_deg) = pose_error(
                            &Rigid2::identity(),
                            &(placement.global_from_local * node_poses[node]),
                            &truth,
                        );
                        let is_correct = scoring.correct.accepts(error_m, error_deg);
                        let is_wrong = !scoring.wrong_placement.accepts(error_m, error_deg);
                        placed += 1;
                        correct += usize::from(is_correct);
                        wrong += usize::from(is_wrong);
                        outcome = json!({
                            "placed_after_s": first_time.map(|t| time.seconds_since(t)),
                            "node": node,
                            "error_m": error_m,
                            "error_deg": error_deg,
                            "correct": is_correct,
                            "wrong": is_wrong,
                            "score": placement.score,
                        });
                        break 'events;
                    }
                    _ => {}
                }
            }
        }
        first_ms.extend(searches_ms.first());
        all_ms.extend(&searches_ms);
        first_cpu_ms.extend(searches_cpu_ms.first());
        all_cpu_ms.extend(&searches_cpu_ms);
        println!(
            "{}",
            json!({
                "session": k,
                "placement": outcome,
                "refusals": refusals,
                "searches": searches_ms.len(),
                "first_search_ms": searches_ms.first(),
                "first_search_cpu_ms": searches_cpu_ms.first(),
                "search_cpu_ms_total": searches_cpu_ms.iter().sum::<f64>(),
                "search_ms_total": searches_ms.iter().sum::<f64>(),
            })
        );
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied()
    };
    let p95 = |v: &Vec<f64>| {
        v.get((v.len() * 95).div_ceil(100).saturating_sub(1))
            .copied()
    };
    let mut first_sorted = first_ms.clone();
    let first_median = median(&mut first_sorted);
    let mut all_sorted = all_ms.clone();
    let all_median = median(&mut all_sorted);
    println!(
        "{}",
        json!({
            "world": format!("{:?}", args.world).to_lowercase(),
            "seed": args.seed,
            "sessions": args.sessions,
            "max_duration_s": args.max_duration_s,
            "placed": placed,
            "correct": correct,
            "wrong": wrong,
            "prepare_ms_median": median(&mut prepare_ms),
            "first_search_ms_median": first_median,
            "first_search_ms_p95": p95(&first_sorted),
            "search_ms_median": all_median,
            "search_ms_p95": p95(&all_sorted),
            "first_search_cpu_ms_median": median(&mut first_cpu_ms),
            "search_cpu_ms_total": all_cpu_ms.iter().sum::<f64>(),
            "searches": all_ms.len(),
            "search_ms_total": all_ms.iter().sum::<f64>(),
        })
    );
    Ok(())
}
