//! Tests of [`GlobalSlam`]: bookkeeping, acceptance, placement, optimization and retraction, and the
//! shared fixtures (`straight_run`, `drive_on`, `wide_closure`) its submodules' tests build on.

use super::*;
use crate::geometry::rigid2;
use crate::global_slam::ConstraintBuilderOptions;
use crate::grid::MapLimits;
use crate::pose_graph::ConstraintKind;

/// One trajectory driving along x in 0.2 m steps, 0.1 s apart; submap 0 holds its first 11 nodes and is
/// finished at node 11.
pub(crate) fn straight_run(nodes: u32) -> GlobalSlam {
    let options = GlobalSlamOptions {
        optimize_every_n_nodes: 0,
        constraint_builder: ConstraintBuilderOptions {
            sampling_ratio: 0.0,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut global = GlobalSlam::new(options).expect("valid options");
    drive_on(&mut global, 0..nodes);
    global
}

/// Adds the nodes `indices` of [`straight_run`]'s trajectory.
pub(super) fn drive_on(global: &mut GlobalSlam, indices: std::ops::Range<u32>) {
    drive_on_recovering(global, indices, None);
}

/// [`drive_on`], LLO having placed a scan by a recovery search just before node `recovered_at`.
fn drive_on_recovering(
    global: &mut GlobalSlam,
    indices: std::ops::Range<u32>,
    recovered_at: Option<u32>,
) {
    for i in indices {
        let submaps = if i <= 10 {
            vec![(0, Rigid2::identity())]
        } else {
            vec![(1, rigid2(2.2, 0.0, 0.0))]
        };
        let finished = if i == 11 {
            vec![(
                0,
                ProbabilityGrid::new(MapLimits::new(
                    0.05,
                    nalgebra::Vector2::new(-1.0, -1.0),
                    40,
                    40,
                )),
            )]
        } else {
            Vec::new()
        };
        let node = LloNode {
            time: Timestamp(i64::from(i) * 100_000_000),
            local_pose: rigid2(0.2 * f64::from(i), 0.0, 0.0),
            points: vec![Point2::new(1.0, 0.0)],
            insertion_submaps: submaps,
            finished_submaps: finished,
            recovered: recovered_at == Some(i),
        };
        global.add_node(0, node).expect("node added");
    }
}

/// A match of `node` against submap 0, `error` away from where the node is.
pub(crate) fn wide_closure(node: u32, error: Rigid2) -> LoopClosure {
    LoopClosure {
        submap: SubmapId {
            trajectory: 0,
            index: 0,
        },
        node: NodeId {
            trajectory: 0,
            index: node,
        },
        submap_from_node: rigid2(0.2 * f64::from(node), 0.0, 0.0) * error,
        score: 0.7,
        runner_up_score: None,
        information: None,
    }
}

/// The translation information (x) of node `index`'s constraint to submap 1 of [`straight_run`].
pub(super) fn intra_information_x(global: &GlobalSlam, index: u32) -> f64 {
    let submap = VariableId::Submap(SubmapId {
        trajectory: 0,
        index: 1,
    });
    let node = VariableId::Node(NodeId {
        trajectory: 0,
        index,
    });
    global
        .graph()
        .constraints()
        .find(|(_, c)| {
            c.kind == ConstraintKind::NodeToSubmapIntra && c.from == submap && c.to == node
        })
        .map(|(_, c)| c.information[(0, 0)])
        .expect("the node's constraint to submap 1")
}

#[test]
fn a_node_far_along_its_submap_is_held_to_it_more_loosely_when_asked() {
    // By default every node is held to its submap alike.
    let global = straight_run(101);
    assert_eq!(
        intra_information_x(&global, 11).to_bits(),
        intra_information_x(&global, 100).to_bits()
    );
    // With growth: submap 1 starts at node 11; node 100 is 17.8 m of path further.
    let mut grown = GlobalSlam::new(GlobalSlamOptions {
        intra_submap_translation_sigma_per_m: 0.1,
        intra_submap_rotation_sigma_per_m: 0.01,
        optimize_every_n_nodes: 0,
        ..GlobalSlamOptions::default()
    })
    .expect("valid options");
    drive_on(&mut grown, 0..101);
    let sigma = |information: f64| information.sqrt().recip();
    let near = sigma(intra_information_x(&grown, 11));
    let far = sigma(intra_information_x(&grown, 100));
    assert!((near - 0.5).abs() < 1e-9, "{near}");
    let expected = 0.5f64.hypot(0.1 * 17.8);
    assert!((far - expected).abs() < 1e-6, "{far} vs {expected}");
}

#[test]
fn a_match_far_from_the_estimate_waits_for_another_that_agrees_with_it() {
    let mut global = straight_run(200);
    // Near the estimate: accepted at once.
    global.add_search_results([wide_closure(140, rigid2(0.05, -0.03, 0.004))]);
    assert_eq!(global.accepted_loop_closures().len(), 1);
    let shifted = rigid2(1.5, -0.8, 0.2);
    // Alone, a match 1.7 m from the estimate is held back (beyond drift, it would need a chorus).
    global.add_search_results([wide_closure(150, shifted)]);
    assert_eq!(global.accepted_loop_closures().len(), 1);
    // One 0.6 m off that disagrees with it (the trajectory between them says otherwise) is held back
    // too: within what 4 m of drift since the closure of node 140 explains (0.7 m), beyond 0.5 m.
    let drift = rigid2(0.48, 0.36, 0.0);
    global.add_search_results([wide_closure(160, drift)]);
    assert_eq!(global.accepted_loop_closures().len(), 1);
    // One that agrees with the second closes the cycle: both are accepted, the first is not.
    let events = global.add_search_results([wide_closure(170, drift * rigid2(0.02, 0.01, 0.002))]);
    let accepted: Vec<u32> = global
        .accepted_loop_closures()
        .iter()
        .map(|c| c.node.index)
        .collect();
    assert_eq!(accepted, vec![140, 160, 170]);
    assert!(
        events
            .iter()
            .any(|e| matches!(e, GlobalSlamEvent::Optimized(_))),
        "a confirmed loop is optimized at once"
    );
    // A wide match far behind along the path (more than agreement_path_length) never agrees.
    let mut global = straight_run(400);
    global.add_search_results([wide_closure(150, rigid2(0.8, 0.6, 0.0))]);
    global.add_search_results([wide_closure(390, rigid2(0.8, 0.6, 0.0))]);
    assert!(global.accepted_loop_closures().is_empty());
}

#[test]
fn the_closures_of_forgotten_nodes_and_submaps_are_forgotten_with_them() {
    let mut global = straight_run(200);
    global.add_search_results([
        wide_closure(139, rigid2(0.0, 0.01, 0.0)),
        wide_closure(140, rigid2(0.0, 0.0, 0.0)),
    ]);
    // Held back: 0.6 m from its estimate, waiting for another match to agree with it.
    global.add_search_results([wide_closure(160, rigid2(0.48, 0.36, 0.0))]);
    assert_eq!(global.accepted_loop_closures().len(), 2);
    assert_eq!(global.pending_unconfirmed.len(), 1);
    let node = |index| NodeId {
        trajectory: 0,
        index,
    };
    global.forget(&[], &[node(139), node(160)]);
    let kept: Vec<u32> = global
        .accepted_loop_closures()
        .iter()
        .map(|c| c.node.index)
        .collect();
    assert_eq!(kept, [140]);
    assert_eq!(global.acceptances.len(), 1);
    assert_eq!(global.closure_states.len(), 1);
    assert!(global.pending_unconfirmed.is_empty());
    assert_eq!(global.loop_closures_accepted(), 2, "the count keeps them");
    // Its submap trimmed, the last one goes too.
    let submap = SubmapId {
        trajectory: 0,
        index: 0,
    };
    global.forget(&[submap], &[]);
    assert!(global.accepted_loop_closures().is_empty());
    assert!(global.closure_states.is_empty());
    assert_eq!(global.loop_closures_accepted(), 2);
}

#[test]
fn a_closure_the_optimized_graph_refuses_is_retracted() {
    let mut global = straight_run(200);
    // Three neighbouring nodes; the middle one matched 0.3 m sideways (10σ), its neighbours where the
    // chain puts them. Each is near enough its estimate to be accepted at once.
    global.add_search_results([
        wide_closure(139, rigid2(0.0, 0.01, 0.0)),
        wide_closure(140, rigid2(0.0, 0.3, 0.0)),
        wide_closure(141, rigid2(0.0, 0.0, 0.0)),
    ]);
    assert_eq!(global.accepted_loop_closures().len(), 3);
    global.optimize();
    assert_eq!(global.closures_retracted(), 1);
    let checks = global.loop_closure_checks();
    let retracted: Vec<u32> = checks
        .iter()
        .filter(|c| c.retracted)
        .map(|c| c.closure.node.index)
        .collect();
    assert_eq!(retracted, vec![140]);
    // Optimized again without it: the others hold, and it no longer pulls node 140 sideways.
    assert!(
        checks
            .iter()
            .filter(|c| !c.retracted)
            .all(LoopClosureCheck::holds)
    );
    let node = global
        .node_pose(NodeId {
            trajectory: 0,
            index: 140,
        })
        .expect("node");
    assert!(node.translation.vector.y.abs() < 0.02, "{node:?}");
    // With retraction off, the same closure stays in the graph.
    let mut global = straight_run(200);
    global.options.loop_closure_retraction_chi2 = 0.0;
    global.add_search_results([
        wide_closure(139, rigid2(0.0, 0.01, 0.0)),
        wide_closure(140, rigid2(0.0, 0.3, 0.0)),
        wide_closure(141, rigid2(0.0, 0.0, 0.0)),
    ]);
    global.optimize();
    assert_eq!(global.closures_retracted(), 0);
    assert!(global.loop_closure_checks().iter().all(|c| !c.retracted));
}

#[test]
fn a_retracted_closure_returns_once_the_graph_fits_it() {
    let mut global = straight_run(200);
    global.add_search_results([
        wide_closure(139, rigid2(0.0, 0.01, 0.0)),
        wide_closure(140, rigid2(0.0, 0.3, 0.0)),
        wide_closure(141, rigid2(0.0, 0.0, 0.0)),
    ]);
    global.optimize();
    assert_eq!(global.closures_retracted(), 1);
    let sideways = |global: &GlobalSlam| {
        global
            .node_pose(NodeId {
                trajectory: 0,
                index: 140,
            })
            .expect("node")
            .translation
            .vector
            .y
    };
    let retracted = sideways(&global);
    // A looser bound (standing in for a graph reshaped by later closures) fits it again: it is back in
    // the graph and pulls node 140 sideways once more.
    global.options.loop_closure_retraction_chi2 = 1e6;
    global.optimize();
    assert_eq!(global.closures_retracted(), 0);
    assert!(
        sideways(&global) > retracted + 0.01,
        "{} vs {retracted}",
        sideways(&global)
    );
}

#[test]
fn a_match_farther_than_drift_explains_is_refused_even_when_another_agrees() {
    let mut global = straight_run(40);
    // Nodes 12 and 13 are 2.4–2.6 m of path from submap 0's first node: drift explains at most
    // 0.5 m + 5 % of that. Two matches that agree with each other 1 m away are both refused.
    let error = rigid2(1.0, 0.0, 0.0);
    global.add_search_results([wide_closure(12, error)]);
    global.add_search_results([wide_closure(13, error)]);
    assert!(global.accepted_loop_closures().is_empty());
    assert_eq!(global.closures_beyond_drift(), 2);
    // Within the bound (0.1 m) it is accepted at once, with its innovation recorded.
    global.add_search_results([wide_closure(14, rigid2(0.1, 0.0, 0.0))]);
    let checks = global.loop_closure_checks();
    assert_eq!(checks.len(), 1);
    assert!((checks[0].acceptance.innovation_translation_m - 0.1).abs() < 1e-9);
    assert!(!checks[0].acceptance.confirmed_by_agreement);
    // Far along the path (35 m driven, no loop closed) the same 1 m is within what drift explains: it
    // waits for a second opinion instead.
    let mut global = straight_run(200);
    global.add_search_results([wide_closure(175, error)]);
    global.add_search_results([wide_closure(178, error)]);
    let checks = global.loop_closure_checks();
    assert_eq!(checks.len(), 2);
    assert!(checks.iter().all(|c| c.acceptance.confirmed_by_agreement));
    assert_eq!(global.closures_beyond_drift(), 0);
}

#[test]
fn an_llo_recovery_adds_its_heading_doubt_to_the_nodes_after_it() {
    let turned = rigid2(0.0, 0.0, 10f64.to_radians());
    // Nodes 30 and 31 lie 6 m along: drift explains 3° + 0.2°/m, so two matches turned 10° against
    // submap 0 are both beyond drift.
    let mut global = straight_run(40);
    global.add_search_results([wide_closure(30, turned)]);
    global.add_search_results([wide_closure(31, turned)]);
    assert!(global.accepted_loop_closures().is_empty());
    assert_eq!(global.closures_beyond_drift(), 2);
    // LLO recovered just before node 20 (3.8 m along): the same matches are within its 0.26 rad (15°)
    // of doubt, far from the estimate, so the second confirms the first.
    let mut global = straight_run(20);
    drive_on_recovering(&mut global, 20..40, Some(20));
    let node = |index| NodeId {
        trajectory: 0,
        index,
    };
    let submap_0 = SubmapId {
        trajectory: 0,
        index: 0,
    };
    let record = &global.nodes[&node(30)];
    let window = global.search_window(node(30), record, submap_0, &global.submaps[&submap_0]);
    let (doubt_rad, doubt_m) =
        global.recovery_doubt(node(30), record, submap_0, &global.submaps[&submap_0]);
    assert!((doubt_rad - 0.26).abs() < 1e-9);
    assert!(
        (doubt_m - 0.26 * 2.2).abs() < 1e-9,
        "lever: 2.2 m since node 19"
    );
    assert!(window.angular_rad > 30f64.to_radians());
    global.add_search_results([wide_closure(30, turned)]);
    global.add_search_results([wide_closure(31, turned)]);
    assert_eq!(global.accepted_loop_closures().len(), 2);
    assert!(
        global
            .loop_closure_checks()
            .iter()
            .all(|c| c.acceptance.confirmed_by_agreement)
    );
    assert_eq!(global.closures_beyond_drift(), 0);
    // A node before the recovery has no doubt.
    let before = &global.nodes[&node(15)];
    assert_eq!(
        global.recovery_doubt(node(15), before, submap_0, &global.submaps[&submap_0]),
        (0.0, 0.0)
    );
}

#[test]
fn a_slip_beyond_drift_is_repaired_when_nodes_and_submaps_agree_on_it() {
    let mut global = straight_run(40);
    let error = rigid2(1.0, 0.0, 0.0);
    let to_submap_1 = |node: u32| LoopClosure {
        submap: SubmapId {
            trajectory: 0,
            index: 1,
        },
        submap_from_node: rigid2(0.2 * f64::from(node) - 2.2, 0.0, 0.0) * error,
        ..wide_closure(node, error)
    };
    // Four nodes agree on a 1 m correction, all against submap 0: still refused.
    for node in [12, 13, 14, 15] {
        global.add_search_results([wide_closure(node, error)]);
    }
    assert!(global.accepted_loop_closures().is_empty());
    // A fifth node agrees through another submap: the chorus is accepted together.
    global.add_search_results([to_submap_1(5)]);
    let accepted: Vec<u32> = global
        .accepted_loop_closures()
        .iter()
        .map(|c| c.node.index)
        .collect();
    assert_eq!(accepted, vec![12, 13, 14, 15, 5]);
    assert_eq!(global.closures_beyond_drift(), 0);
}

#[test]
fn the_search_window_grows_with_the_path_since_the_last_loop() {
    let global = straight_run(300);
    let cb = ConstraintBuilderOptions::default();
    let node = NodeId {
        trajectory: 0,
        index: 250,
    };
    let sid = SubmapId {
        trajectory: 0,
        index: 0,
    };
    let window = global.search_window(node, &global.nodes()[&node], sid, &global.submaps()[&sid]);
    // 50 m driven since the start (no loop closed yet), the submap ~49 m back along the path.
    let path = 0.2 * 250.0 - 0.0;
    assert!(
        (window.linear_m
            - (cb.fast_correlative.linear_search_window + cb.linear_window_growth * path))
            .abs()
            < 1e-6,
        "{window:?}"
    );
    assert!(window.angular_rad > cb.fast_correlative.angular_search_window);
    // The submap the robot has just left is searched with the default window.
    let recent = NodeId {
        trajectory: 0,
        index: 11,
    };
    let window = global.search_window(
        recent,
        &global.nodes()[&recent],
        sid,
        &global.submaps()[&sid],
    );
    assert!(window.linear_m < cb.fast_correlative.linear_search_window + 0.2);
}

#[test]
fn a_placed_trajectory_is_searched_as_if_it_had_just_closed_a_loop() {
    let mut global = placed_second_trajectory();
    let cb = ConstraintBuilderOptions::default();
    let sid = SubmapId {
        trajectory: 0,
        index: 0,
    };
    let window_at = |global: &GlobalSlam, index: u32| {
        let node = NodeId {
            trajectory: 1,
            index,
        };
        global.search_window(node, &global.nodes()[&node], sid, &global.submaps()[&sid])
    };
    // Placed at its newest node after 50 m unplaced: there the map holds it as well as a closure would.
    let placed = window_at(&global, 249);
    assert!(
        (placed.linear_m - cb.fast_correlative.linear_search_window).abs() < 1e-9,
        "{placed:?}"
    );
    assert!((placed.angular_rad - cb.fast_correlative.angular_search_window).abs() < 1e-9);
    // Its nodes after the placement drift from there again.
    drive_second_trajectory(&mut global, 250..300);
    let later = window_at(&global, 299);
    let expected = cb.fast_correlative.linear_search_window + cb.linear_window_growth * 10.0;
    assert!((later.linear_m - expected).abs() < 1e-6, "{later:?}");
}

/// [`straight_run`]'s map (trajectory 0) and a second trajectory driven 50 m beside it, placed at its
/// newest node.
pub(super) fn placed_second_trajectory() -> GlobalSlam {
    placed_second_trajectory_fitted(None)
}

/// [`placed_second_trajectory`], placed by a search that fitted the scans of its nodes `fitted`.
fn placed_second_trajectory_fitted(fitted: Option<(u32, u32)>) -> GlobalSlam {
    let mut global = straight_run(20);
    global.start_trajectory(1, None).expect("new trajectory");
    drive_second_trajectory(&mut global, 0..250);
    assert!(global.place_trajectory(1, rigid2(-48.0, 0.0, 0.0), fitted));
    global
}

/// Matches of trajectory 1's nodes 240–244 against trajectory 0's two submaps (the last through submap
/// 1), each putting its node 1 m from where [`placed_second_trajectory`] has it; what was decided of each.
fn chorus_one_metre_off(global: &mut GlobalSlam) -> Vec<MatchDecision> {
    let error = rigid2(1.0, 0.0, 0.0);
    [(240, 0), (241, 0), (242, 0), (243, 0), (244, 1)]
        .into_iter()
        .flat_map(|(index, submap)| {
            let submap_at = if submap == 0 { 0.0 } else { 2.2 };
            let closure = LoopClosure {
                submap: SubmapId {
                    trajectory: 0,
                    index: submap,
                },
                node: NodeId {
                    trajectory: 1,
                    index,
                },
                submap_from_node: rigid2(-48.0 + 0.2 * f64::from(index) - submap_at, 0.0, 0.0)
                    * error,
                score: 0.7,
                runner_up_score: None,
                information: None,
            };
            decisions(&global.add_search_results([closure]))
        })
        .map(|(_, decision)| decision)
        .collect()
}

#[test]
fn no_chorus_beyond_drift_moves_the_nodes_that_fitted_a_placement() {
    use MatchDecision::*;
    // Placed at node 249, nodes 240–244 lie before it: 1 m off is beyond the drift they may have.
    let a_chorus = [
        HeldBeyondDrift,
        HeldBeyondDrift,
        HeldBeyondDrift,
        HeldBeyondDrift,
        ConfirmedBeyondDrift,
    ];
    // Placed without a search: the chorus repairs what it takes for an LLO slip.
    let mut global = placed_second_trajectory_fitted(None);
    assert_eq!(chorus_one_metre_off(&mut global), a_chorus);
    // Placed by a search that fitted nodes 200–249 to the map: the placement vouches for their LLO,
    // and the chorus contradicts it.
    let mut global = placed_second_trajectory_fitted(Some((200, 249)));
    assert_eq!(chorus_one_metre_off(&mut global), [RefusedByPlacement; 5]);
    assert!(global.accepted_loop_closures().is_empty());
    // Fitted with nodes 245–249 only: LLO between 240–244 and them is the search's blind spot.
    let mut global = placed_second_trajectory_fitted(Some((245, 249)));
    assert_eq!(chorus_one_metre_off(&mut global), a_chorus);
    // Unplaced and placed again without a search: nothing vouches any more.
    let mut global = placed_second_trajectory_fitted(Some((200, 249)));
    assert!(global.unplace_trajectory(1));
    assert!(global.place_trajectory(1, rigid2(-48.0, 0.0, 0.0), None));
    assert_eq!(chorus_one_metre_off(&mut global), a_chorus);
}

#[test]
fn a_prior_found_by_a_search_elsewhere_pins_the_nodes_it_fitted_as_a_placement_here_does() {
    use MatchDecision::*;
    // Trajectory 1 started at its robot's placement, 50 m of route before it.
    let started = |fitted: Option<(u32, u32)>| {
        let mut global = straight_run(20);
        global
            .start_trajectory(1, Some(rigid2(-48.0, 0.0, 0.0)))
            .expect("new trajectory");
        if let Some(fitted) = fitted {
            assert!(global.set_placement_fit(1, fitted));
        }
        drive_second_trajectory(&mut global, 0..250);
        global
    };
    // A bare prior: drift grows from its first node, 48 m allow 1 m, and a second match confirms the
    // first.
    let decided = chorus_one_metre_off(&mut started(None));
    assert_eq!(decided[..2], [HeldUnconfirmed, Confirmed]);
    // The robot's search fitted nodes 0–249 at it: pinned there, the matches are refused.
    let mut global = started(Some((0, 249)));
    assert_eq!(chorus_one_metre_off(&mut global), [RefusedByPlacement; 5]);
    assert!(global.accepted_loop_closures().is_empty());
    // Unanchored, a trajectory has no placement to pin anything.
    let mut global = straight_run(20);
    global.start_trajectory(1, None).expect("new trajectory");
    assert!(!global.set_placement_fit(1, (0, 9)));
}

/// Adds the nodes `indices` of trajectory 1, along x in 0.2 m steps, all in its submap 0.
pub(super) fn drive_second_trajectory(global: &mut GlobalSlam, indices: std::ops::Range<u32>) {
    for i in indices {
        let node = LloNode {
            time: Timestamp(1_000_000_000_000 + i64::from(i) * 100_000_000),
            local_pose: rigid2(0.2 * f64::from(i), 0.0, 0.0),
            points: vec![Point2::new(1.0, 0.0)],
            insertion_submaps: vec![(0, Rigid2::identity())],
            finished_submaps: Vec::new(),
            recovered: false,
        };
        global.add_node(1, node).expect("node added");
    }
}

/// The decisions the events of `add_search_results` report, by node index.
fn decisions(events: &[GlobalSlamEvent]) -> Vec<(u32, MatchDecision)> {
    events
        .iter()
        .filter_map(|e| match e {
            GlobalSlamEvent::MatchDecided(d) => Some((d.closure.node.index, d.decision)),
            _ => None,
        })
        .collect()
}

#[test]
fn each_match_is_reported_once_with_the_rule_that_decided_it() {
    use MatchDecision::*;
    let mut global = straight_run(200);
    let near = global.add_search_results([wide_closure(140, rigid2(0.05, -0.03, 0.004))]);
    assert_eq!(decisions(&near), [(140, Accepted)]);
    let far = global.add_search_results([wide_closure(150, rigid2(1.5, -0.8, 0.2))]);
    assert_eq!(decisions(&far), [(150, HeldBeyondDrift)]);
    let drift = rigid2(0.48, 0.36, 0.0);
    let held = global.add_search_results([wide_closure(160, drift)]);
    assert_eq!(decisions(&held), [(160, HeldUnconfirmed)]);
    let agreeing =
        global.add_search_results([wide_closure(170, drift * rigid2(0.02, 0.01, 0.002))]);
    assert_eq!(decisions(&agreeing), [(170, Confirmed)]);

    // Two matches of one node at places 1 m apart: neither is believed.
    let mut global = straight_run(200);
    let split = global.add_search_results([
        wide_closure(140, Rigid2::identity()),
        wide_closure(140, rigid2(1.0, 0.0, 0.0)),
    ]);
    assert_eq!(decisions(&split), [(140, Outvoted), (140, Outvoted)]);

    // A chorus beyond drift: four held, the fifth (through another submap) confirms them.
    let mut global = straight_run(40);
    let error = rigid2(1.0, 0.0, 0.0);
    for node in [12, 13, 14, 15] {
        let events = global.add_search_results([wide_closure(node, error)]);
        assert_eq!(decisions(&events), [(node, HeldBeyondDrift)]);
    }
    let fifth = global.add_search_results([LoopClosure {
        submap: SubmapId {
            trajectory: 0,
            index: 1,
        },
        submap_from_node: rigid2(0.2 * 5.0 - 2.2, 0.0, 0.0) * error,
        ..wide_closure(5, error)
    }]);
    assert_eq!(decisions(&fifth), [(5, ConfirmedBeyondDrift)]);
}

#[test]
fn matches_of_one_node_outvote_each_other_only_as_rivals() {
    use MatchDecision::*;
    let pair = |global: &mut GlobalSlam, apart: f64| {
        decisions(&global.add_search_results([
            wide_closure(140, Rigid2::identity()),
            wide_closure(140, rigid2(apart, 0.0, 0.0)),
        ]))
    };
    // 0.3 m apart: they do not agree, and by default every match that does not agree is a rival.
    assert_eq!(
        pair(&mut straight_run(200), 0.3),
        [(140, Outvoted), (140, Outvoted)]
    );
    // Rivals only beyond 0.5 m or 3°: 0.3 m apart is one place, each judged alone (both near the estimate).
    let rivals_beyond = |global: &mut GlobalSlam| {
        global.options.constraint_builder.rival_translation = 0.5;
        global.options.constraint_builder.rival_rotation = 3f64.to_radians();
    };
    let mut global = straight_run(200);
    rivals_beyond(&mut global);
    assert_eq!(pair(&mut global, 0.3), [(140, Accepted), (140, Accepted)]);
    // 1 m apart they are still two places, and neither is believed.
    let mut global = straight_run(200);
    rivals_beyond(&mut global);
    assert_eq!(pair(&mut global, 1.0), [(140, Outvoted), (140, Outvoted)]);
}

/// [`straight_run`]'s 200 nodes, optimized, settled, then a closure of node 140 that pulls it 3 cm aside
/// and one more optimization; returns how far nodes 100 and 140 moved in it (metres).
fn shifts_after_a_closure_once_settled(settled_region_hops: usize) -> (f64, f64) {
    let mut global = GlobalSlam::new(GlobalSlamOptions {
        optimize_every_n_nodes: 0,
        settled_region_hops,
        constraint_builder: ConstraintBuilderOptions {
            sampling_ratio: 0.0,
            ..Default::default()
        },
        ..Default::default()
    })
    .expect("valid options");
    drive_on(&mut global, 0..200);
    global.optimize();
    global.set_trajectory_settled(0, true);
    let node = |index| {
        VariableId::Node(NodeId {
            trajectory: 0,
            index,
        })
    };
    let before = |global: &GlobalSlam, index| global.graph().pose(node(index)).expect("node");
    let (far, near) = (before(&global, 100), before(&global, 140));
    global.add_search_results([wide_closure(140, rigid2(0.0, 0.03, 0.0))]);
    assert_eq!(global.accepted_loop_closures().len(), 1);
    global.optimize();
    let moved = |was: Rigid2, index| {
        (before(&global, index).translation.vector - was.translation.vector).norm()
    };
    (moved(far, 100), moved(near, 140))
}

#[test]
fn once_settled_an_optimization_moves_only_what_lies_near_the_new_constraints() {
    // One hop from the closure's ends (node 140, submap 0): submap 0's nodes, nodes 139 and 141 and
    // submap 1 move; node 100 holds still, and node 140 moves a little, the chain held two nodes away.
    let (far, near) = shifts_after_a_closure_once_settled(1);
    assert!(far == 0.0, "node 100 held still: moved {far} m");
    assert!(near > 1e-5, "node 140 moved {near} m");
    // The whole graph: the closure's pull reaches node 100 too (about 1 cm).
    let (far, near) = shifts_after_a_closure_once_settled(0);
    assert!(far > 5e-3, "node 100 moved {far} m");
    assert!(near > far, "node 140 moved {near} m");
}
