//! The simulated worlds a shell can build by name (`--world`): `evermap-demo`'s commands and the
//! session-start example. With the feature `clap` it is a `clap::ValueEnum`.

use crate::{AislesOptions, StoreOptions, WorldOptions};

/// The simulated worlds, by name.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum World {
    /// A supermarket after typical floor plans: checkouts and entrance at the front, cases along the
    /// walls, service counters, produce islands, gondola runs of different lengths with end caps,
    /// columns on a grid (10,800 m²).
    #[default]
    Store,
    /// The adversarial store: 3 blocks of 21 identical shelf rows, pillars at some row ends (10,800 m²).
    Aisles,
}

impl World {
    /// The world at its default (benchmark) size.
    pub fn options(self) -> WorldOptions {
        match self {
            Self::Store => StoreOptions::default().into(),
            Self::Aisles => AislesOptions::default().into(),
        }
    }

    /// The world at the fleet demo's size, about a quarter of the benchmark's floor area (48 × 30 m).
    pub fn demo_options(self) -> WorldOptions {
        match self {
            Self::Store => StoreOptions {
                width: 48.0,
                depth: 30.0,
                banks: 1,
                pallet_slots: 10,
                display_slots: 6,
                pedestrians: 4,
                carts: 2,
                ..StoreOptions::default()
            }
            .into(),
            Self::Aisles => AislesOptions {
                width: 48.0,
                depth: 30.0,
                blocks: 2,
                pallet_slots: 14,
                display_slots: 10,
                doors: 3,
                pedestrians: 4,
                carts: 2,
                ..AislesOptions::default()
            }
            .into(),
        }
    }

    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Self::Store => "store",
            Self::Aisles => "aisles",
        }
    }
}
