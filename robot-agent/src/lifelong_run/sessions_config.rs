//! The configuration of a multi-session run: one TOML file, every field optional.

use mapping::lifelong::LifelongOptions;
use mapping::local_slam::LocalTrajectoryBuilderOptions;
use mapping::metrics::ScoringOptions;
use serde::Deserialize;

use super::SessionsError;
use crate::config_file::load_toml;

/// Configuration of a multi-session run; one TOML file, every field optional.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionsConfig {
    /// Local LiDAR odometry (LLO), restarted for every session.
    pub local: LocalTrajectoryBuilderOptions,
    /// The lifelong map (global SLAM, the session start — `[lifelong.relocalization]` and
    /// `[lifelong.session_start]` —, trimming, policy).
    pub lifelong: LifelongOptions,
    /// What the scores count, and the window AMS searches each node's match in.
    pub scoring: ScoringOptions,
}

impl SessionsConfig {
    /// The configuration in the TOML file at `path`, or the defaults without one; `policy` overrides the
    /// file's trimming policy.
    pub fn load(
        path: Option<&std::path::Path>,
        policy: Option<mapping::lifelong::TrimPolicy>,
    ) -> Result<Self, SessionsError> {
        let mut config = match path {
            Some(path) => load_toml(path)?,
            None => Self::default(),
        };
        if let Some(policy) = policy {
            config.lifelong.policy = policy;
        }
        Ok(config)
    }
}
