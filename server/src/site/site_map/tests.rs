use mapping::geometry::rigid2;

use super::*;
use crate::testing::{grid, match_to_submap, node};

fn batch(session: &str, seq: u64, items: Vec<UploadItem>) -> UploadBatch {
    UploadBatch {
        site: "s".into(),
        robot_id: "r".into(),
        session_uuid: session.into(),
        seq,
        items,
    }
}

fn open(map: &mut SiteMap, session: &str) -> SessionOpened {
    let opened = map.check_open("r", session).unwrap();
    map.open_session("r", session, opened.trajectory, map.version() + 1)
        .unwrap();
    opened
}

/// Options under which a robot's prior is committed at once (no probation): for the tests of what
/// follows a placement.
fn committed_at_once() -> LifelongOptions {
    let mut options = LifelongOptions::default();
    options.session_start.probation_matches = 0;
    options
}

fn apply(map: &mut SiteMap, b: &UploadBatch) {
    assert_eq!(map.check_upload(b).unwrap(), UploadCheck::Apply);
    map.apply_upload(b, map.version() + 1).unwrap();
}

#[test]
fn sessions_get_trajectories_in_order_and_reopen_idempotently() {
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    assert_eq!(open(&mut map, "a").trajectory, 0);
    assert_eq!(open(&mut map, "b").trajectory, 1);
    assert_eq!(map.version(), 2);
    let again = map.check_open("r", "a").unwrap();
    assert_eq!((again.trajectory, again.created), (0, false));
    assert!(matches!(
        map.check_open("other", "a"),
        Err(SiteError::WrongRobot { .. })
    ));
}

#[test]
fn uploads_must_come_in_sequence_and_fit_the_session() {
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    assert!(matches!(
        map.check_upload(&batch("a", 1, vec![node(0, &[0])])),
        Err(SiteError::UnknownSession(_))
    ));
    open(&mut map, "a");
    assert!(matches!(
        map.check_upload(&batch("a", 2, vec![node(0, &[0])])),
        Err(SiteError::SequenceGap {
            expected: 1,
            got: 2,
            ..
        })
    ));
    apply(&mut map, &batch("a", 1, vec![node(0, &[0])]));
    assert_eq!(
        map.check_upload(&batch("a", 1, vec![node(0, &[0])]))
            .unwrap(),
        UploadCheck::Duplicate { last_seq: 1 }
    );
    let orphan = batch(
        "a",
        2,
        vec![
            node(1, &[0]),
            UploadItem::SubmapFinished {
                index: 3,
                grid: grid(),
            },
        ],
    );
    assert!(matches!(
        map.check_upload(&orphan),
        Err(SiteError::InvalidBatch(_))
    ));
    let late_prior = batch(
        "a",
        2,
        vec![UploadItem::SessionStartPrior {
            global_from_local: Rigid2::identity(),
            glm_on_robot: false,
            at_dock: false,
            fitted: None,
        }],
    );
    assert!(matches!(
        map.check_upload(&late_prior),
        Err(SiteError::InvalidBatch(_))
    ));
    apply(
        &mut map,
        &batch("a", 2, vec![node(1, &[0]), UploadItem::SessionEnd]),
    );
    assert!(map.is_closed("a"));
    assert!(matches!(
        map.check_upload(&batch("a", 3, vec![node(2, &[0])])),
        Err(SiteError::SessionClosed(_))
    ));
}

#[test]
fn deltas_carry_new_submaps_and_moved_poses_only() {
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    open(&mut map, "a");
    apply(
        &mut map,
        &batch("a", 1, vec![node(0, &[0]), node(1, &[0, 1])]),
    );
    let v_before = map.version();
    assert!(map.delta_since(0).unwrap().submaps_added.is_empty());
    apply(
        &mut map,
        &batch(
            "a",
            2,
            vec![
                node(2, &[0, 1]),
                UploadItem::SubmapFinished {
                    index: 0,
                    grid: grid(),
                },
            ],
        ),
    );
    let v_finished = map.version();
    let delta = map.delta_since(v_before).unwrap();
    assert_eq!(delta.to_version, v_finished);
    assert_eq!(delta.submaps_added.len(), 1);
    assert_eq!(delta.submaps_added[0].revision, v_finished);
    assert_eq!(*delta.submaps_added[0].grid, grid());
    assert!(
        map.delta_since(v_finished)
            .unwrap()
            .submaps_added
            .is_empty()
    );
    assert!(map.delta_since(v_finished + 1).is_err());
    let id = SubmapId {
        trajectory: 0,
        index: 0,
    };
    assert_eq!(map.submap(id, 0).unwrap().revision, v_finished);
    assert!(map.submap(id, v_finished).is_ok());
    assert!(matches!(
        map.submap(id, v_before),
        Err(SiteError::NotFound(_))
    ));
    assert_eq!(map.counts().finished_submaps, 1);
    assert_eq!(map.counts().nodes, 3);
    assert_eq!(map.grids_for_render().len(), 1);
}

#[test]
fn a_start_prior_places_the_session() {
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    open(&mut map, "a");
    apply(&mut map, &batch("a", 1, vec![node(0, &[0])]));
    open(&mut map, "b");
    let prior = rigid2(10.0, -2.0, 0.5);
    apply(
        &mut map,
        &batch(
            "b",
            1,
            vec![
                UploadItem::SessionStartPrior {
                    global_from_local: prior,
                    glm_on_robot: false,
                    at_dock: false,
                    fitted: None,
                },
                node(3, &[0]),
            ],
        ),
    );
    let poses = map.node_poses();
    let b0 = poses[&NodeId {
        trajectory: 1,
        index: 0,
    }];
    let expected = prior * rigid2(0.3, 0.0, 0.0);
    assert!(
        (b0.translation.vector - expected.translation.vector).norm() < 1e-9,
        "{b0:?}"
    );
}

#[test]
fn a_prior_placed_sessions_grids_are_drawn_at_the_prior() {
    // A session whose local frame sits at `prior` in the site frame: its submap grid (drawn in the
    // session's own LLO frame) must be placed by `prior`, in renders and in the deltas agents cache.
    let mut map = SiteMap::new("s", committed_at_once()).unwrap();
    open(&mut map, "a");
    apply(&mut map, &batch("a", 1, vec![node(0, &[0])]));
    open(&mut map, "b");
    let prior = rigid2(10.0, -2.0, 0.5);
    apply(
        &mut map,
        &batch(
            "b",
            1,
            vec![
                UploadItem::SessionStartPrior {
                    global_from_local: prior,
                    glm_on_robot: false,
                    at_dock: false,
                    fitted: None,
                },
                node(3, &[0]),
                UploadItem::SubmapFinished {
                    index: 0,
                    grid: grid(),
                },
            ],
        ),
    );
    let b_submap = SubmapId {
        trajectory: 1,
        index: 0,
    };
    let renders: Vec<_> = map.grids_for_render();
    assert_eq!(renders.len(), 1, "only b's submap is finished");
    let (global_from_grid, _) = &renders[0];
    let expected = prior;
    assert!(
        (global_from_grid.translation.vector - expected.translation.vector).norm() < 1e-6
            && (global_from_grid.rotation.angle() - expected.rotation.angle()).abs() < 1e-9,
        "{global_from_grid:?}"
    );
    let snapshot = map.submap(b_submap, 0).unwrap_or_else(|_| {
        map.delta_since(0)
            .unwrap()
            .submaps_added
            .into_iter()
            .find(|s| s.id == b_submap)
            .unwrap()
    });
    let cached_global_from_grid = snapshot.global_pose * snapshot.local_pose.inverse();
    assert!(
        (cached_global_from_grid.translation.vector - expected.translation.vector).norm() < 1e-6,
        "{cached_global_from_grid:?}"
    );
}

/// A session's items: one node per submap, each submap finished right after its node, all at the same
/// places in every session (so a later session covers an earlier one cell for cell).
fn covering_session(submaps: u32, prior: Option<Rigid2>, end: bool) -> Vec<UploadItem> {
    let mut items: Vec<UploadItem> = prior
        .map(|global_from_local| UploadItem::SessionStartPrior {
            global_from_local,
            glm_on_robot: false,
            at_dock: false,
            fitted: None,
        })
        .into_iter()
        .collect();
    for s in 0..submaps {
        items.push(node(s, &[s]));
        items.push(UploadItem::SubmapFinished {
            index: s,
            grid: grid(),
        });
    }
    if end {
        items.push(UploadItem::SessionEnd);
    }
    items
}

fn ids(trajectory: u32, submaps: u32) -> Vec<SubmapId> {
    (0..submaps)
        .map(|index| SubmapId { trajectory, index })
        .collect()
}

#[test]
fn a_covering_session_trims_stale_submaps_but_never_session_zero_and_deltas_say_so() {
    let mut map = SiteMap::new("s", committed_at_once()).unwrap();
    for session in ["a", "b"] {
        open(&mut map, session);
        let prior = (session != "a").then(Rigid2::identity);
        apply(
            &mut map,
            &batch(session, 1, covering_session(6, prior, true)),
        );
    }
    // b covers a, but a is session 0.
    assert_eq!(map.counts().trimmed_submaps, 0);
    assert_eq!(map.counts().finished_submaps, 12);
    let before_c = map.version();
    open(&mut map, "c");
    apply(
        &mut map,
        &batch("c", 1, covering_session(6, Some(Rigid2::identity()), true)),
    );
    let counts = map.counts();
    assert_eq!(counts.trimmed_submaps, 6, "{counts:?}");
    assert_eq!(counts.finished_submaps, 12);
    let delta = map.delta_since(before_c).unwrap();
    assert_eq!(delta.trimmed, ids(1, 6), "b's submaps go");
    let whole: Vec<SubmapId> = map
        .delta_since(0)
        .unwrap()
        .submaps_added
        .iter()
        .map(|s| s.id)
        .collect();
    assert_eq!(whole, [ids(0, 6), ids(2, 6)].concat());
    assert!(map.submap(ids(1, 1)[0], 0).is_err());
    assert_eq!(map.grids_for_render().len(), 12);
    // Chow–Liu replaced b's nodes: none of them is left in the graph.
    assert!(map.node_poses().keys().all(|n| n.trajectory != 1));
}

#[test]
fn a_running_session_is_never_trimmed() {
    let mut map = SiteMap::new("s", committed_at_once()).unwrap();
    open(&mut map, "a");
    apply(&mut map, &batch("a", 1, covering_session(6, None, true)));
    open(&mut map, "b");
    apply(
        &mut map,
        &batch("b", 1, covering_session(6, Some(Rigid2::identity()), false)),
    );
    open(&mut map, "c");
    apply(
        &mut map,
        &batch("c", 1, covering_session(6, Some(Rigid2::identity()), true)),
    );
    assert_eq!(map.counts().trimmed_submaps, 0, "b is still mapping");
    apply(&mut map, &batch("b", 2, vec![UploadItem::SessionEnd]));
    open(&mut map, "d");
    apply(
        &mut map,
        &batch("d", 1, covering_session(6, Some(Rigid2::identity()), true)),
    );
    assert_eq!(map.counts().trimmed_submaps, 12, "b and c, once finished");
}

#[test]
fn an_unplaced_session_is_not_published_and_is_dropped_when_it_ends() {
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    open(&mut map, "a");
    apply(&mut map, &batch("a", 1, covering_session(6, None, true)));
    open(&mut map, "b");
    // No prior: the robot could not place it, and b ends before the server's session start has held
    // back enough nodes to search, so nothing places b.
    apply(&mut map, &batch("b", 1, covering_session(6, None, false)));
    assert_eq!(map.counts().finished_submaps, 6, "b's submaps float");
    assert!(
        map.delta_since(0)
            .unwrap()
            .submaps_added
            .iter()
            .all(|s| s.id.trajectory == 0)
    );
    let before_end = map.version();
    apply(&mut map, &batch("b", 2, vec![UploadItem::SessionEnd]));
    let counts = map.counts();
    assert_eq!((counts.dropped_sessions, counts.trimmed_submaps), (1, 0));
    assert!(map.delta_since(before_end).unwrap().trimmed.is_empty());
    assert!(map.node_poses().keys().all(|n| n.trajectory == 0));
    // The robot's next dock: the base session ended at its last node; the dropped one nowhere.
    let last = map.node_poses()[&NodeId {
        trajectory: 0,
        index: 5,
    }];
    assert_eq!(map.session_end_pose("a"), Some(last));
    assert_eq!(map.session_end_pose("b"), None);
    assert_eq!(map.session_end_pose("unknown"), None);
}

#[test]
fn a_robot_matched_session_gets_the_robots_matches_and_no_cross_session_search() {
    // Returns (loop closures added for b, searches the server queued for b).
    let run = |glm_on_robot: bool, with_match: bool| {
        let mut options = LifelongOptions::default();
        // Every candidate pair searched: the server's own GLM would search b's node for sure.
        options.global.constraint_builder.sampling_ratio = 1.0;
        let mut map = SiteMap::new("s", options).unwrap();
        open(&mut map, "a");
        apply(&mut map, &batch("a", 1, covering_session(3, None, true)));
        let (closures, searches) = (map.counts().loop_closures, map.searches_queued());
        open(&mut map, "b");
        let mut items = vec![
            UploadItem::SessionStartPrior {
                global_from_local: Rigid2::identity(),
                glm_on_robot,
                at_dock: false,
                fitted: None,
            },
            node(0, &[0]),
        ];
        if with_match {
            items.push(UploadItem::GlobalMatch {
                submap: SubmapId {
                    trajectory: 0,
                    index: 0,
                },
                submap_from_node: rigid2(0.0, 0.0, 0.0),
                score: 0.8,
            });
        }
        apply(&mut map, &batch("b", 1, items));
        (
            map.counts().loop_closures - closures,
            map.searches_queued() - searches,
        )
    };
    assert_eq!(run(true, true), (1, 0), "the robot's match, no search");
    assert_eq!(run(true, false), (0, 0));
    let (_, searched) = run(false, false);
    assert!(searched > 0, "without GLM on the robot the server searches");
}

#[test]
fn a_prior_on_probation_is_not_published_trims_nothing_and_is_dropped_if_never_confirmed() {
    // Reference: Zhao et al. 2021 §III (a session updates the map only once localized); issue 14 §3.
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    open(&mut map, "a");
    apply(&mut map, &batch("a", 1, covering_session(6, None, true)));
    for session in ["b", "c"] {
        open(&mut map, session);
        // The robot's prior, and no match along the route agrees with it.
        apply(
            &mut map,
            &batch(
                session,
                1,
                covering_session(6, Some(Rigid2::identity()), false),
            ),
        );
        assert_eq!(
            map.counts().finished_submaps,
            6,
            "{session} is on probation"
        );
        apply(&mut map, &batch(session, 2, vec![UploadItem::SessionEnd]));
    }
    // c covers b cell for cell, but neither was confirmed: nothing trimmed, both dropped.
    let counts = map.counts();
    assert_eq!(
        (counts.dropped_sessions, counts.trimmed_submaps),
        (2, 0),
        "{counts:?}"
    );
    assert!(map.node_poses().keys().all(|n| n.trajectory == 0));
}

#[test]
fn a_robots_dock_placement_is_kept_at_the_end_only_on_its_word() {
    // Issue 33 item 4: the robot's dock placement, still on probation when the session ends, is
    // committed where the robot says it stands (`DockPlacementKept`); without that word it is dropped as
    // any placement on probation is.
    let run = |kept: bool| {
        let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
        open(&mut map, "a");
        apply(&mut map, &batch("a", 1, covering_session(6, None, true)));
        open(&mut map, "b");
        let mut items = covering_session(6, None, false);
        items.insert(
            0,
            UploadItem::SessionStartPrior {
                global_from_local: Rigid2::identity(),
                glm_on_robot: true,
                at_dock: true,
                fitted: None,
            },
        );
        apply(&mut map, &batch("b", 1, items));
        assert_eq!(map.counts().finished_submaps, 6, "b is on probation");
        let mut end = vec![UploadItem::SessionEnd];
        if kept {
            end.insert(0, UploadItem::DockPlacementKept);
        }
        apply(&mut map, &batch("b", 2, end));
        map.counts()
    };
    let kept = run(true);
    assert_eq!(
        (
            kept.dropped_sessions,
            kept.finished_submaps,
            kept.session_starts.committed
        ),
        (0, 12, 1),
        "{kept:?}"
    );
    let not_kept = run(false);
    assert_eq!(
        (not_kept.dropped_sessions, not_kept.finished_submaps),
        (1, 6),
        "{not_kept:?}"
    );
}

#[test]
fn only_a_dock_placement_can_be_kept() {
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    open(&mut map, "a");
    apply(&mut map, &batch("a", 1, covering_session(2, None, true)));
    open(&mut map, "b");
    let mut items = covering_session(2, Some(Rigid2::identity()), false);
    items.push(UploadItem::DockPlacementKept);
    match map.check_upload(&batch("b", 1, items)) {
        Err(SiteError::InvalidBatch(why)) => assert!(why.contains("DockPlacementKept"), "{why}"),
        other => panic!("a prior that is not the dock's cannot be kept: {other:?}"),
    }
}

#[test]
fn agreeing_robot_matches_commit_a_prior_and_publish_its_submaps() {
    let mut options = LifelongOptions::default();
    options.session_start.probation_matches = 2;
    options.session_start.probation_min_separation_m = 0.15;
    options.session_start.hold_back_nodes = 1;
    let mut map = SiteMap::new("s", options).unwrap();
    open(&mut map, "a");
    apply(&mut map, &batch("a", 1, covering_session(6, None, true)));
    open(&mut map, "b");
    // b drives a's route (node k at x = 0.1 k) and its robot matches node k to a's submap k where it is.
    let mut items = vec![UploadItem::SessionStartPrior {
        global_from_local: Rigid2::identity(),
        glm_on_robot: true,
        at_dock: false,
        fitted: None,
    }];
    for k in 0..6u32 {
        items.push(node(k, &[k]));
        items.push(UploadItem::SubmapFinished {
            index: k,
            grid: grid(),
        });
        if k % 2 == 0 {
            // Submap k of a sits at x = k (see `node`), node k at x = 0.1 k.
            items.push(match_to_submap(k));
        }
    }
    apply(&mut map, &batch("b", 1, items));
    assert_eq!(
        map.counts().finished_submaps,
        12,
        "committed: b's submaps are published"
    );
}

#[test]
fn history_and_session_views_follow_the_published_map() {
    use crate::site::PlacementState;
    let mut map = SiteMap::new("s", LifelongOptions::default()).unwrap();
    open(&mut map, "a");
    assert!(map.history().latest().is_none());
    assert_eq!(map.session_views()[0].state, PlacementState::Waiting);
    apply(
        &mut map,
        &batch(
            "a",
            1,
            vec![
                node(0, &[0]),
                node(1, &[0]),
                UploadItem::SubmapFinished {
                    index: 0,
                    grid: grid(),
                },
            ],
        ),
    );
    let first = map.history().latest().unwrap().clone();
    assert_eq!(first.version, map.version());
    assert_eq!(first.grids.len(), 1);
    assert_eq!(first.counts.finished_submaps, 1);
    open(&mut map, "b");
    assert_eq!(
        map.history().latest().unwrap().version,
        first.version,
        "an open changes no map"
    );
    assert_eq!(
        map.history().at(map.version()).unwrap().version,
        first.version
    );
    apply(&mut map, &batch("b", 1, vec![node(0, &[0])]));
    let views = map.session_views();
    assert_eq!(views[0].state, PlacementState::Base);
    assert_eq!(views[0].trajectory_poses.len(), 2);
    assert_eq!(
        views[0].latest_pose,
        views[0].trajectory_poses.last().copied()
    );
    assert_eq!((views[1].robot_id.as_str(), views[1].trajectory), ("r", 1));
    assert_eq!(
        views[1].state,
        PlacementState::Searching,
        "no prior: the server searches"
    );
    assert!(views[1].trajectory_poses.is_empty() && views[1].latest_pose.is_none());
    apply(&mut map, &batch("b", 2, vec![UploadItem::SessionEnd]));
    let views = map.session_views();
    assert_eq!(views[1].state, PlacementState::Dropped);
    assert!(views[1].closed);
}

#[test]
fn session_start_decisions_are_counted_and_replay_counts_them_alike() {
    let mut options = LifelongOptions::default();
    options.session_start.hold_back_nodes = 2;
    options.session_start.retry_every_n_nodes = 2;
    options.session_start.give_up_after_nodes = 8;
    // A prior nothing confirms is revoked 0.25 m along its route.
    options.session_start.probation_timeout_m = 0.25;
    let mut changes = vec![("a", covering_session(6, None, true))];
    // b: no prior: the server searches for it, retries, and gives up after 8 nodes.
    changes.push(("b", (0..10).map(|i| node(i, &[0])).collect()));
    // c: its robot's prior, revoked at its 4th node (0.3 m), before any search of the server is due.
    let mut c = vec![UploadItem::SessionStartPrior {
        global_from_local: Rigid2::identity(),
        glm_on_robot: false,
        at_dock: false,
        fitted: None,
    }];
    c.extend((0..5).map(|i| node(i, &[0])));
    changes.push(("c", c));
    let build = || {
        let mut map = SiteMap::new("s", options.clone()).unwrap();
        for (session, items) in &changes {
            open(&mut map, session);
            apply(&mut map, &batch(session, 1, items.clone()));
        }
        map
    };
    let map = build();
    let starts = map.counts().session_starts;
    let searches = starts.placed + starts.refused;
    assert_eq!((starts.priors, starts.revoked), (1, 1), "{starts:?}");
    assert!(
        searches >= 2,
        "b is searched and searched again: {starts:?}"
    );
    assert_eq!(
        starts.retries,
        searches - 1,
        "only b was searched: {starts:?}"
    );
    assert_eq!(
        (starts.placed, starts.committed, starts.gave_up),
        (0, 0, 1),
        "b fits nowhere on a map of parallel lines: {starts:?}"
    );
    assert_eq!(build().counts(), map.counts(), "replay counts the same");
}
