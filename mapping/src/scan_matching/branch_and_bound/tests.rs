//! Tests of the branch-and-bound matcher: exactness against exhaustive search (Hess et al. 2016 §V-B: the
//! bounds are admissible, so B&B returns the exhaustive optimum) and pose recovery as in Cartographer's
//! `FastCorrelativeScanMatcherTest.CorrectPose`.

use nalgebra::Vector2;

use crate::scan_matching::mean_probability;
use rand::{Rng as _, SeedableRng as _};
use rand_pcg::Pcg64;

use super::*;
use crate::geometry::Rigid2Ext as _;
use crate::scan_matching::test_support::{room_grid, room_scan};
use crate::scan_matching::{LeastSquaresScanMatcher, LeastSquaresScanMatcherOptions};

fn random_grid(rng: &mut Pcg64) -> ProbabilityGrid {
    let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(-0.4, 0.3), 32, 24));
    // Mostly free or unknown, with a sprinkling of likely-occupied cells, like a real submap.
    for v in grid.values_mut() {
        let roll: f64 = rng.random();
        *v = if roll < 0.2 {
            0
        } else if roll < 0.8 {
            rng.random_range(1..8000)
        } else {
            rng.random_range(1..=32767)
        };
    }
    grid
}

fn random_points(rng: &mut Pcg64, n: usize, radius: f32) -> Vec<Point2<f32>> {
    (0..n)
        .map(|_| {
            Point2::new(
                rng.random_range(-radius..radius),
                rng.random_range(-radius..radius),
            )
        })
        .collect()
}

/// The best score over every candidate of `space`, each scored by transforming the points with the
/// candidate pose in floating point.
fn brute_force(space: &SearchSpace, grid: &ProbabilityGrid, points: &[Point2<f32>]) -> f64 {
    let mut best = f64::NEG_INFINITY;
    for k in 0..space.num_scans() {
        let b = space.bounds(k);
        for dy in b.min_y..=b.max_y {
            for dx in b.min_x..=b.max_x {
                best = best.max(mean_probability(grid, points, &space.pose(k, dx, dy)));
            }
        }
    }
    best
}

fn check_match(
    result: Option<Match>,
    expected: f64,
    grid: &ProbabilityGrid,
    points: &[Point2<f32>],
) {
    let result = result.expect("min_score 0 always matches");
    assert!(
        (f64::from(result.score) - expected).abs() < 1e-5,
        "B&B {} vs exhaustive {expected}",
        result.score
    );
    let rescored = mean_probability(grid, points, &result.pose);
    assert!(
        (rescored - expected).abs() < 1e-5,
        "returned pose scores {rescored}"
    );
}

#[test]
fn match_near_equals_exhaustive_search() {
    for seed in 0..4 {
        let mut rng = Pcg64::seed_from_u64(seed);
        let grid = random_grid(&mut rng);
        let points = random_points(&mut rng, 12, 0.5);
        let options = FastCorrelativeScanMatcherOptions {
            linear_search_window: 0.45,
            angular_search_window: 0.6,
            branch_and_bound_depth: 3,
        };
        let matcher = FastCorrelativeScanMatcher::new(&grid, options);
        let initial = rigid2(
            rng.random_range(-0.3..1.0),
            rng.random_range(0.3..1.5),
            rng.random_range(-3.0..3.0),
        );
        let space = matcher.near_space(&initial, &points);
        assert!(space.num_scans() > 5);
        let expected = brute_force(&space, &grid, &points);
        check_match(
            matcher.match_near(&initial, &points, 0.0),
            expected,
            &grid,
            &points,
        );
    }
}

#[test]
fn match_full_equals_exhaustive_search() {
    for (seed, depth) in [(10, 2), (11, 3), (12, 4), (13, 0)] {
        let mut rng = Pcg64::seed_from_u64(seed);
        let grid = random_grid(&mut rng);
        let points = random_points(&mut rng, 10, 0.4);
        let options = FastCorrelativeScanMatcherOptions {
            branch_and_bound_depth: depth,
            ..Default::default()
        };
        let matcher = FastCorrelativeScanMatcher::new(&grid, options);
        let space = matcher.full_space(&points);
        let expected = brute_force(&space, &grid, &points);
        check_match(matcher.match_full(&points, 0.0), expected, &grid, &points);
    }
}

#[test]
fn min_score_is_a_threshold() {
    let mut rng = Pcg64::seed_from_u64(20);
    let grid = random_grid(&mut rng);
    let points = random_points(&mut rng, 10, 0.4);
    let matcher = FastCorrelativeScanMatcher::new(
        &grid,
        FastCorrelativeScanMatcherOptions {
            branch_and_bound_depth: 3,
            ..Default::default()
        },
    );
    let best = matcher.match_full(&points, 0.0).expect("matches").score;
    assert!(matcher.match_full(&points, best + 1e-3).is_none());
    let again = matcher.match_full(&points, best - 1e-3).expect("matches");
    assert!((again.score - best).abs() < 1e-6);
    assert!(matcher.match_full(&[], 0.0).is_none());
}

#[test]
fn recovers_random_poses_near() {
    let grid = room_grid();
    let matcher = FastCorrelativeScanMatcher::new(
        &grid,
        FastCorrelativeScanMatcherOptions {
            linear_search_window: 0.5,
            angular_search_window: 0.4,
            branch_and_bound_depth: 5,
        },
    );
    let refiner = LeastSquaresScanMatcher::new(LeastSquaresScanMatcherOptions {
        translation_weight: 0.0,
        rotation_weight: 0.0,
        ..Default::default()
    });
    let mut rng = Pcg64::seed_from_u64(42);
    for _ in 0..50 {
        let truth = rigid2(
            rng.random_range(0.5..5.5),
            rng.random_range(0.5..4.5),
            rng.random_range(-3.1..3.1),
        );
        let points = room_scan(&truth);
        let initial = rigid2(
            truth.x() + rng.random_range(-0.4..0.4),
            truth.y() + rng.random_range(-0.4..0.4),
            truth.theta() + rng.random_range(-0.3..0.3),
        );
        let result = matcher
            .match_near(&initial, &points, 0.5)
            .expect("finds the room");
        let error = result.pose.inverse() * truth;
        // Correlative matches are exact only to the search grid: one cell, about two angular steps.
        assert!(
            error.translation.vector.norm() < 0.075,
            "{truth:?} → {result:?}"
        );
        assert!(
            error.rotation.angle().abs() < 0.025,
            "{truth:?} → {result:?}"
        );
        // The least-squares matcher takes it from there to sub-centimetre.
        let (refined, _) = refiner.match_pose(
            &result.pose.translation.vector,
            &result.pose,
            &points,
            &grid,
        );
        let error = refined.inverse() * truth;
        assert!(
            error.translation.vector.norm() < 0.01,
            "{truth:?} → {refined:?}"
        );
        assert!(
            error.rotation.angle().abs() < 0.005,
            "{truth:?} → {refined:?}"
        );
        assert!(result.score > 0.7, "{result:?}");
    }
}

#[test]
fn recovers_random_poses_full() {
    let grid = room_grid();
    let matcher =
        FastCorrelativeScanMatcher::new(&grid, FastCorrelativeScanMatcherOptions::default());
    let mut rng = Pcg64::seed_from_u64(43);
    for _ in 0..50 {
        let truth = rigid2(
            rng.random_range(0.5..5.5),
            rng.random_range(0.5..4.5),
            rng.random_range(-3.1..3.1),
        );
        let points = room_scan(&truth);
        let result = matcher.match_full(&points, 0.5).expect("finds the room");
        let error = result.pose.inverse() * truth;
        // Correlative matches are exact only to the search grid: one cell, about two angular steps.
        assert!(
            error.translation.vector.norm() < 0.075,
            "{truth:?} → {result:?}"
        );
        assert!(
            error.rotation.angle().abs() < 0.025,
            "{truth:?} → {result:?}"
        );
    }
}

#[test]
fn validate_rejects_bad_options() {
    assert!(
        FastCorrelativeScanMatcherOptions::default()
            .validate()
            .is_ok()
    );
    for bad in [
        FastCorrelativeScanMatcherOptions {
            branch_and_bound_depth: 17,
            ..Default::default()
        },
        FastCorrelativeScanMatcherOptions {
            angular_search_window: 4.0,
            ..Default::default()
        },
        FastCorrelativeScanMatcherOptions {
            linear_search_window: -0.1,
            ..Default::default()
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
}

#[test]
fn full_candidates_are_distinct_peaks_led_by_the_global_best() {
    for (seed, depth) in [(30, 2), (31, 3), (32, 0)] {
        let mut rng = Pcg64::seed_from_u64(seed);
        let grid = random_grid(&mut rng);
        let points = random_points(&mut rng, 10, 0.4);
        let matcher = FastCorrelativeScanMatcher::new(
            &grid,
            FastCorrelativeScanMatcherOptions {
                branch_and_bound_depth: depth,
                ..Default::default()
            },
        );
        let best = matcher.match_full(&points, 0.0).expect("matches");
        let candidates = matcher.match_full_candidates(&points, 0.0, 4, f32::INFINITY);
        assert_eq!(candidates.len(), 4, "seed {seed}");
        assert!((candidates[0].score - best.score).abs() < 1e-6);
        for pair in candidates.windows(2) {
            assert!(pair[0].score >= pair[1].score, "sorted, seed {seed}");
        }
        let resolution = grid.limits().resolution;
        for (i, a) in candidates.iter().enumerate() {
            for b in &candidates[i + 1..] {
                let d = (a.pose.translation.vector - b.pose.translation.vector) / resolution;
                let rotation = crate::geometry::normalize_angle(
                    a.pose.rotation.angle() - b.pose.rotation.angle(),
                );
                let same = d.x.abs().round() as i32 <= DISTINCT_TRANSLATION_CELLS
                    && d.y.abs().round() as i32 <= DISTINCT_TRANSLATION_CELLS
                    && rotation.abs() <= DISTINCT_ROTATION_RAD + 1e-9;
                assert!(!same, "two candidates of one peak, seed {seed}");
            }
        }
        // A threshold above the fourth keeps only the better ones.
        let fewer =
            matcher.match_full_candidates(&points, candidates[3].score + 1e-4, 4, f32::INFINITY);
        assert!(fewer.len() < 4 && !fewer.is_empty());
    }
}

#[test]
fn a_score_window_returns_the_unbounded_candidates_within_it() {
    for (seed, depth) in [(40, 2), (41, 3), (42, 0), (43, 4)] {
        let mut rng = Pcg64::seed_from_u64(seed);
        let grid = random_grid(&mut rng);
        let points = random_points(&mut rng, 10, 0.4);
        let matcher = FastCorrelativeScanMatcher::new(
            &grid,
            FastCorrelativeScanMatcherOptions {
                branch_and_bound_depth: depth,
                ..Default::default()
            },
        );
        let all = matcher.match_full_candidates(&points, 0.0, 12, f32::INFINITY);
        assert!(all.len() >= 4, "seed {seed}: {} candidates", all.len());
        for window in [0.0, 0.02, 0.05, 0.1] {
            let bounded = matcher.match_full_candidates(&points, 0.0, 12, window);
            let expected: Vec<_> = all
                .iter()
                .filter(|m| m.score >= all[0].score - window - 1e-4)
                .collect();
            assert!(!bounded.is_empty());
            assert!(
                (bounded[0].score - all[0].score).abs() < 1e-6,
                "seed {seed}"
            );
            // Rounding of the window to score units may keep or cut a leaf right at its edge.
            let clear: Vec<_> = all
                .iter()
                .filter(|m| m.score >= all[0].score - window + 1e-4)
                .collect();
            assert!(
                bounded.len() >= clear.len() && bounded.len() <= expected.len(),
                "seed {seed}, window {window}: {} bounded, {}..={} expected",
                bounded.len(),
                clear.len(),
                expected.len()
            );
            for m in &bounded {
                assert!(
                    all.iter()
                        .any(|a| a.pose == m.pose && (a.score - m.score).abs() < 1e-6),
                    "seed {seed}, window {window}: a candidate the unbounded search did not return"
                );
            }
        }
    }
}
