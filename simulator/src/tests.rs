use mapping::geometry::Rigid2Ext as _;
use mapping::grid::{UNKNOWN_VALUE, value_to_probability};
use mapping::lifelong::{MAP_CHANGE_TOLERANCE_M, OCCUPIED_PROBABILITY, map_change_rate};
use mapping::sensor::SensorEvent;
use nalgebra::{Point2, Vector2};

use super::*;

fn short() -> SessionOptions {
    SessionOptions {
        max_duration_s: 20.0,
        mapping_max_duration_s: 20.0,
        ..SessionOptions::default()
    }
}

/// Both worlds at their default (benchmark) size.
fn worlds() -> [WorldOptions; 2] {
    [
        StoreOptions::default().into(),
        AislesOptions::default().into(),
    ]
}

/// Both worlds at the fleet demo's size (48 × 30 m), for the brute-force checks.
fn small_worlds() -> [WorldOptions; 2] {
    [
        StoreOptions {
            width: 48.0,
            depth: 30.0,
            banks: 1,
            ..StoreOptions::default()
        }
        .into(),
        AislesOptions {
            width: 48.0,
            depth: 30.0,
            blocks: 2,
            ..AislesOptions::default()
        }
        .into(),
    ]
}

#[test]
fn default_worlds_are_supermarkets() {
    for world in worlds() {
        let store = Store::generate(&world, 7).expect("store");
        assert!(store.area_m2() >= 10_000.0);
        let [goods, pallets, displays, _, _] = store.items_present(0);
        assert!(goods > 1000, "{}: {goods} goods modules", world.name());
        assert!(pallets > 0 && displays > 0, "{}", world.name());
        assert!(store.aisles().len() >= 40, "{}", world.name());
    }
    // The store's structure has what a supermarket has; the aisles world only shelves and pillars.
    let store = Store::generate(StoreOptions::default(), 7).expect("store");
    let count = |f: &dyn Fn(&Aabb) -> bool| store.structure().iter().filter(|b| f(b)).count();
    let size = |b: &Aabb| (b.max.x - b.min.x, b.max.y - b.min.y);
    let checkstands = count(&|b| {
        let (w, h) = size(b);
        (w - store_layout::CHECKSTAND_WIDTH_M).abs() < 1e-9
            && (h - store_layout::CHECKSTAND_LENGTH_M).abs() < 1e-9
    });
    let columns = count(&|b| {
        let (w, h) = size(b);
        (w - store_layout::COLUMN_SIZE_M).abs() < 1e-9 && (h - w).abs() < 1e-9
    });
    assert!(checkstands >= 10, "{checkstands} checkstands");
    assert!(columns >= 20, "{columns} columns");
    let [_, _, _, _, cart_rows] = store.items_present(0);
    assert!(cart_rows > 0);
}

#[test]
fn worlds_are_deterministic_per_seed() {
    for world in worlds() {
        let a = Store::generate(&world, 3).expect("store");
        let b = Store::generate(&world, 3).expect("store");
        let c = Store::generate(&world, 4).expect("store");
        for day in [0, 1, 7] {
            assert_eq!(a.obstacles(day), b.obstacles(day));
            assert_ne!(a.obstacles(day), c.obstacles(day));
        }
        assert_eq!(a.cleaning_route(5), b.cleaning_route(5));
    }
}

#[test]
fn sessions_are_deterministic_and_well_formed() {
    for world in worlds() {
        let store = Store::generate(&world, 7).expect("store");
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
        assert!(finite > 600, "{}: {finite} finite ranges", world.name());
        // Different sessions start on different days at different places.
        let c = store.session(4, &short()).expect("session");
        assert!(c.events[0].time() > a.events[a.events.len() - 1].time());
        assert!((c.start_pose.translation.vector - a.start_pose.translation.vector).norm() > 0.1);
    }
}

#[test]
fn routes_stay_clear_of_obstacles() {
    for world in worlds() {
        let store = Store::generate(&world, 11).expect("store");
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
                            let q = p + Vector2::new(f64::from(dx), f64::from(dy)) * resolution;
                            if let Some(i) = grid.limits.flat_index(&grid.limits.cell_index(&q)) {
                                assert!(
                                    !grid.occupied[i],
                                    "{} session {session}: route hits an obstacle at {q:?}",
                                    world.name()
                                );
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Distance from `p` to the polyline `route`.
fn distance_to_route(p: &Point2<f64>, route: &[Point2<f64>]) -> f64 {
    route
        .windows(2)
        .map(|s| {
            let d = s[1] - s[0];
            let t = ((p - s[0]).dot(&d) / d.norm_squared().max(1e-12)).clamp(0.0, 1.0);
            (p - (s[0] + d * t)).norm()
        })
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn the_mapping_route_covers_every_aisle_every_shelf_and_the_perimeter() {
    for world in worlds() {
        let store = Store::generate(&world, 2).expect("store");
        let route = store.cleaning_route(0);
        // Every aisle end to end.
        for (a, b) in store.aisles() {
            let steps = ((b - a).norm() / 0.5).ceil() as usize;
            for k in 0..=steps {
                let p = a + (b - a) * (k as f64 / steps as f64);
                let d = distance_to_route(&p, &route);
                assert!(d < 1e-6, "{}: aisle point {p:?} {d} m off", world.name());
            }
        }
        // Every goods section is passed within half an aisle plus the goods zone (the aisles world's
        // outer rows face its 4 m perimeter aisle).
        let bound = if world.name() == "store" { 1.7 } else { 2.2 };
        for item in store.movable_items() {
            if item.kind != ItemKind::Goods {
                continue;
            }
            let Some(Some(b)) = item.variants.last() else {
                continue;
            };
            let centre = Point2::from((b.min.coords + b.max.coords) / 2.0);
            let d = distance_to_route(&centre, &route);
            assert!(
                d < bound,
                "{}: goods at {centre:?} {d:.2} m off",
                world.name()
            );
        }
        // The perimeter: the route runs within 5 m of all four walls (the back aisle runs in front of
        // the 3.2 m service zone).
        let (w, d) = (world.width(), world.depth());
        let reach =
            |f: &dyn Fn(&Point2<f64>) -> f64| route.iter().map(f).fold(f64::INFINITY, f64::min);
        assert!(reach(&|p| p.x) < 5.0);
        assert!(reach(&|p| w - p.x) < 5.0);
        assert!(reach(&|p| p.y) < 5.0);
        assert!(reach(&|p| d - p.y) < 5.0);
        // It is a loop: the mapping run ends where it started.
        assert!((route[0] - route[route.len() - 1]).norm() < 1e-9 || world.name() == "aisles");
    }
}

#[test]
fn static_structure_never_changes() {
    for world in small_worlds() {
        let store = Store::generate(&world, 9).expect("store");
        let structure = store.structure().to_vec();
        let resolution = 0.1;
        let day_zero = store.occupancy(0, resolution);
        for day in 0..=25 {
            let obstacles = store.obstacles(day);
            assert_eq!(&obstacles[..structure.len()], structure.as_slice());
            let occupancy = store.occupancy(day, resolution);
            assert_eq!(occupancy.limits, day_zero.limits);
        }
        // Every cell inside the structure is occupied on every day.
        let limits = &day_zero.limits;
        for day in [0, 5, 25] {
            let occupancy = store.occupancy(day, resolution);
            for b in &structure {
                let (lo, hi) = (limits.cell_index(&b.min), limits.cell_index(&b.max));
                for y in lo.y..=hi.y {
                    for x in lo.x..=hi.x {
                        let cell = mapping::grid::CellIndex::new(x, y);
                        if b.contains(&limits.cell_center(&cell))
                            && let Some(i) = limits.flat_index(&cell)
                        {
                            assert!(occupancy.occupied[i]);
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn goods_change_at_the_configured_rate_in_tenth_of_a_metre_steps() {
    for world in worlds() {
        let store = Store::generate(&world, 4).expect("store");
        let p = world.change_probability();
        let items = store.movable_items();
        let (mut changed, mut total) = (0usize, 0usize);
        let mut before = store.states(0);
        for day in 1..=10 {
            let after = store.states(day);
            for (i, item) in items.iter().enumerate() {
                if item.kind == ItemKind::Goods {
                    total += 1;
                    changed += usize::from(before[i] != after[i]);
                }
            }
            before = after;
        }
        let rate = changed as f64 / total as f64;
        // Binomial: thousands of goods sections × 10 days, so the rate is within a few 0.001 of p.
        assert!(
            (rate - p).abs() < 0.01,
            "{}: goods rate {rate} vs {p}",
            world.name()
        );
        for item in items.iter().filter(|i| i.kind == ItemKind::Goods) {
            for b in item.variants.iter().flatten() {
                let depth = (b.max.x - b.min.x).min(b.max.y - b.min.y);
                let steps = depth / store_layout::GOODS_STEP_M;
                assert!(
                    (steps - steps.round()).abs() < 1e-6 && depth <= 0.3 + 1e-9,
                    "{}: goods {depth} m deep",
                    world.name()
                );
            }
        }
    }
}

#[test]
fn occupancy_matches_the_geometry_cell_by_cell() {
    for world in small_worlds() {
        let store = Store::generate(&world, 6).expect("store");
        for day in [0, 3] {
            let resolution = 0.2;
            let occupancy = store.occupancy(day, resolution);
            let obstacles = store.obstacles(day);
            let limits = &occupancy.limits;
            let mut occupied = 0;
            for y in 0..limits.height {
                for x in 0..limits.width {
                    let cell = mapping::grid::CellIndex::new(x, y);
                    let centre = limits.cell_center(&cell);
                    let truth = obstacles.iter().any(|b| b.contains(&centre));
                    let i = limits.flat_index(&cell).expect("inside");
                    assert_eq!(
                        occupancy.occupied[i],
                        truth,
                        "{} at {centre:?}",
                        world.name()
                    );
                    occupied += usize::from(truth);
                }
            }
            assert!(occupied > 1000, "{}: {occupied}", world.name());
        }
    }
}

/// Structure-only scans of `caster` from `origin` facing `heading`, every 6th beam of the simulated
/// LiDAR (270°, 25 m; misses read 25 m).
fn structure_scan(caster: &RayCaster, origin: &Point2<f64>, heading: f64) -> Vec<f64> {
    let options = SessionOptions::default();
    let beams = (options.lidar_fov / options.lidar_angle_increment).floor() as usize + 1;
    (0..beams)
        .step_by(6)
        .map(|k| {
            let a = heading - 0.5 * options.lidar_fov + k as f64 * options.lidar_angle_increment;
            caster
                .cast(
                    origin,
                    &Vector2::new(a.cos(), a.sin()),
                    options.lidar_range_max,
                )
                .unwrap_or(options.lidar_range_max)
                .min(options.lidar_range_max)
        })
        .collect()
}

/// Beams (of [`structure_scan`]) that disagree by more than this are evidence against a place, m (the
/// relocalization window).
const DISAGREE_M: f64 = 0.3;

/// The scans a robot takes leaving aisle `(a, b)` at either end: 2 m inside the aisle on its centre line,
/// facing out, shifted by `shift` metres along the aisle.
fn leaving_scans(
    caster: &RayCaster,
    a: &Point2<f64>,
    b: &Point2<f64>,
    shift: f64,
) -> [Vec<f64>; 2] {
    let along = (b - a).normalize();
    let heading = along.y.atan2(along.x);
    [
        structure_scan(
            caster,
            &(a + along * (2.0 + shift)),
            heading + std::f64::consts::PI,
        ),
        structure_scan(caster, &(b - along * (2.0 + shift)), heading),
    ]
}

/// For every aisle end, how unlike its best look-alike at the end of any other aisle it looks: the
/// fraction of beams of the structure-only scan leaving the aisle there that disagree by more than
/// [`DISAGREE_M`] with the closest scan leaving another aisle (either end, shifted up to ±1 m along it).
fn look_alike_distances(store: &Store) -> Vec<f64> {
    let caster = RayCaster::new(store.structure().to_vec(), 1.0);
    let aisles = store.aisles();
    let candidates: Vec<Vec<Vec<f64>>> = aisles
        .iter()
        .map(|(a, b)| {
            (-4..=4)
                .flat_map(|k| leaving_scans(&caster, a, b, 0.25 * f64::from(k)))
                .collect()
        })
        .collect();
    aisles
        .iter()
        .enumerate()
        .flat_map(|(i, (a, b))| {
            let candidates = &candidates;
            leaving_scans(&caster, a, b, 0.0).map(move |reference| {
                candidates
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .flat_map(|(_, scans)| scans.iter())
                    .map(|scan| {
                        let disagree = scan
                            .iter()
                            .zip(&reference)
                            .filter(|(r, s)| (*r - *s).abs() > DISAGREE_M)
                            .count();
                        disagree as f64 / reference.len() as f64
                    })
                    .fold(f64::INFINITY, f64::min)
            })
        })
        .collect()
}

#[test]
fn aisles_are_told_apart_in_the_store_but_not_in_the_aisles_world() {
    let fraction_apart = |world: WorldOptions, threshold: f64| {
        let store = Store::generate(&world, 1).expect("store");
        let mut distances = look_alike_distances(&store);
        distances.sort_by(f64::total_cmp);
        let apart = distances.iter().filter(|d| **d > threshold).count();
        eprintln!(
            "{}: {} aisle ends, beams disagreeing with the best look-alike: min {:.3} median {:.3} max {:.3}, {apart} above {threshold}",
            world.name(),
            distances.len(),
            distances[0],
            distances[distances.len() / 2],
            distances[distances.len() - 1]
        );
        apart as f64 / distances.len() as f64
    };
    let store = fraction_apart(StoreOptions::default().into(), 0.05);
    let aisles = fraction_apart(AislesOptions::default().into(), 0.05);
    assert!(store > 0.9, "store: {store}");
    assert!(aisles < 0.5, "aisles: {aisles}");
}

#[test]
fn layout_changes_more_than_half_in_25_sessions() {
    let store = Store::generate(AislesOptions::default(), 5).expect("store");
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
fn the_store_changes_day_to_day_but_keeps_its_structure() {
    let store = Store::generate(StoreOptions::default(), 5).expect("store");
    let change = |a: u32, b: u32| {
        let (a, b) = (store.occupancy(a, 0.05), store.occupancy(b, 0.05));
        map_change_rate(&a.surface_grid(), &b.surface_grid(), MAP_CHANGE_TOLERANCE_M).rate
    };
    let (day, month) = (change(0, 1), change(0, 25));
    eprintln!("store: truth change rate day 1 {day:.3}, day 25 {month:.3}");
    assert!(
        day > 0.0 && day < 0.5 * month,
        "one day: {day}, 25 days: {month}"
    );
    assert!(month > 0.3, "25 days: {month}");
    assert!(change(3, 3).abs() < f64::EPSILON);
}

#[test]
fn surface_grid_marks_surfaces_occupied_free_space_free_and_interiors_unknown() {
    let store = Store::generate(StoreOptions::default(), 5).expect("store");
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
    let store = Store::generate(StoreOptions::default(), 7).expect("store");
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
    for world in worlds().into_iter().chain(small_worlds()) {
        assert!(world.validate().is_ok(), "{world:?}");
    }
    assert!(SessionOptions::default().validate().is_ok());
    let bad = AislesOptions {
        aisle_width: 0.5,
        ..AislesOptions::default()
    };
    assert!(Store::generate(&bad, 1).is_err());
    for bad in [
        StoreOptions {
            aisle_width: 1.0,
            ..StoreOptions::default()
        },
        StoreOptions {
            width: 30.0,
            ..StoreOptions::default()
        },
        StoreOptions {
            depth: 20.0,
            ..StoreOptions::default()
        },
        StoreOptions {
            banks: 0,
            ..StoreOptions::default()
        },
        StoreOptions {
            change_probability: 1.5,
            ..StoreOptions::default()
        },
    ] {
        assert!(Store::generate(&bad, 1).is_err(), "{bad:?}");
    }
    let bad = SessionOptions {
        lidar_dropout: 1.5,
        ..SessionOptions::default()
    };
    assert!(bad.validate().is_err());
}

#[test]
fn with_dock_starts_a_session_cleans_on_from_where_the_last_one_ended_unless_carried() {
    let options = SessionOptions {
        dock_starts: true,
        ..short()
    };
    for world in small_worlds() {
        let store = Store::generate(world, 3).unwrap();
        let sessions: Vec<SimulatedSession> = (0..=8)
            .map(|k| store.session(k, &options).unwrap())
            .collect();
        let mut continued = 0;
        for pair in sessions.windows(2) {
            let (before, after) = (&pair[0], &pair[1]);
            let end = before.ground_truth.last().unwrap().1;
            let gap = (after.start_pose.translation.vector - end.translation.vector).norm();
            if after.starts_at_previous_end {
                continued += 1;
                // The last scan is at most one scan period (1 m/s × 1/15 s) before the end.
                assert!(gap < 0.1, "session {}: {gap} m from the end", after.index);
            }
        }
        // Session 1 starts elsewhere after the mapping run; of 7 later ones about 1 in 5 is carried.
        assert!(!sessions[1].starts_at_previous_end);
        assert!((4..=7).contains(&continued), "{continued} of 7 continued");
        // Without the option no session continues.
        let plain = store.session(5, &short()).unwrap();
        assert!(!plain.starts_at_previous_end);
    }
}
