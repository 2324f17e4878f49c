//! The multi-session path on a small simulated store: session 0 maps it, later sessions (changed goods,
//! people about) start with no prior, relocalize and localize in session 0's frame.

use mapping::metrics::{ScoringOptions, align_to_truth, score_session};
use prost::Message as _;
use robot_agent::lifelong_run::{
    RunResume, SessionInput, SessionsConfig, resume_session_inputs, run_session_inputs,
};
use simulator::{AislesOptions, SessionOptions, Store};

/// The small store of these tests and its first `n` sessions of at most `duration_s` each.
fn small_store_sessions(n: u32, duration_s: f64) -> Vec<simulator::SimulatedSession> {
    let store_options = AislesOptions {
        width: 36.0,
        depth: 24.0,
        blocks: 1,
        pallet_slots: 8,
        display_slots: 6,
        doors: 2,
        pedestrians: 3,
        carts: 1,
        ..AislesOptions::default()
    };
    let store = Store::generate(&store_options, 5).expect("store");
    let options = SessionOptions {
        max_duration_s: duration_s,
        ..SessionOptions::default()
    };
    (0..n)
        .map(|k| store.session(k, &options).expect("session"))
        .collect()
}

/// The sessions as a run's inputs (the robot checking its dock first with `from_dock`).
fn inputs(
    sessions: &[simulator::SimulatedSession],
    from_dock: bool,
) -> impl Iterator<Item = SessionInput> + '_ {
    sessions.iter().map(move |s| SessionInput {
        events: s.events.clone(),
        base_from_laser: s.base_from_laser,
        from_dock,
    })
}

#[test]
fn a_run_resumed_from_its_checkpoint_does_what_the_uninterrupted_run_did() {
    let sessions = small_store_sessions(3, 30.0);
    let config = SessionsConfig::default();
    let whole = run_session_inputs(
        inputs(&sessions, true),
        &config,
        &[],
        &mut |_| {},
        &mut |_| {},
    )
    .expect("uninterrupted run");
    // Stopped after session 1: its map as a site checkpoint's bytes, and the robot's dock.
    let mut saved = None;
    run_session_inputs(
        inputs(&sessions[..2], true),
        &config,
        &[],
        &mut |_| {},
        &mut |end| {
            let checkpoint = proto::SiteCheckpoint::of(end.map, 0, 0);
            saved = Some((
                proto::pb::SiteCheckpoint::from(&checkpoint).encode_to_vec(),
                end.dock,
            ));
        },
    )
    .expect("first part");
    let (bytes, dock) = saved.expect("session 1 ended");
    let decoded = proto::pb::SiteCheckpoint::decode(bytes.as_slice()).expect("decodes");
    let map = proto::SiteCheckpoint::try_from(&decoded)
        .expect("reads")
        .restore(config.lifelong.clone())
        .expect("restores");
    let resumed = resume_session_inputs(
        RunResume {
            map,
            first_session: 2,
            dock,
        },
        inputs(&sessions[2..], true),
        &config,
        &mut |_| {},
        &mut |_| {},
    )
    .expect("resumed run");
    let (a, b) = (&whole.sessions[2], &resumed.sessions[0]);
    assert_eq!(b.session, 2);
    assert!(a.placed, "the session the test resumes at is placed: {a:?}");
    assert_eq!(a.counts, b.counts);
    assert_eq!(a.committed_at_node, b.committed_at_node);
    assert_eq!(a.closures, b.closures);
    assert_eq!(a.cross_session_closures, b.cross_session_closures);
    assert_eq!(whole.records[2].online, resumed.records[0].online);
    assert_eq!(whole.records[2].smoothed, resumed.records[0].smoothed);
    let poses = |map: &mapping::lifelong::LifelongMap| {
        map.node_poses()
            .map(|(id, _, pose)| (id, pose))
            .collect::<Vec<_>>()
    };
    assert_eq!(poses(&whole.map), poses(&resumed.map));
}

#[test]
fn later_sessions_relocalize_and_localize_in_the_session_zero_frame() {
    let sessions = small_store_sessions(3, 40.0);
    let mut ended = Vec::new();
    let run = run_session_inputs(
        inputs(&sessions, false),
        &SessionsConfig::default(),
        &[],
        &mut |_| {},
        &mut |end| {
            ended.push(end.summary.session);
        },
    )
    .expect("run");
    assert_eq!(run.sessions.len(), 3);
    assert_eq!(ended, [0, 1, 2], "every session reported as it ended");
    let world_from_map = align_to_truth(&run.records[0].smoothed, &sessions[0].ground_truth);
    for (k, session) in sessions.iter().enumerate().skip(1) {
        let summary = &run.sessions[k];
        let record = &run.records[k];
        let score = score_session(
            &record.track(&session.ground_truth),
            &world_from_map,
            &ScoringOptions::default(),
        );
        eprintln!(
            "session {k}: placement {:?} m / {:?}° after {:?} s, MRCL {:.3} (smoothed {:.3}), ATE {:.3} m (smoothed {:.3}), AMS {:?} over {} nodes, {} cross-session matches",
            score.placement_error_m,
            score.placement_error_deg,
            score.placed_after_s,
            score.mrcl,
            score.mrcl_smoothed,
            score.ate_rms_m,
            score.ate_rms_smoothed_m,
            score.ams,
            score.scored_scans,
            summary.cross_session_closures,
        );
        assert!(score.initialized, "session {k}: {score:?}");
        assert!(score.initialized_committed, "session {k}: {score:?}");
        assert!(!score.wrong_placement);
        assert!(score.mrcl > 0.9, "session {k}: MRCL {}", score.mrcl);
        assert!(
            score.mrcl_smoothed > 0.9,
            "session {k}: {}",
            score.mrcl_smoothed
        );
        assert_eq!(score.scored_scans, summary.nodes_added);
        assert!(
            score.ams.is_some_and(|a| a > 0.5),
            "session {k}: {:?}",
            score.ams
        );
        assert!(summary.cross_session_closures > 0);
    }
}
