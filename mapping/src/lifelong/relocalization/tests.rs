use nalgebra::Vector2;

use super::start_search::thinned_to;
use super::*;
use crate::geometry::Rigid2Ext as _;
use crate::geometry::rigid2;
use crate::grid::MapLimits;
use crate::scan_matching::test_support::{
    ROOM_WALLS, room_grid, room_scan, wall_points, walls_grid,
};

/// Points every 10 cm along the room's walls seen from `world_from_robot`; the inner walls (goods,
/// displays) stand `shift` metres further along +y than when the map was made.
fn changed_room_scan(world_from_robot: &Rigid2, shift: f64) -> Vec<Point2<f32>> {
    let walls: Vec<([f64; 2], [f64; 2])> = ROOM_WALLS
        .iter()
        .enumerate()
        .map(|(k, &(a, b))| {
            let dy = if k >= 4 { shift } else { 0.0 };
            ([a[0], a[1] + dy], [b[0], b[1] + dy])
        })
        .collect();
    wall_points(&walls, world_from_robot, 0.05, 0.1, f64::INFINITY)
}

#[test]
fn a_tolerant_match_survives_moved_goods_and_stays_precise() {
    let grid = room_grid();
    let truth = rigid2(2.7, 2.2, 0.4);
    let scans = vec![(Rigid2::identity(), changed_room_scan(&truth, 0.15))];
    let options = |match_tolerance| RelocalizationOptions {
        voxel_size: 0.0,
        min_score: 0.3,
        match_tolerance,
        ..RelocalizationOptions::default()
    };
    let exact = relocalize_scans_in_grid(&grid, &scans, &options(0.0))
        .found()
        .expect("the outer walls alone place the scan");
    let tolerant = relocalize_scans_in_grid(&grid, &scans, &options(0.15))
        .found()
        .expect("tolerant match");
    assert!(
        tolerant.score > exact.score + 0.05,
        "tolerant {} vs exact {}",
        tolerant.score,
        exact.score
    );
    let pose = tolerant.global_from_local;
    let error = (pose.translation.vector - truth.translation.vector).norm();
    assert!(error < 0.05, "refined on the sharp map: {error} m off");
    assert!((pose.theta() - truth.theta()).abs() < 1f64.to_radians());
}

#[test]
fn nothing_to_match_is_not_found() {
    let grid = room_grid();
    let options = RelocalizationOptions::default();
    assert_eq!(
        relocalize_scans_in_grid(&grid, &[], &options),
        RelocalizationOutcome::NotFound
    );
    assert_eq!(
        relocalize_scans_in_grid(&grid, &[(Rigid2::identity(), Vec::new())], &options),
        RelocalizationOutcome::NotFound
    );
    assert!(
        RelocalizationOptions {
            match_tolerance: -0.1,
            ..options
        }
        .validate()
        .is_err()
    );
}

/// Two identical corridors, 20 m × 2 m, closed at x = 0 and open at x = 20; only the first
/// (y ∈ [0, 2]) has a pillar against its wall at x ∈ [15, 16]. Walls as segments.
const CORRIDORS: [([f64; 2], [f64; 2]); 8] = [
    ([0.0, 0.0], [20.0, 0.0]),
    ([0.0, 2.0], [20.0, 2.0]),
    ([0.0, 0.0], [0.0, 2.0]),
    ([15.0, 0.0], [15.0, 0.5]),
    ([15.0, 0.5], [16.0, 0.5]),
    ([16.0, 0.5], [16.0, 0.0]),
    ([0.0, 8.0], [20.0, 8.0]),
    ([0.0, 10.0], [20.0, 10.0]),
];
const CORRIDOR_B_BACK: ([f64; 2], [f64; 2]) = ([0.0, 8.0], [0.0, 10.0]);

/// The corridors in a 5 cm grid; only the corridors and a 0.3 m margin are known.
fn corridors_grid() -> ProbabilityGrid {
    let walls: Vec<([f64; 2], [f64; 2])> =
        CORRIDORS.iter().copied().chain([CORRIDOR_B_BACK]).collect();
    let limits = MapLimits::new(0.05, Vector2::new(-1.0, -1.0), 440, 240);
    walls_grid(&walls, &limits, |c| {
        let inside = |y0: f64| (-0.3..=20.3).contains(&c.x) && (y0 - 0.3..=y0 + 2.3).contains(&c.y);
        inside(0.0) || inside(8.0)
    })
}

/// What a robot at `world_from_robot` in the first corridor sees: wall points every 10 cm within 4 m
/// of it (the first corridor's walls only), in its frame.
fn corridor_scan(world_from_robot: &Rigid2) -> Vec<Point2<f32>> {
    wall_points(&CORRIDORS[..6], world_from_robot, 0.05, 0.1, 4.0)
}

/// The scans of a robot driving the first corridor from (3, 1) to (18.5, 1) past the pillar, 0.5 m
/// apart, as `(local_from_tracking, points)` with LLO's frame at its first pose.
fn corridor_route() -> Vec<(Rigid2, Vec<Point2<f32>>)> {
    let start = rigid2(3.0, 1.0, 0.0);
    (0..=31)
        .map(|k| {
            let world = rigid2(3.0 + 0.5 * f64::from(k), 1.0, 0.0);
            (start.inverse() * world, corridor_scan(&world))
        })
        .collect()
}

#[test]
fn an_ambiguous_start_is_placed_once_the_robot_sees_what_tells_the_places_apart() {
    let grid = corridors_grid();
    // The one pillar tells the corridors apart at z ≈ 3.3 per point (set here, and per point: counted
    // in blocks it is one piece of evidence, see `one_pillar_is_one_piece_of_evidence`).
    let options = RelocalizationOptions {
        min_disambiguation_z: 3.0,
        route_block_m: 0.0,
        ..RelocalizationOptions::default()
    };
    // The robot drives the first corridor from x = 3 to x = 18.5; LLO's frame is its first pose.
    let start = rigid2(3.0, 1.0, 0.0);
    let scans = corridor_route();
    let search = StartSearch::new(&grid, &options);
    let first_answer = search.search(&scans[..3]);
    // The first search ranks by score margin: an ambiguous one is refused before any fit is judged.
    assert_eq!(first_answer.fit, None);
    let first = first_answer.outcome;
    let RelocalizationOutcome::Ambiguous {
        runner_up_from_best,
        ..
    } = first
    else {
        panic!("both corridors' closed ends look alike: {first:?}");
    };
    // The runner-up is the other corridor, 8 m over.
    let [dx, dy, _] = runner_up_from_best;
    assert!((dx.hypot(dy) - 8.0).abs() < 0.5, "{runner_up_from_best:?}");
    let mut placed = None;
    for k in (5..=scans.len()).step_by(4) {
        let answer = search.search_again(&scans[..k], 0.0);
        match answer.outcome {
            RelocalizationOutcome::Found(found) => {
                // Placed: its fit passed the floor, and the answer says by how much.
                assert!(
                    answer
                        .fit
                        .is_some_and(|fit| fit >= options.min_unfiltered_score),
                    "{:?}",
                    answer.fit
                );
                placed = Some((k, found));
                break;
            }
            RelocalizationOutcome::Ambiguous { .. } => {}
            RelocalizationOutcome::NotFound => panic!("nothing fits {k} scans"),
        }
    }
    let (k, found) = placed.unwrap_or_else(|| {
        panic!(
            "not placed by the corridor's end: {:?}",
            search.search_again(&scans, 0.0).outcome
        )
    });
    // Only scans within 4 m of the pillar see it (x ≥ 11, scan 16 on).
    assert!(
        k > 16,
        "placed at {k} scans, before anything told the corridors apart"
    );
    let error = (found.global_from_local.translation.vector - start.translation.vector).norm();
    assert!(error < 0.05, "placed {error} m off");
    assert!(found.global_from_local.theta().abs() < 1f64.to_radians());
}

#[test]
fn a_cloud_longer_than_the_short_route_is_held_to_the_long_route_bar() {
    let grid = corridors_grid();
    // Per point, the pillar tells the corridors apart at z ≈ 3.3 (see the test above).
    let options = |long_route_scans| RelocalizationOptions {
        min_disambiguation_z: 3.0,
        long_route_min_disambiguation_z: 1e6,
        long_route_scans,
        route_block_m: 0.0,
        ..RelocalizationOptions::default()
    };
    let scans = corridor_route();
    let k = scans.len();
    let short = StartSearch::new(&grid, &options(k));
    assert!((short.disambiguation_z(k) - 3.0).abs() < 1e-12);
    assert!(
        matches!(
            short.search_again(&scans, 0.0).outcome,
            RelocalizationOutcome::Found(_)
        ),
        "the whole route, at the short-route bar, tells the corridors apart"
    );
    let long = StartSearch::new(&grid, &options(k - 1));
    assert!((long.disambiguation_z(k) - 1e6).abs() < 1e-6);
    assert!(
        matches!(
            long.search_again(&scans, 0.0).outcome,
            RelocalizationOutcome::Ambiguous { .. }
        ),
        "one scan past the short route, the long-route bar holds"
    );
}

/// The corridors prepared for searches compared point by point (see
/// `one_pillar_is_one_piece_of_evidence`), and the two placements of [`corridor_route`]'s LLO frame
/// (its first pose) they are told apart by: the truth, and the look-alike in the other corridor, 8 m
/// over.
fn per_point_corridors() -> (StartSearch, Rigid2, Rigid2) {
    let options = RelocalizationOptions {
        route_block_m: 0.0,
        ..RelocalizationOptions::default()
    };
    let search = StartSearch::new(&corridors_grid(), &options);
    (search, rigid2(3.0, 1.0, 0.0), rigid2(3.0, 9.0, 0.0))
}

#[test]
fn the_route_overturns_a_look_alike_placement_and_upholds_the_true_one() {
    // The robot drives the first corridor from x = 3 to x = 18.5 (past the pillar).
    let (search, truth, look_alike) = per_point_corridors();
    let scans = corridor_route();
    // Before the pillar neither fits the route better (the one pillar gives z ≈ 3.3 past it).
    let early = search.contest(&scans[..8], &look_alike, &[truth]).unwrap();
    assert!(early.abs() < 1.0, "decided before the pillar: z {early}");
    // Past it, the route tells them apart, either way round.
    let wrong = search.contest(&scans, &look_alike, &[truth]).unwrap();
    assert!(
        wrong <= -3.0,
        "the truth does not overturn the look-alike: z {wrong}"
    );
    let right = search.contest(&scans, &truth, &[look_alike]).unwrap();
    assert!(right >= 3.0, "the truth is not upheld: z {right}");
    assert!(
        (right + wrong).abs() < 0.5,
        "not one test either way round: {right} {wrong}"
    );
    // A rival that refines onto the placement is no rival.
    let nudged = truth * rigid2(0.05, 0.02, 0.0);
    assert_eq!(search.contest(&scans, &truth, &[nudged]), None);
}

/// [`corridor_route`] as a drifting LLO records it: each 0.5 m step's heading off by `drift_rad_per_m`
/// per metre more than the last, so the merged cloud bends (the scans themselves are the truth's).
fn bent_corridor_route(drift_rad_per_m: f64) -> Vec<(Rigid2, Vec<Point2<f32>>)> {
    let mut local = Rigid2::identity();
    corridor_route()
        .into_iter()
        .enumerate()
        .map(|(k, (_, points))| {
            if k > 0 {
                local *= rigid2(0.5, 0.0, 0.5 * drift_rad_per_m);
            }
            (local, points)
        })
        .collect()
}

#[test]
fn a_route_bent_by_drift_is_judged_in_pieces() {
    // Per point, as in the tests above: the pillar tells the corridors apart.
    let (search, truth, look_alike) = per_point_corridors();
    let straight = corridor_route();
    let rigid = |scans: &[(Rigid2, Vec<Point2<f32>>)]| {
        search.contest_each(scans, &truth, &[look_alike])[0].unwrap()
    };
    let pieces = |scans: &[(Rigid2, Vec<Point2<f32>>)]| {
        search.contest_each_in_pieces(scans, &truth, &[look_alike], 4.0)[0].unwrap()
    };
    // Straight, the pieces see the pillar as the whole route does, and more sharply.
    assert!(
        pieces(&straight) > rigid(&straight),
        "{} {}",
        pieces(&straight),
        rigid(&straight)
    );
    // Bent by 1°/m (15° over the route), one rigid pose fits neither corridor: the whole route decides
    // nothing, and the pieces, each refined where it is, still see the pillar.
    let bent = bent_corridor_route(1f64.to_radians());
    let (bent_rigid, bent_pieces) = (rigid(&bent), pieces(&bent));
    assert!(bent_rigid.abs() < 0.5, "rigid z {bent_rigid}");
    assert!(bent_pieces > 2.0, "pieces z {bent_pieces}");
    // One test either way round: the pieces give the look-alike, placed, the same freedom.
    let swapped = search.contest_each_in_pieces(&bent, &look_alike, &[truth], 4.0)[0].unwrap();
    assert!(
        (swapped + bent_pieces).abs() < 1e-9,
        "{swapped} {bent_pieces}"
    );
    // Off: no pieces; a rival that refines onto the placement is no rival, as in `contest_each`.
    assert!(
        search
            .contest_each_in_pieces(&straight, &truth, &[look_alike], 0.0)
            .is_empty()
    );
    let nudged = truth * rigid2(0.05, 0.02, 0.0);
    assert_eq!(
        search.contest_each_in_pieces(&straight, &truth, &[nudged], 4.0),
        vec![None]
    );
}

#[test]
fn a_retry_the_bent_route_leaves_undecided_is_decided_in_pieces() {
    let (search, truth, look_alike) = per_point_corridors();
    // Bent by 0.5°/m (7.5° over the route; at 1°/m no rigid pose fits the map well enough to be found).
    let bent = bent_corridor_route(0.5f64.to_radians());
    // Over the whole route, one rigid pose fits either corridor about as badly: undecided (z 1.3).
    let whole = search.search_again(&bent, 0.0);
    assert!(
        matches!(whole.outcome, RelocalizationOutcome::Ambiguous { .. }),
        "{:?}",
        whole.outcome
    );
    // In pieces of 4 m each refined where it is, the pillar tells them apart: placed in the right one.
    let pieces = search.search_again(&bent, 4.0);
    let RelocalizationOutcome::Found(found) = pieces.outcome else {
        panic!("{:?}", pieces.outcome);
    };
    let off = |pose: &Rigid2| {
        (pose.translation.vector - found.global_from_local.translation.vector).norm()
    };
    assert!(off(&truth) < 0.3, "{} m from the truth", off(&truth));
    assert!(off(&look_alike) > 5.0);
    let z = pieces.weakest_z.expect("a rival was beaten");
    assert!(z >= search.disambiguation_z(bent.len()), "z {z}");
    // The best is what the whole route ranked first either way.
    assert_eq!(pieces.best, whole.best);
}

#[test]
fn the_recheck_decides_in_pieces_where_the_retry_would() {
    let (search, truth, look_alike) = per_point_corridors();
    let bent = bent_corridor_route(0.5f64.to_radians());
    let candidates = [look_alike, truth];
    // Over the whole route the bent corridor fits both about as badly: no retry brought forward.
    assert!(!search.route_decides(&bent, &candidates, 0.0));
    // In the retry's pieces the pillar decides: the recheck says the search is worth making now.
    assert!(search.route_decides(&bent, &candidates, 4.0));
    assert!(search.route_decides(&bent, &[truth, look_alike], 4.0));
    // Before the pillar the pieces tell nothing either.
    assert!(!search.route_decides(&bent[..8], &candidates, 4.0));
}

#[test]
fn one_pillar_is_one_piece_of_evidence() {
    // The route past the pillar, as in the test above: per point the pillar's dozen points decide
    // (|z| > 3); counted per 1.2 m block (the default) they are one piece of evidence, and a whole
    // route of look-alike corridor around it decides nothing.
    let grid = corridors_grid();
    let truth = rigid2(3.0, 1.0, 0.0);
    let look_alike = rigid2(3.0, 9.0, 0.0);
    let scans = corridor_route();
    let z = |block_m: f64| {
        let options = RelocalizationOptions {
            route_block_m: block_m,
            ..RelocalizationOptions::default()
        };
        StartSearch::new(&grid, &options)
            .contest(&scans, &truth, &[look_alike])
            .unwrap()
    };
    let (per_point, blocked) = (z(0.0), z(RelocalizationOptions::default().route_block_m));
    assert!(per_point > 3.0, "per point: z {per_point}");
    assert!(blocked > 0.0 && blocked < 2.0, "per block: z {blocked}");
}

#[test]
fn a_first_search_is_refused_where_its_best_fits_the_unfiltered_map_below_the_floor() {
    let grid = corridors_grid();
    let scans = corridor_route();
    let answer = |min_unfiltered_score: f32| {
        StartSearch::new(
            &grid,
            &RelocalizationOptions {
                min_unfiltered_score,
                // The corridors differ by one pillar: no margin asked, so the best is placed.
                min_score_margin: 0.0,
                ..RelocalizationOptions::default()
            },
        )
        .search(&scans)
    };
    // The route past the pillar places the robot, and says how well it fits.
    let placed = answer(0.0);
    let Some(fit) = placed.fit else {
        panic!("the route past the pillar places: {placed:?}");
    };
    assert!(
        matches!(placed.outcome, RelocalizationOutcome::Found(_)),
        "{placed:?}"
    );
    // The same search with the floor just above that fit refuses it.
    let refused = answer(fit + 0.01);
    assert!(
        matches!(refused.outcome, RelocalizationOutcome::NotFound),
        "{refused:?}"
    );
    assert_eq!(refused.fit, Some(fit));
}

#[test]
fn the_route_decides_between_candidates_once_it_passes_what_tells_them_apart() {
    let grid = corridors_grid();
    // Per point, at the pillar's z ≈ 3.3 (see `one_pillar_is_one_piece_of_evidence`).
    let options = RelocalizationOptions {
        min_disambiguation_z: 3.0,
        route_block_m: 0.0,
        ..RelocalizationOptions::default()
    };
    let search = StartSearch::new(&grid, &options);
    let truth = rigid2(3.0, 1.0, 0.0);
    let candidates = [rigid2(3.0, 9.0, 0.0), truth];
    let scans = corridor_route();
    // Whichever comes first in the list: before the pillar the corridors look alike.
    assert!(!search.route_decides(&scans[..8], &candidates, 0.0));
    assert!(search.route_decides(&scans, &candidates, 0.0));
    assert!(search.route_decides(&scans, &[truth, candidates[0]], 0.0));
    // No candidate: nothing decided.
    assert!(!search.route_decides(&scans, &[], 0.0));
}

#[test]
fn the_strict_decision_refuses_look_alike_places_and_answers_distinct_ones() {
    let grid = corridors_grid();
    // The pillar is the only difference and leaves about 12 points after thinning: its evidence is about
    // √12 ≈ 3.5 standard errors, below the default 4 of a building's worth of points.
    let options = RelocalizationOptions {
        min_answer_z: 3.0,
        ..RelocalizationOptions::default()
    };
    let search = StartSearch::new(&grid, &options);
    let one_scan = |world: &Rigid2| vec![(Rigid2::identity(), corridor_scan(world))];
    // Near the closed end the two corridors look alike: refused, though one of them is right.
    let evidence = search.evidence(&one_scan(&rigid2(3.0, 1.0, 0.0)));
    let (_, _, offset) = evidence
        .as_ref()
        .and_then(|e| e.weakest)
        .expect("the other corridor is a candidate");
    assert!(
        (offset[0].hypot(offset[1]) - 8.0).abs() < 0.5,
        "{evidence:?}"
    );
    let outcome = search.decide(evidence.as_ref());
    assert!(
        matches!(outcome, RelocalizationOutcome::Ambiguous { .. }),
        "look-alike ends placed: {outcome:?}"
    );
    // Driving past the pillar, only the first corridor fits: placed, and the first scan right.
    let truth = rigid2(12.0, 1.0, 0.3);
    let stack: Vec<(Rigid2, Vec<Point2<f32>>)> = (0..12)
        .map(|k| {
            let world = rigid2(12.0 + 0.5 * f64::from(k), 1.0, 0.3);
            (truth.inverse() * world, corridor_scan(&world))
        })
        .collect();
    let evidence = search.evidence(&stack);
    let found = search
        .decide(evidence.as_ref())
        .found()
        .unwrap_or_else(|| panic!("the pillar tells the corridors apart: {evidence:?}"));
    let error = (found.global_from_local.translation.vector - truth.translation.vector).norm();
    assert!(error < 0.05, "placed {error} m off");
    assert!((found.global_from_local.theta() - truth.theta()).abs() < 1f64.to_radians());
    assert_eq!(search.decide(None), RelocalizationOutcome::NotFound);
}

#[test]
fn a_first_scan_that_disagrees_with_its_cloud_is_refused() {
    let grid = room_grid();
    let search = StartSearch::new(&grid, &RelocalizationOptions::default());
    let cloud_pose = rigid2(2.5, 2.0, 0.3);
    let evidence = |shift: f64| SearchEvidence {
        global_from_local: cloud_pose,
        first_scan_global_from_local: rigid2(2.5 + shift, 2.0, 0.3),
        first_scan_shift_m: shift,
        score: 0.7,
        sharp_score: 0.6,
        runner_up: None,
        weakest: None,
        distinct_candidates: 1,
        cloud_points: 300,
        rivals: Vec::new(),
    };
    // A small shift is answered with the cloud's pose.
    let agreeing = search.decide(Some(&evidence(0.05))).found();
    assert_eq!(agreeing.map(|f| f.global_from_local), Some(cloud_pose));
    let RelocalizationOutcome::Ambiguous {
        runner_up_from_best,
        ..
    } = search.decide(Some(&evidence(0.25)))
    else {
        panic!("a first scan 0.25 m from its cloud's pose of it was placed");
    };
    // The rival reported is the first scan's own pose.
    let [dx, dy, dtheta] = runner_up_from_best;
    assert!(
        (dx.hypot(dy) - 0.25).abs() < 1e-9,
        "{runner_up_from_best:?}"
    );
    assert!(dtheta.abs() < 1e-9, "{runner_up_from_best:?}");
}

#[test]
fn the_fit_at_a_pose_tells_mapped_ground_from_unmapped() {
    let grid = room_grid();
    let truth = rigid2(2.5, 2.0, 0.3);
    let scans = vec![(rigid2(1.0, -2.0, 0.5), room_scan(&truth))];
    let search = StartSearch::new(&grid, &RelocalizationOptions::default());
    // The scans' local frame at the truth: the first scan lands on the truth.
    let global_from_local = truth * scans[0].0.inverse();
    let at_truth = search.fit(&scans, &global_from_local).expect("points");
    assert!(at_truth.hit_fraction > 0.95, "{at_truth:?}");
    assert!((at_truth.known_fraction - 1.0).abs() < 1e-9, "{at_truth:?}");
    assert!(at_truth.sharp_score > 0.8, "{at_truth:?}");
    // Moved 3 m along x, most of the cloud falls outside the room's known cells.
    let off = search
        .fit(&scans, &(rigid2(3.0, 0.0, 0.0) * global_from_local))
        .expect("points");
    assert!(off.known_fraction < 0.7, "{off:?}");
    assert!(off.hit_fraction < 0.4, "{off:?}");
    assert!(off.sharp_score < at_truth.sharp_score - 0.3, "{off:?}");
    assert_eq!(at_truth.cloud_points, off.cloud_points);
    assert!(search.fit(&[], &global_from_local).is_none());
}

#[test]
fn a_cloud_is_thinned_for_the_search_to_at_most_the_cap() {
    let cloud: Vec<Point2<f32>> = (0..2000)
        .map(|k| Point2::new((k % 50) as f32 * 0.1, (k / 50) as f32 * 0.1))
        .collect();
    let thinned = thinned_to(&cloud, 200, 0.05);
    assert!(
        thinned.len() <= 200 && thinned.len() > 50,
        "{}",
        thinned.len()
    );
    assert_eq!(thinned_to(&cloud[..100], 200, 0.05).len(), 100);
    // The voxels stop growing at 2 m: a cap below what 2 m voxels leave is not met.
    assert!(thinned_to(&cloud, 1, 0.05).len() > 1);
}
