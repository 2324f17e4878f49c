//! The layout and change schedule of the `aisles` world: the adversarial store of identical shelf rows.

use serde::{Deserialize, Serialize};

use super::SimulationError;

/// Layout and dynamics of the `aisles` world (`--world aisles`): the store the simulator modelled until
/// issue 14, kept unchanged as the adversarial case. All lengths in metres.
///
/// The floor is `width × depth` inside the outer walls. Shelf rows run along x in `blocks` blocks separated
/// by cross aisles; a perimeter aisle runs along the walls. A shelf row is a fixed frame (`frame_depth`)
/// with a goods zone of `goods_depth` on each face, filled module by module with goods that protrude by a
/// varying amount or are absent, so what the LiDAR sees of a shelf changes from day to day while the frame
/// behind stays put.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AislesOptions {
    /// Inner width (x) of the store. Default 120 m.
    pub width: f64,
    /// Inner depth (y) of the store. Default 90 m (10,800 m² with the default width).
    pub depth: f64,
    /// Thickness of the outer walls. Default 0.3 m.
    pub wall_thickness: f64,
    /// Number of shelf blocks along x. Default 3.
    pub blocks: usize,
    /// Width of the cross aisles between blocks and of the perimeter aisle. Default 4 m.
    pub cross_aisle_width: f64,
    /// Width of the aisles between shelf rows (between goods zones). Default 2.6 m.
    pub aisle_width: f64,
    /// Depth of a shelf row's fixed frame. Default 0.8 m.
    pub frame_depth: f64,
    /// Depth of the goods zone on each face of a shelf row. Default 0.3 m.
    pub goods_depth: f64,
    /// Length of one shelf module (goods change module by module). Default 1.25 m.
    pub module_length: f64,
    /// Fraction of shelf rows with a fixed pillar at each end. Default 0.25.
    pub pillar_fraction: f64,
    /// Probability that a goods module, pallet, display or door changes state from one session to the
    /// next. Default 0.12 (after 25 sessions about 96 % of them have changed at least once).
    pub change_probability: f64,
    /// Pallet slots (in aisles, against a shelf face); each is occupied or not per session. Default 60.
    pub pallet_slots: usize,
    /// Display / promotion-stand slots (against walls and shelf ends). Default 40.
    pub display_slots: usize,
    /// Doors in the outer walls (open or closed per session). Default 6.
    pub doors: usize,
    /// Pedestrians walking the aisles during a session. Default 12.
    pub pedestrians: usize,
    /// Shopping carts pushed through the aisles during a session. Default 6.
    pub carts: usize,
}

impl Default for AislesOptions {
    fn default() -> Self {
        Self {
            width: 120.0,
            depth: 90.0,
            wall_thickness: 0.3,
            blocks: 3,
            cross_aisle_width: 4.0,
            aisle_width: 2.6,
            frame_depth: 0.8,
            goods_depth: 0.3,
            module_length: 1.25,
            pillar_fraction: 0.25,
            change_probability: 0.12,
            pallet_slots: 60,
            display_slots: 40,
            doors: 6,
            pedestrians: 12,
            carts: 6,
        }
    }
}

impl AislesOptions {
    /// Checks that every length is positive and the layout fits.
    pub fn validate(&self) -> Result<(), SimulationError> {
        let positive = [
            ("width", self.width),
            ("depth", self.depth),
            ("wall_thickness", self.wall_thickness),
            ("cross_aisle_width", self.cross_aisle_width),
            ("aisle_width", self.aisle_width),
            ("frame_depth", self.frame_depth),
            ("goods_depth", self.goods_depth),
            ("module_length", self.module_length),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(SimulationError::InvalidOption {
                    field,
                    reason: "must be finite and > 0".into(),
                });
            }
        }
        for (field, v) in [
            ("pillar_fraction", self.pillar_fraction),
            ("change_probability", self.change_probability),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(SimulationError::InvalidOption {
                    field,
                    reason: "must be in [0, 1]".into(),
                });
            }
        }
        if self.blocks == 0 {
            return Err(SimulationError::InvalidOption {
                field: "blocks",
                reason: "must be at least 1".into(),
            });
        }
        if self.aisle_width < 1.6 || self.cross_aisle_width < 2.4 {
            return Err(SimulationError::InvalidOption {
                field: "aisle_width",
                reason: "aisles must be at least 1.6 m and cross aisles 2.4 m wide for the robot"
                    .into(),
            });
        }
        let block_width =
            (self.width - (self.blocks + 1) as f64 * self.cross_aisle_width) / self.blocks as f64;
        if block_width < 2.0 * self.module_length {
            return Err(SimulationError::InvalidOption {
                field: "width",
                reason: format!("blocks would be {block_width:.2} m wide: too narrow"),
            });
        }
        if self.depth < 2.0 * self.cross_aisle_width + self.row_pitch() {
            return Err(SimulationError::InvalidOption {
                field: "depth",
                reason: "no room for a shelf row".into(),
            });
        }
        Ok(())
    }

    /// Distance between the centre lines of neighbouring shelf rows.
    pub fn row_pitch(&self) -> f64 {
        self.frame_depth + 2.0 * self.goods_depth + self.aisle_width
    }
}
