//! The multi-session path on real data: MIT CSAIL cut into two time sessions, the second relocalized
//! with no prior against the first's map and localized by GLM across sessions, scored against the
//! benchmark's relations (Kümmerle et al. 2009) over the relations that span both sessions.

use mapping::io::relations::read_relations;
use mapping::metrics::relations_error;
use robot_agent::lifelong_run::{SessionsConfig, run_sessions};
use robot_agent::source::read_recording;
use tests::datasets_dir;

#[test]
fn csail_in_two_sessions_localizes_across_sessions() -> anyhow::Result<()> {
    let recording = read_recording(&datasets_dir().join("rosbag1/mit-csail.orig.bag"))?;
    let relations = read_relations(std::io::BufReader::new(std::fs::File::open(
        datasets_dir().join("relations/mit-csail.relations"),
    )?))?;
    let run = run_sessions(&recording, 2, &SessionsConfig::default(), &[], &mut |_| {})?;
    let session_of = |t| run.boundaries.partition_point(|b| *b <= t);
    let cross: Vec<_> = relations
        .iter()
        .filter(|r| session_of(r.t1) != session_of(r.t2))
        .cloned()
        .collect();
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
    assert!(cross.rot_abs_mean_deg < 1.0, "{cross:?}");
    // Two sessions: the first is never trimmed and the last has nothing fresher, so nothing is trimmed.
    assert_eq!(run.map.counts().trimmed_total, 0);
    assert_eq!(
        run.map.counts().nodes,
        run.sessions.iter().map(|s| s.nodes_added).sum::<usize>()
    );
    Ok(())
}
