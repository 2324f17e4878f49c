//! Options of the lifelong map: trimming, policy and sparsification cadence.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::global_slam::{GlobalSlamOptions, GlobalSlamOptionsError};
use crate::sparsification::{SparsificationOptions, SparsificationOptionsError};

/// What happens to stale submaps when a session ends (the issue's `--policy`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TrimPolicy {
    /// Trim covered stale submaps and replace them (and their nodes) by the Chow–Liu tree over their
    /// Markov blanket: the paper's method.
    #[default]
    Clt,
    /// Trim covered stale submaps and drop them, their nodes and every constraint touching them, replacing
    /// nothing (Cartographer's trimmer).
    Delete,
    /// Never trim: the graph grows with every session.
    Keep,
    /// The first session's map is never updated (held fixed); later sessions only localize against it
    /// and their nodes and submaps are dropped when they end.
    Frozen,
}

impl TrimPolicy {
    /// Every policy, in declaration order.
    pub const ALL: [Self; 4] = [Self::Clt, Self::Delete, Self::Keep, Self::Frozen];

    /// The lowercase name used in configuration files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Self::Clt => "clt",
            Self::Delete => "delete",
            Self::Keep => "keep",
            Self::Frozen => "frozen",
        }
    }
}

impl fmt::Display for TrimPolicy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// An unknown [`TrimPolicy`] name.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[error("unknown policy {0:?} (expected clt, delete, keep or frozen)")]
pub struct ParseTrimPolicyError(pub String);

impl FromStr for TrimPolicy {
    type Err = ParseTrimPolicyError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| ParseTrimPolicyError(s.to_owned()))
    }
}

/// When a stale submap counts as superseded by fresher ones.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SubmapTrimmerOptions {
    /// A stale submap is trimmed when more than this fraction of its counted cells is covered by at least
    /// [`Self::min_fresher_submaps`] fresher submaps. Unitless, in `[0, 1]`. Default 0.6.
    pub min_covered_fraction: f64,
    /// `K`: how many fresher submaps (of later sessions) must know a cell for it to count as covered.
    /// Count, ≥ 1. Default 1 (as Cartographer's `fresh_submaps_count`).
    pub min_fresher_submaps: usize,
    /// No trimming at the end of a session that finished fewer submaps than this. Count. Default 5 (as
    /// Cartographer's `min_added_submaps_count`).
    pub min_fresh_submaps_before_trimming: usize,
    /// Only every `cell_stride`-th cell along each grid axis is tested (1 = every cell). Count, ≥ 1.
    /// Default 2 (a quarter of the cells, at 5 cm still one test per 10 cm).
    pub cell_stride: usize,
    /// Count only the stale submap's occupied cells (probability above 0.5) instead of all its known
    /// cells. Default false.
    pub count_occupied_only: bool,
}

impl Default for SubmapTrimmerOptions {
    fn default() -> Self {
        Self {
            min_covered_fraction: 0.6,
            min_fresher_submaps: 1,
            min_fresh_submaps_before_trimming: 5,
            cell_stride: 2,
            count_occupied_only: false,
        }
    }
}

/// Invalid [`LifelongOptions`].
#[derive(Debug, Error, PartialEq)]
pub enum LifelongOptionsError {
    /// The global SLAM options are invalid.
    #[error(transparent)]
    Global(#[from] GlobalSlamOptionsError),
    /// The sparsification options are invalid.
    #[error(transparent)]
    Sparsification(#[from] SparsificationOptionsError),
    /// Another field is out of range.
    #[error("{field} {reason}")]
    OutOfRange {
        /// The field.
        field: &'static str,
        /// What it must satisfy.
        reason: &'static str,
    },
}

impl SubmapTrimmerOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), LifelongOptionsError> {
        if !(0.0..=1.0).contains(&self.min_covered_fraction) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "min_covered_fraction",
                reason: "must be in [0, 1]",
            });
        }
        if self.min_fresher_submaps == 0 {
            return Err(LifelongOptionsError::OutOfRange {
                field: "min_fresher_submaps",
                reason: "must be at least 1",
            });
        }
        if self.cell_stride == 0 {
            return Err(LifelongOptionsError::OutOfRange {
                field: "cell_stride",
                reason: "must be at least 1",
            });
        }
        Ok(())
    }
}

/// Everything a [`super::LifelongMap`] is configured with.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LifelongOptions {
    /// The pose graph, GLM and optimizer of the map (`GlobalSlamOptions::default()`, whose
    /// `unanchored_search_every_n_nodes` is 0: an unplaced session is placed by retrying relocalization
    /// over the whole map, not by a full search of every submap from one scan).
    pub global: GlobalSlamOptions,
    /// The whole-map search of a session's start ([`super::StartSearch`]).
    pub relocalization: super::RelocalizationOptions,
    /// Hold-back, retries and probation of a session's start ([`super::SessionStart`]): every shell
    /// (offline commands, fleet agent, server) starts sessions with these.
    pub session_start: super::SessionStartOptions,
    /// When stale submaps are trimmed.
    pub trimmer: SubmapTrimmerOptions,
    /// What trimming does. Default `clt`.
    pub policy: TrimPolicy,
    /// Optimize the graph again once this many sparsifications have accumulated, after the batch of trims
    /// of the session end that reached it (count; 0 = never: the session's final optimization, just before
    /// its trims, is the optimum every tree is built at, and the next session's optimizations take up what
    /// the trees approximate). Default 0 (the paper's is 5).
    /// Why: `docs/TUNING.md#ll-optimize-every-n-sparsifications`.
    pub optimize_every_n_sparsifications: usize,
    /// Iteration cap of those optimizations (count, ≥ 1). Default 50 (the paper's).
    pub sparsification_max_iterations: usize,
    /// How the Chow–Liu tree is built.
    pub sparsification: SparsificationOptions,
    /// Report, for every trimmed submap, the KL divergence of the whole remaining graph's posterior
    /// against the exact marginal (dense, `O(n³)`: small graphs and tests only) instead of the blanket's.
    /// With it, `delete` reports its divergence too. Default false.
    pub whole_graph_kld: bool,
}

impl Default for LifelongOptions {
    fn default() -> Self {
        Self {
            global: GlobalSlamOptions::default(),
            relocalization: super::RelocalizationOptions::default(),
            session_start: super::SessionStartOptions::default(),
            trimmer: SubmapTrimmerOptions::default(),
            policy: TrimPolicy::default(),
            optimize_every_n_sparsifications: 0,
            sparsification_max_iterations: 50,
            sparsification: SparsificationOptions::default(),
            whole_graph_kld: false,
        }
    }
}

impl LifelongOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), LifelongOptionsError> {
        self.global.validate()?;
        self.relocalization.validate()?;
        self.session_start.validate()?;
        self.trimmer.validate()?;
        self.sparsification.validate()?;
        if self.sparsification_max_iterations == 0 {
            return Err(LifelongOptionsError::OutOfRange {
                field: "sparsification_max_iterations",
                reason: "must be at least 1",
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn setting_one_field_of_the_global_section_keeps_every_other_default() {
        let options: LifelongOptions =
            toml::from_str("[global]\noptimize_every_n_nodes = 45\n").unwrap();
        assert_eq!(options.global.optimize_every_n_nodes, 45);
        assert_eq!(
            options.global.unanchored_search_every_n_nodes, 0,
            "sessions are placed by SessionStart, never by a single scan"
        );
        assert_eq!(
            LifelongOptions {
                global: GlobalSlamOptions {
                    optimize_every_n_nodes: LifelongOptions::default()
                        .global
                        .optimize_every_n_nodes,
                    ..options.global
                },
                ..options
            },
            LifelongOptions::default()
        );
    }

    #[test]
    fn defaults_are_valid_and_bad_values_are_named() {
        assert_eq!(LifelongOptions::default().validate(), Ok(()));
        let bad = LifelongOptions {
            trimmer: SubmapTrimmerOptions {
                min_fresher_submaps: 0,
                ..SubmapTrimmerOptions::default()
            },
            ..LifelongOptions::default()
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("min_fresher_submaps")
        );
        let bad = LifelongOptions {
            sparsification_max_iterations: 0,
            ..LifelongOptions::default()
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("sparsification_max_iterations")
        );
    }

    #[test]
    fn policy_names_round_trip_through_from_str_and_serde() {
        for policy in TrimPolicy::ALL {
            assert_eq!(policy.name().parse::<TrimPolicy>(), Ok(policy));
            assert_eq!(
                serde_json::to_string(&policy).unwrap(),
                format!("\"{policy}\"")
            );
        }
        assert!("prune".parse::<TrimPolicy>().is_err());
        let options: LifelongOptions = toml::from_str("policy = \"frozen\"").unwrap();
        assert_eq!(options.policy, TrimPolicy::Frozen);
    }
}
