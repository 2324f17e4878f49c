//! The errors of a multi-session run.

use mapping::lifelong::LifelongError;

use crate::config_file::ConfigFileError;

/// Errors of a multi-session run.
#[derive(Debug, thiserror::Error)]
pub enum SessionsError {
    /// The lifelong map refused the configuration, a session or a node.
    #[error("lifelong map: {0}")]
    Map(#[from] LifelongError),
    /// The configuration is invalid.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// The configuration file could not be read or parsed.
    #[error(transparent)]
    ConfigFile(#[from] ConfigFileError),
    /// A section of the configuration refused its options.
    #[error("invalid configuration: {0}")]
    Options(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// The recording has no laser scans.
    #[error("the recording has no laser scans")]
    NoScans,
    /// The worker thread died.
    #[error("lifelong map worker failed: {0}")]
    Worker(String),
    /// The worker thread could not be started.
    #[error("lifelong map worker failed: {0}")]
    Spawn(#[source] std::io::Error),
}
