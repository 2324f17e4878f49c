//! Size and dynamics of the `store` world, the simulated supermarket laid out by
//! [`store_layout`](super::store_layout).

use serde::{Deserialize, Serialize};

use super::SimulationError;
use super::store_layout::{
    CASE_DEPTH_M, CHECKSTAND_LENGTH_M, END_CAP_DEPTH_M, FRONT_CORRIDOR_WIDTH_M, GONDOLA_DEPTH_M,
    GOODS_DEPTH_M, ISLAND_WIDTH_M, MAIN_AISLE_WIDTH_M, MODULE_LENGTH_M, POWER_AISLE_WIDTH_M,
    PRODUCE_LANE_WIDTH_M, PROMO_DEPTH_M, SERVICE_ZONE_DEPTH_M,
};

/// Size and dynamics of the simulated supermarket (`--world store`). All lengths in metres. The fixture
/// dimensions (gondola depth, case depth, checkstands, column grid, ...) are the documented constants of
/// [`store_layout`](super::store_layout); these options choose the floor and how busy and changeable it
/// is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StoreOptions {
    /// Inner width (x, along the front wall) of the store. Default 120 m.
    pub width: f64,
    /// Inner depth (y, front wall to back wall) of the store. Default 90 m (10,800 m², the area the
    /// lifelong benchmarks have always used).
    pub depth: f64,
    /// Thickness of the outer walls. Default 0.3 m.
    pub wall_thickness: f64,
    /// Gondola banks from front to back, separated by cross aisles. Default 2.
    pub banks: usize,
    /// Width of the aisles between gondolas (between the goods fronts). Default 2.0 m (typical
    /// 1.8–2.4 m).
    pub aisle_width: f64,
    /// Probability that a goods module, pallet, display, promotion, cart row or door changes state from
    /// one session to the next. Default 0.12, as in the `aisles` world.
    pub change_probability: f64,
    /// Half-pallet slots against gondola faces in the aisles; each is occupied or not per session.
    /// Default 40.
    pub pallet_slots: usize,
    /// Impulse-display slots along the power aisle in front of the checkouts. Default 16.
    pub display_slots: usize,
    /// Pedestrians walking during a session. Default 12.
    pub pedestrians: usize,
    /// Shopping carts pushed about during a session. Default 6.
    pub carts: usize,
}

impl Default for StoreOptions {
    fn default() -> Self {
        Self {
            width: 120.0,
            depth: 90.0,
            wall_thickness: 0.3,
            banks: 2,
            aisle_width: 2.0,
            change_probability: 0.12,
            pallet_slots: 40,
            display_slots: 16,
            pedestrians: 12,
            carts: 6,
        }
    }
}

impl StoreOptions {
    /// Checks that lengths are positive, the aisle width is one a robot and shoppers use, and the floor
    /// has room for the front end, the perimeter, at least two gondolas and every bank.
    pub fn validate(&self) -> Result<(), SimulationError> {
        for (field, v) in [
            ("width", self.width),
            ("depth", self.depth),
            ("wall_thickness", self.wall_thickness),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(SimulationError::InvalidOption {
                    field,
                    reason: "must be finite and > 0".into(),
                });
            }
        }
        if !(1.6..=3.0).contains(&self.aisle_width) {
            return Err(SimulationError::InvalidOption {
                field: "aisle_width",
                reason: "must be in [1.6, 3.0] m (a robot and a shopper pass each other)".into(),
            });
        }
        if !(0.0..=1.0).contains(&self.change_probability) {
            return Err(SimulationError::InvalidOption {
                field: "change_probability",
                reason: "must be in [0, 1]".into(),
            });
        }
        if self.banks == 0 {
            return Err(SimulationError::InvalidOption {
                field: "banks",
                reason: "must be at least 1".into(),
            });
        }
        if self.width < self.min_width() {
            return Err(SimulationError::InvalidOption {
                field: "width",
                reason: format!("must be at least {:.1} m", self.min_width()),
            });
        }
        if self.depth < self.min_depth() {
            return Err(SimulationError::InvalidOption {
                field: "depth",
                reason: format!(
                    "must be at least {:.1} m for {} banks",
                    self.min_depth(),
                    self.banks
                ),
            });
        }
        Ok(())
    }

    /// Distance between neighbouring gondolas' left edges.
    pub fn gondola_pitch(&self) -> f64 {
        GONDOLA_DEPTH_M + self.aisle_width
    }

    /// The narrowest floor: wall cases and a perimeter aisle on each side, eight gondolas, the produce
    /// department, and room along the front for a few checkouts.
    fn min_width(&self) -> f64 {
        2.0 * (CASE_DEPTH_M + MAIN_AISLE_WIDTH_M)
            + 8.0 * self.gondola_pitch()
            + 2.0 * ISLAND_WIDTH_M
            + PRODUCE_LANE_WIDTH_M
            + MAIN_AISLE_WIDTH_M
    }

    /// The shallowest floor: the front end, the back service zone and aisle, and banks with gondola runs
    /// of at least four modules between their end caps.
    fn min_depth(&self) -> f64 {
        let end = END_CAP_DEPTH_M + GOODS_DEPTH_M + PROMO_DEPTH_M;
        let bank = 2.0 * end + 4.0 * MODULE_LENGTH_M;
        FRONT_CORRIDOR_WIDTH_M
            + CHECKSTAND_LENGTH_M
            + POWER_AISLE_WIDTH_M
            + SERVICE_ZONE_DEPTH_M
            + MAIN_AISLE_WIDTH_M
            + self.banks as f64 * bank
            + (self.banks - 1) as f64 * MAIN_AISLE_WIDTH_M
    }
}
