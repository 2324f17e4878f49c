//! Real sessions for checkpoint tests: [`session_inputs`] runs LLO over a small simulated store once,
//! [`feed`] hands any stretch of them to a map (session 1 starts unplaced and is placed after 5 nodes;
//! session 2 is on probation for its first 30), and [`snapshot`] prints everything the map exposes so
//! that equal text means bit-equal maps (`{:?}` prints each `f32`/`f64` so that it parses back to the
//! same bits, −0.0 included).

use mapping::geometry::Rigid2;
use mapping::global_slam::LoopClosure;
use mapping::grid::ProbabilityGrid;
use mapping::lifelong::{LifelongEvent, LifelongMap, LifelongOptions, TrimPolicy};
use mapping::local_slam::{LloDriver, LloNode, LocalTrajectoryBuilderOptions};
use mapping::sensor::collate_for_llo;

use crate::{SessionOptions, Store, StoreOptions};

/// One session's LLO output: its nodes, the submaps still active at its end, and its true start in the
/// map frame (session 0's start) for the prior.
pub struct SessionInput {
    /// Its nodes.
    pub nodes: Vec<LloNode>,
    /// LLO's submaps still active at the end, finished.
    pub active_submaps: Vec<(usize, ProbabilityGrid)>,
    /// Its true start in the map frame: the prior.
    pub map_from_local: Rigid2,
}

/// Sessions [`session_inputs`] makes.
pub const SESSIONS: u32 = 4;

/// Runs LLO over [`SESSIONS`] short sessions of a 48 × 30 m simulated store (seed 5).
pub fn session_inputs() -> Vec<SessionInput> {
    let store = Store::generate(
        StoreOptions {
            width: 48.0,
            depth: 30.0,
            banks: 1,
            ..StoreOptions::default()
        },
        5,
    )
    .expect("store");
    let sim = SessionOptions {
        mapping_max_duration_s: 45.0,
        max_duration_s: 25.0,
        lidar_rate_hz: 7.5,
        ..SessionOptions::default()
    };
    let llo_options = LocalTrajectoryBuilderOptions::default();
    let mut world_from_map = None;
    (0..SESSIONS)
        .map(|session| {
            let simulated = store.session(session, &sim).expect("session");
            let world_from_map = *world_from_map.get_or_insert(simulated.start_pose);
            let mut llo = LloDriver::new(llo_options.clone());
            let mut nodes = Vec::new();
            for event in collate_for_llo(&simulated.events) {
                let Some((_, insertion)) =
                    llo.add_event(event, &simulated.base_from_laser).into_node()
                else {
                    continue;
                };
                nodes.push(insertion.into_llo_node());
            }
            let active_submaps = llo
                .builder()
                .active_submaps()
                .submaps()
                .iter()
                .map(|(index, submap)| (*index, submap.grid.cropped_to_known()))
                .collect();
            SessionInput {
                nodes,
                active_submaps,
                map_from_local: world_from_map.inverse() * simulated.start_pose,
            }
        })
        .collect()
}

/// `clt`, trimming early on these short sessions so that later sessions trim and sparsify.
pub fn options() -> LifelongOptions {
    let mut options = LifelongOptions {
        policy: TrimPolicy::Clt,
        ..LifelongOptions::default()
    };
    options.trimmer.min_fresh_submaps_before_trimming = 1;
    options.trimmer.min_fresher_submaps = 1;
    options.trimmer.min_covered_fraction = 0.3;
    options
}

/// What the map said while being fed, as text: `{:?}` prints every `f32`/`f64` so that it parses back
/// to the same bits (−0.0 included), so equal logs mean bit-equal outputs.
pub type Log = Vec<String>;

fn log_events(log: &mut Log, what: &str, events: &[LifelongEvent]) {
    for event in events {
        log.push(format!("{what}: {event:?}"));
    }
}

/// Where the map is in the sessions: feeding resumes from here.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Position {
    /// The session being fed.
    pub session: u32,
    /// Nodes of `session` already fed.
    pub nodes: usize,
    /// Whether `session` was started.
    pub started: bool,
}

/// Feeds `inputs` from `from` up to `to` (exclusive: `to.nodes` nodes of `to.session` fed), the way
/// every shell does: start (session 1 unplaced, placed after 5 nodes; session 2 on probation, committed
/// after 30), nodes with GLM run on the calling thread, the active submaps, the end.
pub fn feed(
    map: &mut LifelongMap,
    inputs: &[SessionInput],
    from: Position,
    to: Position,
    log: &mut Log,
) {
    let mut at = from;
    while at.session < to.session || (at.session == to.session && at.nodes < to.nodes) {
        let session = at.session;
        let Some(input) = inputs.get(session as usize) else {
            return;
        };
        if !at.started {
            let prior = (session != 1).then_some(input.map_from_local);
            log_events(
                log,
                "start",
                &map.start_session(session, prior).expect("start"),
            );
            if session == 2 {
                map.begin_probation(session).expect("probation");
            }
            at.started = true;
        }
        if at.nodes < input.nodes.len() {
            let node = input.nodes[at.nodes].clone();
            let (id, events) = map.add_node(session, node).expect("node");
            log.push(format!("node {id:?}"));
            log_events(log, "add_node", &events);
            let events = map.run_pending_searches(Vec::<LoopClosure>::new());
            log_events(log, "glm", &events);
            at.nodes += 1;
            if session == 1 && at.nodes == 5 {
                let placed = map
                    .place_session(session, input.map_from_local, Some((0, 4)))
                    .expect("place");
                log.push(format!("placed {placed}"));
            }
            if session == 2 && at.nodes == 30 {
                log.push(format!("committed {}", map.commit_session(session)));
            }
            log.push(format!(
                "unplaced {} probation {} committed {}",
                map.is_unplaced(session),
                map.is_on_probation(session),
                map.is_committed(session)
            ));
            continue;
        }
        let events = map
            .finish_submaps(session, input.active_submaps.clone())
            .expect("finish submaps");
        log_events(log, "finish_submaps", &events);
        log_events(
            log,
            "glm",
            &map.run_pending_searches(Vec::<LoopClosure>::new()),
        );
        log_events(
            log,
            "finish_session",
            &map.finish_session(session).expect("finish"),
        );
        log.push(format!("counts {:?}", map.counts()));
        at = Position {
            session: session + 1,
            nodes: 0,
            started: false,
        };
    }
}

/// Everything the map exposes, bit for bit: its whole state as text, plus the public views.
pub fn snapshot(map: &LifelongMap) -> String {
    let poses: Vec<String> = map
        .node_poses()
        .map(|(id, time, pose)| format!("{id:?} {time:?} {pose:?}"))
        .collect();
    let submaps: Vec<String> = map
        .submaps()
        .map(|(id, pose, grid)| format!("{id:?} {pose:?} {:?}", grid.map(|g| g.values())))
        .collect();
    format!(
        "{:?}\n{poses:?}\n{submaps:?}\n{:?}\n{:?}",
        map.to_state(),
        map.counts(),
        map.global().loop_closure_checks()
    )
}
