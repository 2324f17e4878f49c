//! The multi-session path on a small simulated store: session 0 maps it, later sessions (changed goods,
//! people about) start with no prior, relocalize and localize in session 0's frame.

use mapping::metrics::{ScoringOptions, align_to_truth, score_session};
use robot_agent::lifelong_run::{SessionInput, SessionsConfig, run_session_inputs};
use simulator::{AislesOptions, SessionOptions, Store};

#[test]
fn later_sessions_relocalize_and_localize_in_the_session_zero_frame() {
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
        max_duration_s: 40.0,
        ..SessionOptions::default()
    };
    let sessions: Vec<_> = (0..3)
        .map(|k| store.session(k, &options).expect("session"))
        .collect();
    let inputs = sessions.iter().map(|s| SessionInput {
        events: s.events.clone(),
        base_from_laser: s.base_from_laser,
        from_dock: false,
    });
    let mut ended = Vec::new();
    let run = run_session_inputs(
        inputs,
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
