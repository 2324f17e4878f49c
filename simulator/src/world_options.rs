//! Which simulated world to lay out: the realistic supermarket or the adversarial aisles.

use serde::{Deserialize, Serialize};

use super::{AislesOptions, SimulationError, StoreOptions};

/// The world a [`Store`](super::Store) is generated from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum WorldOptions {
    /// `--world store`: a supermarket after typical published floor plans (see
    /// [`store_layout`](super::store_layout)). The default.
    Store(StoreOptions),
    /// `--world aisles`: blocks of identical shelf rows, the layout before issue 14 (the adversarial case).
    Aisles(AislesOptions),
}

impl Default for WorldOptions {
    fn default() -> Self {
        Self::Store(StoreOptions::default())
    }
}

impl WorldOptions {
    /// Checks the options of the chosen world.
    pub fn validate(&self) -> Result<(), SimulationError> {
        match self {
            Self::Store(o) => o.validate(),
            Self::Aisles(o) => o.validate(),
        }
    }

    /// The world's name on the command line (`store`, `aisles`).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Store(_) => "store",
            Self::Aisles(_) => "aisles",
        }
    }

    /// Inner width (x) of the floor, metres.
    pub fn width(&self) -> f64 {
        match self {
            Self::Store(o) => o.width,
            Self::Aisles(o) => o.width,
        }
    }

    /// Inner depth (y) of the floor, metres.
    pub fn depth(&self) -> f64 {
        match self {
            Self::Store(o) => o.depth,
            Self::Aisles(o) => o.depth,
        }
    }

    /// Thickness of the outer walls, metres.
    pub fn wall_thickness(&self) -> f64 {
        match self {
            Self::Store(o) => o.wall_thickness,
            Self::Aisles(o) => o.wall_thickness,
        }
    }

    /// Probability that a movable item changes state from one session to the next.
    pub fn change_probability(&self) -> f64 {
        match self {
            Self::Store(o) => o.change_probability,
            Self::Aisles(o) => o.change_probability,
        }
    }

    /// (pedestrians, carts) walking during a session.
    pub fn walkers(&self) -> (usize, usize) {
        match self {
            Self::Store(o) => (o.pedestrians, o.carts),
            Self::Aisles(o) => (o.pedestrians, o.carts),
        }
    }
}

impl From<StoreOptions> for WorldOptions {
    fn from(options: StoreOptions) -> Self {
        Self::Store(options)
    }
}

impl From<&StoreOptions> for WorldOptions {
    fn from(options: &StoreOptions) -> Self {
        Self::Store(options.clone())
    }
}

impl From<AislesOptions> for WorldOptions {
    fn from(options: AislesOptions) -> Self {
        Self::Aisles(options)
    }
}

impl From<&AislesOptions> for WorldOptions {
    fn from(options: &AislesOptions) -> Self {
        Self::Aisles(options.clone())
    }
}

impl From<&WorldOptions> for WorldOptions {
    fn from(options: &WorldOptions) -> Self {
        options.clone()
    }
}
