use super::*;
use crate::geometry::Rigid2Ext as _;
use crate::grid::{UNKNOWN_VALUE, value_to_probability};
use crate::lifelong::{MAP_CHANGE_TOLERANCE_M, OCCUPIED_PROBABILITY, map_change_rate};
use crate::sensor::SensorEvent;

fn short() -> SessionOptions {
    SessionOptions {
        max_duration_s: 20.0,
        mapping_max_duration_s: 20.0,
        ..SessionOptions::default()
    }
}

#[test]
fn default_store_is_a_supermarket() {
    let store = Store::generate(&StoreOptions::default(), 7).expect("store");
    assert!(store.area_m2() >= 10_000.0);
    let [goods, _, _, _] = store.items_present(0);
    assert!(goods > 1000, "{goods} goods modules");
}

#[test]
fn sessions_are_deterministic_and_well_formed() {
    let store = Store::generate(&StoreOptions::default(), 7).expect("store");
    let a = store.session(3, &short()).expect("session");
    let b = store.session(3, &short()).expect("session");
    // Bitwise equality (NaN readings compare unequal under PartialEq).
    assert_eq!(format!("{:?}", a.events), format!("{:?}", b.events));
    assert!((a.duration_s - 20.0).abs() < 0.02);
    let scans: Vec<_> = a
        .events
        .iter()
        .filter_map(|e| match e {
            SensorEvent::Scan(s) => Some(s),
            _ => None,
        })
        .collect();
    assert_eq!(scans.len(), a.ground_truth.len());
    assert!((scans.len() as f64 - 20.0 * 15.0).abs() <= 2.0);
    assert_eq!(scans[0].ranges.len(), 819);
    assert!(a.events.windows(2).all(|w| w[0].time() <= w[1].time()));
    let finite = scans[0].ranges.iter().filter(|r| r.is_finite()).count();
    assert!(finite > 600, "{finite} finite ranges");
    // Different sessions start on different days at different places.
    let c = store.session(4, &short()).expect("session");
    assert!(c.events[0].time() > a.events[a.events.len() - 1].time());
    assert!((c.start_pose.translation.vector - a.start_pose.translation.vector).norm() > 0.1);
}

#[test]
fn routes_stay_clear_of_obstacles() {
    let store = Store::generate(&StoreOptions::default(), 11).expect("store");
    let resolution = 0.1;
    for session in [0, 1, 2, 5, 13, 25] {
        let grid = store.occupancy(session, resolution);
        let route = store.route(session, if session == 0 { 1 } else { 2 });
        for pair in route.windows(2) {
            let length = (pair[1] - pair[0]).norm();
            let steps = (length / 0.2).ceil() as usize;
            for k in 0..=steps {
                let p = pair[0] + (pair[1] - pair[0]) * (k as f64 / steps.max(1) as f64);
                for dy in -3..=3 {
                    for dx in -3..=3 {
                        let q =
                            p + nalgebra::Vector2::new(f64::from(dx), f64::from(dy)) * resolution;
                        if let Some(i) = grid.limits.flat_index(&grid.limits.cell_index(&q)) {
                            assert!(
                                !grid.occupied[i],
                                "session {session}: route hits an obstacle at {q:?}"
                            );
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn layout_changes_more_than_half_in_25_sessions() {
    let store = Store::generate(&StoreOptions::default(), 5).expect("store");
    let change = |a: u32, b: u32| {
        let (a, b) = (store.occupancy(a, 0.05), store.occupancy(b, 0.05));
        map_change_rate(&a.surface_grid(), &b.surface_grid(), MAP_CHANGE_TOLERANCE_M).rate
    };
    let rate = change(0, 25);
    assert!(rate > 0.5, "truth change rate {rate}");
    // Day to day the store changes much less, but it does change: the tolerance is below the
    // simulator's smallest move.
    let day = change(0, 1);
    assert!(
        day > 0.0 && day < 0.5 * rate,
        "one day: {day}, 25 days: {rate}"
    );
    assert!(change(3, 3).abs() < f64::EPSILON);
}

#[test]
fn surface_grid_marks_surfaces_occupied_free_space_free_and_interiors_unknown() {
    let store = Store::generate(&StoreOptions::default(), 5).expect("store");
    let occupancy = store.occupancy(0, 0.1);
    let surface = occupancy.surface();
    let grid = occupancy.surface_grid();
    let (mut surfaces, mut interiors) = (0, 0);
    for (i, value) in grid.values().iter().enumerate() {
        let p = value_to_probability(*value);
        if surface[i] {
            surfaces += 1;
            assert!(p > OCCUPIED_PROBABILITY);
        } else if occupancy.occupied[i] {
            interiors += 1;
            assert_eq!(*value, UNKNOWN_VALUE);
        } else {
            assert!(*value != UNKNOWN_VALUE && p < OCCUPIED_PROBABILITY);
        }
    }
    assert!(surfaces > 0 && interiors > 0, "{surfaces} {interiors}");
}

#[test]
fn truth_heading_follows_the_route() {
    let store = Store::generate(&StoreOptions::default(), 7).expect("store");
    let s = store.session(0, &short()).expect("session");
    // 20 s at 1 m/s with turns in place: between 10 and 20 m driven.
    assert!(
        s.distance_m > 10.0 && s.distance_m < 20.5,
        "{}",
        s.distance_m
    );
    let (_, first) = s.ground_truth[0];
    assert!(first.theta().is_finite());
}

#[test]
fn options_are_validated() {
    assert!(StoreOptions::default().validate().is_ok());
    assert!(SessionOptions::default().validate().is_ok());
    let bad = StoreOptions {
        aisle_width: 0.5,
        ..StoreOptions::default()
    };
    assert!(Store::generate(&bad, 1).is_err());
    let bad = SessionOptions {
        lidar_dropout: 1.5,
        ..SessionOptions::default()
    };
    assert!(bad.validate().is_err());
}
