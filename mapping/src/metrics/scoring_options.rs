//! Options of the lifelong scores ([`score_session`](super::score_session)): what counts as correct, as
//! initialized and as a wrong placement.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::PoseTolerance;

/// Errors of [`ScoringOptions::validate`].
#[derive(Clone, Debug, Error, PartialEq)]
pub enum ScoringOptionsError {
    /// A tolerance or window is negative or not finite.
    #[error("scoring option {field} must be finite and non-negative (got {value})")]
    Invalid {
        /// The field's name.
        field: &'static str,
        /// Its value.
        value: f64,
    },
}

/// What the lifelong scores count (Zhao et al. 2021, §V, and the lifelong issue's targets).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScoringOptions {
    /// A pose is correctly localized within this tolerance of the truth (MRCL, and a correct
    /// initialization). Default 0.3 m and 5° (the paper's).
    pub correct: PoseTolerance,
    /// A session counts as initialized (CRI) when it committed to a correct placement at most this long
    /// after its first scan, seconds. Default 30.
    pub initialization_window_s: f64,
    /// A committed placement farther than this from the truth is a wrong placement (the robot would
    /// navigate in the wrong place). Default 0.5 m and 5°.
    pub wrong_placement: PoseTolerance,
    /// AMS scores each scan by branch and bound within this window around the robot's estimate
    /// ([`MatchScorer`](super::MatchScorer)). Default 0.3 m and 5° (the correct-localization tolerance:
    /// a scan matches the map where the robot believed it was, up to what still counts as correct).
    pub match_window: PoseTolerance,
}

impl ScoringOptions {
    /// The defaults named in the field docs.
    pub const DEFAULT: Self = Self {
        correct: PoseTolerance::CORRECT,
        initialization_window_s: 30.0,
        wrong_placement: PoseTolerance {
            translation_m: 0.5,
            rotation_deg: 5.0,
        },
        match_window: PoseTolerance::CORRECT,
    };

    /// Checks every tolerance and window.
    pub fn validate(&self) -> Result<(), ScoringOptionsError> {
        let fields = [
            ("correct.translation_m", self.correct.translation_m),
            ("correct.rotation_deg", self.correct.rotation_deg),
            ("initialization_window_s", self.initialization_window_s),
            (
                "wrong_placement.translation_m",
                self.wrong_placement.translation_m,
            ),
            (
                "wrong_placement.rotation_deg",
                self.wrong_placement.rotation_deg,
            ),
            (
                "match_window.translation_m",
                self.match_window.translation_m,
            ),
            ("match_window.rotation_deg", self.match_window.rotation_deg),
        ];
        for (field, value) in fields {
            if !(value.is_finite() && value >= 0.0) {
                return Err(ScoringOptionsError::Invalid { field, value });
            }
        }
        Ok(())
    }
}

impl Default for ScoringOptions {
    fn default() -> Self {
        Self::DEFAULT
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_a_negative_window_is_not() {
        assert_eq!(ScoringOptions::default().validate(), Ok(()));
        let bad = ScoringOptions {
            initialization_window_s: -1.0,
            ..ScoringOptions::DEFAULT
        };
        assert!(matches!(
            bad.validate(),
            Err(ScoringOptionsError::Invalid {
                field: "initialization_window_s",
                ..
            })
        ));
        let bad = ScoringOptions {
            correct: PoseTolerance {
                translation_m: f64::NAN,
                rotation_deg: 5.0,
            },
            ..ScoringOptions::DEFAULT
        };
        assert!(bad.validate().is_err());
    }
}
