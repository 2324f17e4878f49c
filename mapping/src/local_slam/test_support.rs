//! The room LLO's tests drive through.

// The simulator links this crate's non-test build: only its nalgebra-typed ray caster is used here.
use simulator::{Aabb, RayCaster};

/// An irregular 12 m × 9 m room with pillars and a recess, so that no rotation of a scan fits as well as
/// the true one.
pub(crate) fn room() -> RayCaster {
    let wall = 0.2;
    RayCaster::new(
        vec![
            Aabb::new(0.0, 0.0, 12.0, wall),
            Aabb::new(0.0, 9.0 - wall, 7.0, 9.0),
            Aabb::new(7.0, 7.5, 12.0, 7.5 + wall),
            Aabb::new(7.0, 7.5, 7.0 + wall, 9.0),
            Aabb::new(0.0, 0.0, wall, 9.0),
            Aabb::new(12.0 - wall, 0.0, 12.0, 7.7),
            Aabb::new(3.0, 2.0, 3.6, 2.6),
            Aabb::new(8.5, 4.0, 9.5, 4.4),
            Aabb::new(5.0, 6.5, 5.3, 7.6),
            Aabb::new(2.0, 6.0, 2.4, 6.4),
        ],
        1.0,
    )
}
