//! The multi-session path on real data: MIT CSAIL cut into two time sessions, the second relocalized
//! with no prior against the first's map and localized by GLM across sessions, scored against the
//! benchmark's relations (Kümmerle et al. 2009) over the relations that span both sessions.

use mapping::io::relations::read_relations;
use mapping::metrics::{Verdict, judge_placements, relation_error_stats, relations_error};
use robot_agent::lifelong_run::{SessionsConfig, run_sessions, session_boundaries};
use robot_agent::map_probes::{cross_session_probes, relation_errors_at_the_time};
use robot_agent::perturbation::Perturbation;
use robot_agent::source::read_recording;
use tests::datasets_dir;

#[test]
fn csail_in_two_sessions_localizes_across_sessions() -> anyhow::Result<()> {
    let recording = read_recording(&datasets_dir().join("rosbag1/mit-csail.orig.bag"))?;
    let relations = read_relations(std::io::BufReader::new(std::fs::File::open(
        datasets_dir().join("relations/mit-csail.relations"),
    )?))?;
    let config = SessionsConfig::default();
    let (cross, probes) = cross_session_probes(&relations, &session_boundaries(&recording, 2)?);
    let run = run_sessions(&recording, 2, false, &config, &probes, &mut |_| {})?;
    // The placement the robot acted on, judged by the relations against the map it was placed on.
    let online = &run.records[1].online;
    let at_the_time = relation_errors_at_the_time(&cross, &probes, &run.probe_poses, online);
    let verdicts = judge_placements(
        &run.records[1].start.placements,
        &at_the_time,
        config.scoring.wrong_placement,
    );
    eprintln!("placements {verdicts:?}");
    assert_eq!(verdicts.len(), 1, "{verdicts:?}");
    assert_eq!(verdicts[0].placed.verdict, Verdict::Right, "{verdicts:?}");
    assert_eq!(verdicts[0].held.verdict, Verdict::Right, "{verdicts:?}");
    // Measured (release, 2026-12-04): 101 relations; at the time 0.046 m mean, 0.19 m largest, with the
    // map's matches fused into the pose (`mapping::lifelong::LiveAnchor`; 0.047 m and 0.30 m re-anchored on
    // each best match, 0.096 m on the graph's pose alone).
    assert!(verdicts[0].held.relations > 80, "{verdicts:?}");
    let at_the_time = relation_error_stats(&at_the_time, cross.len() - at_the_time.len());
    assert!(at_the_time.trans_abs_mean_m < 0.075, "{at_the_time:?}");
    assert!(at_the_time.trans_abs_max_m < 0.27, "{at_the_time:?}");
    let all = relations_error(&run.scan_poses, &relations);
    let cross = relations_error(&run.scan_poses, &cross);
    eprintln!(
        "all {all:?}\ncross-session {cross:?}\nsessions {:?}",
        run.sessions
    );
    assert_eq!(all.count, 1172, "every relation must find its poses");
    assert_eq!(cross.count, 109);
    let second = &run.sessions[1];
    assert!(second.relocalized, "session 1 must relocalize: {second:?}");
    assert!(
        second.relocalization_offset_m.is_some_and(|d| d < 1.0),
        "{second:?}"
    );
    assert!(second.cross_session_closures > 30, "{second:?}");
    // Measured (release): all 0.0400 m / 0.428°, cross-session 0.084 m / 0.86°, 106 cross-session
    // closures, relocalization offset 0.59 m (session 1 starts in a corridor: the 10-node cloud is
    // ambiguous along it, and GLM then pulls the session into place; 0.16 m before the LLO's correlative
    // range cut and the coarse-to-fine relocalizer). The single-session run scores 0.0375 m / 0.411°.
    assert!(all.trans_abs_mean_m < 0.06, "{all:?}");
    assert!(all.rot_abs_mean_deg < 0.6, "{all:?}");
    assert!(cross.trans_abs_mean_m < 0.2, "{cross:?}");
    // Issue 33: the estimate at the time at most 2× the smoothed cross-session error (0.046 / 0.048 m).
    assert!(
        at_the_time.trans_abs_mean_m <= 2.0 * cross.trans_abs_mean_m,
        "{at_the_time:?} against {cross:?}"
    );
    assert!(cross.rot_abs_mean_deg < 1.0, "{cross:?}");
    // Two sessions: the first is never trimmed and the last has nothing fresher, so nothing is trimmed.
    assert_eq!(run.map.counts().trimmed_total, 0);
    assert_eq!(
        run.map.counts().nodes,
        run.sessions.iter().map(|s| s.nodes_added).sum::<usize>()
    );
    Ok(())
}

/// The same two sessions with the scanner's driver stalling (`scanburst`: scans stamped in bursts after
/// each stall, the odometry on time): `sessions` puts the backlogs back at the times the scans were taken,
/// as `offline` does, and scores at the stamps.
#[test]
fn csail_in_two_sessions_with_a_stalled_scanner_driver_does_not_tear() -> anyhow::Result<()> {
    let recording = read_recording(&datasets_dir().join("rosbag1/mit-csail.orig.bag"))?;
    let (perturbed, done) = Perturbation::parse("scanburst")?.apply(&recording, 1);
    let relations = done.relations_at_stamps(read_relations(std::io::BufReader::new(
        std::fs::File::open(datasets_dir().join("relations/mit-csail.relations"))?,
    ))?);
    let config = SessionsConfig::default();
    let (cross, probes) = cross_session_probes(&relations, &session_boundaries(&perturbed, 2)?);
    let run = run_sessions(&perturbed, 2, false, &config, &probes, &mut |_| {})?;
    assert!(
        run.scans_retimed > 50,
        "{} scans re-timed",
        run.scans_retimed
    );
    let at_the_time =
        relation_errors_at_the_time(&cross, &probes, &run.probe_poses, &run.records[1].online);
    let verdicts = judge_placements(
        &run.records[1].start.placements,
        &at_the_time,
        config.scoring.wrong_placement,
    );
    let all = relations_error(&run.scan_poses, &relations);
    eprintln!(
        "{} scans re-timed; placements {verdicts:?}\nall {all:?}",
        run.scans_retimed
    );
    assert!(
        verdicts.iter().all(|v| v.placed.verdict != Verdict::Wrong),
        "{verdicts:?}"
    );
    assert!(all.count * 10 > relations.len() * 9, "{all:?}");
    assert!(all.trans_abs_max_m < 1.0, "a relation tore: {all:?}");
    assert!(all.trans_abs_mean_m < 0.06, "{all:?}");
    Ok(())
}
