//! The SLAM pipeline on the simulated store: LLO + GLM + PGR must track a short cleaning run.

use mapping::geometry::{Rigid2, rigid2};
use mapping::simulation::{SessionOptions, Store, StoreOptions};
use robot_agent::offline_slam::{SlamConfig, run_offline};
use robot_agent::source::{ReadReport, Recording};

/// RMS of position error after the best rigid alignment of `estimate` onto `truth` (matched by time).
fn ate_rms(
    estimate: &[(mapping::sensor::Timestamp, Rigid2)],
    truth: &[(mapping::sensor::Timestamp, Rigid2)],
) -> (f64, usize) {
    let truth: std::collections::BTreeMap<_, _> = truth.iter().copied().collect();
    let pairs: Vec<(Rigid2, Rigid2)> = estimate
        .iter()
        .filter_map(|(t, e)| truth.get(t).map(|g| (*e, *g)))
        .collect();
    let n = pairs.len() as f64;
    let mean_e = pairs
        .iter()
        .map(|p| p.0.translation.vector)
        .sum::<nalgebra::Vector2<f64>>()
        / n;
    let mean_g = pairs
        .iter()
        .map(|p| p.1.translation.vector)
        .sum::<nalgebra::Vector2<f64>>()
        / n;
    let (mut sin, mut cos) = (0.0, 0.0);
    for (e, g) in &pairs {
        let (a, b) = (e.translation.vector - mean_e, g.translation.vector - mean_g);
        cos += a.dot(&b);
        sin += a.x * b.y - a.y * b.x;
    }
    let theta = sin.atan2(cos);
    let t = mean_g - nalgebra::Rotation2::new(theta) * mean_e;
    let truth_from_estimate = rigid2(t.x, t.y, theta);
    let sum: f64 = pairs
        .iter()
        .map(|(e, g)| {
            ((truth_from_estimate * e).translation.vector - g.translation.vector).norm_squared()
        })
        .sum();
    ((sum / n).sqrt(), pairs.len())
}

#[test]
fn tracks_a_simulated_cleaning_run() {
    let store = Store::generate(&StoreOptions::default(), 3).expect("store");
    let options = SessionOptions {
        max_duration_s: 120.0,
        ..SessionOptions::default()
    };
    let session = store.session(1, &options).expect("session");
    let recording = Recording::from_unsorted(
        session.events.clone(),
        session.base_from_laser,
        ReadReport::default(),
    );
    let run = run_offline(&recording, &SlamConfig::default(), &mut |_| {}).expect("slam");
    let (ate, matched) = ate_rms(&run.scan_poses, &session.ground_truth);
    eprintln!(
        "ATE RMS {ate:.4} m over {matched} scans, {:.0} m driven",
        session.distance_m
    );
    assert!(matched > 1000);
    // Measured 0.019 m (seed 3, session 1, 112 m driven).
    assert!(ate < 0.05, "ATE RMS {ate} m");
}
