//! A lifelong map restored from its state (`LifelongMap::to_state` → `LifelongMap::from_state`)
//! behaves bit for bit like the map it was taken from: fed the same next sessions, both give the same
//! events, node and submap poses, grids, counts and placement decisions (issue 34, item 2, for the
//! mapping core; the server's checkpoint record and its replay test build on this).
//!
//! The sessions are real (`simulator::testing::checkpoint_sessions`): a small simulated store, LLO on its
//! scans, GLM by the real branch-and-bound constraint builder (whose precomputation grids the restored
//! map rebuilds), Chow–Liu trimming at session ends; session 1 starts unplaced and is placed later,
//! session 2 goes through probation.

use mapping::lifelong::{LifelongMap, LifelongMapState};
use simulator::testing::checkpoint_sessions::{
    Log, Position, SESSIONS, SessionInput, feed, options, session_inputs, snapshot,
};

/// Takes the state at `checkpoint`, restores it, and feeds both maps the rest of the sessions.
fn restored_map_behaves_like_the_original(inputs: &[SessionInput], checkpoint: Position) {
    let start = Position {
        session: 0,
        nodes: 0,
        started: false,
    };
    let end = Position {
        session: SESSIONS,
        nodes: 0,
        started: false,
    };
    let mut original = LifelongMap::new(options()).expect("map");
    let mut before = Log::new();
    feed(&mut original, inputs, start, checkpoint, &mut before);

    let state: LifelongMapState = original.to_state();
    let mut restored = LifelongMap::from_state(options(), state.clone()).expect("restore");
    assert!(restored.to_state() == state, "the restored state differs");
    assert_eq!(snapshot(&restored), snapshot(&original));

    let (mut log_original, mut log_restored) = (Log::new(), Log::new());
    feed(&mut original, inputs, checkpoint, end, &mut log_original);
    feed(&mut restored, inputs, checkpoint, end, &mut log_restored);
    assert!(
        log_original.len() > 50,
        "too little happened after the checkpoint: {log_original:?}"
    );
    for (k, (a, b)) in log_original.iter().zip(&log_restored).enumerate() {
        assert_eq!(a, b, "output {k} after the checkpoint at {checkpoint:?}");
    }
    assert_eq!(log_original.len(), log_restored.len());
    assert_eq!(snapshot(&restored), snapshot(&original));

    // Not vacuous: what follows the checkpoint matched against restored submaps, trimmed and sparsified.
    let text = log_original.join("\n");
    assert!(
        text.contains("LoopClosureAdded"),
        "no GLM match after the checkpoint"
    );
    assert!(
        text.contains("SubmapTrimmed"),
        "nothing trimmed after the checkpoint"
    );
}

#[test]
fn a_map_restored_from_its_state_gives_the_same_outputs_as_the_original() {
    let inputs = session_inputs();
    assert_eq!(inputs.len(), SESSIONS as usize);
    for input in &inputs {
        assert!(input.nodes.len() >= 40, "{} nodes", input.nodes.len());
    }
    // At a session end (the checkpoint the server takes), and in the middle of a session on probation
    // (every N versions): queued searches, pending matches and the periodic-optimization count.
    for checkpoint in [
        Position {
            session: 2,
            nodes: 0,
            started: false,
        },
        Position {
            session: 2,
            nodes: 17,
            started: true,
        },
    ] {
        restored_map_behaves_like_the_original(&inputs, checkpoint);
    }
}

#[test]
fn a_state_that_contradicts_itself_is_refused() {
    let map = LifelongMap::new(options()).expect("map");
    let mut state = map.to_state();
    state.base = Some(3);
    assert!(LifelongMap::from_state(options(), state).is_err());

    let mut state = map.to_state();
    state
        .global
        .acceptances
        .push(mapping::global_slam::Acceptance::default());
    let error = LifelongMap::from_state(options(), state)
        .err()
        .expect("refused");
    assert!(error.to_string().contains("acceptances"), "{error}");

    assert!(LifelongMap::from_state(options(), map.to_state()).is_ok());
}
