//! The multi-session path on a small simulated store: session 0 maps it, later sessions (changed goods,
//! people about) start with no prior, relocalize and localize in session 0's frame.

use std::collections::BTreeMap;

use mapping::geometry::{Rigid2, Rigid2Ext as _, rigid2};
use mapping::metrics::{rigid_alignment, trajectory_accuracy};
use mapping::sensor::Timestamp;
use mapping::simulation::{SessionOptions, Store, StoreOptions};
use robot_agent::lifelong_run::{SessionInput, SessionsConfig, run_session_inputs};

fn align(estimate: &[(Timestamp, Rigid2)], truth: &[(Timestamp, Rigid2)]) -> Rigid2 {
    let truth: BTreeMap<_, _> = truth.iter().copied().collect();
    let pairs: Vec<_> = estimate
        .iter()
        .filter_map(|(t, e)| Some((e.translation.vector, truth.get(t)?.translation.vector)))
        .collect();
    rigid_alignment(&pairs)
}

#[test]
fn later_sessions_relocalize_and_localize_in_the_session_zero_frame() {
    let store_options = StoreOptions {
        width: 36.0,
        depth: 24.0,
        blocks: 1,
        pallet_slots: 8,
        display_slots: 6,
        doors: 2,
        pedestrians: 3,
        carts: 1,
        ..StoreOptions::default()
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
    });
    let run = run_session_inputs(inputs, &SessionsConfig::default(), &mut |_| {}).expect("run");
    assert_eq!(run.sessions.len(), 3);
    let world_from_map = align(&run.session_scan_poses[0], &sessions[0].ground_truth);
    for (k, session) in sessions.iter().enumerate().skip(1) {
        let summary = &run.sessions[k];
        let accuracy = trajectory_accuracy(
            &run.session_scan_poses[k],
            &session.ground_truth,
            &world_from_map,
        );
        let [x, y, theta] = summary.relocalized_first_pose.expect("relocalized");
        let time = summary.first_node_time.expect("first node");
        let truth = session
            .ground_truth
            .iter()
            .find(|(t, _)| *t == time)
            .expect("truth at the first node")
            .1;
        let found = world_from_map * rigid2(x, y, theta);
        let error = (found.translation.vector - truth.translation.vector).norm();
        eprintln!(
            "session {k}: relocalization error {error:.3} m, θ {:.2}°, MRCL {:.3}, ATE {:.3} m, {} cross-session matches (AMS {:?})",
            (found.theta() - truth.theta()).to_degrees(),
            accuracy.mrcl,
            accuracy.ate_rms_m,
            summary.cross_session_closures,
            summary.cross_session_ams,
        );
        assert!(error < 0.3, "session {k}: relocalized {error} m off");
        assert!(accuracy.mrcl > 0.9, "session {k}: MRCL {}", accuracy.mrcl);
        assert!(summary.cross_session_closures > 0);
    }
}
