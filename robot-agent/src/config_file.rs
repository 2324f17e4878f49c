//! The one reader of the agent's TOML configuration files (`run`'s [`AgentConfig`], `offline`'s and
//! `relocalize`'s [`SlamConfig`], `sessions`' [`SessionsConfig`]): read the file, parse it into the
//! type, name the file in any error. What a value may be is each type's own `validate()`, called by its
//! user; unknown keys are refused by the types themselves (`#[serde(deny_unknown_fields)]`).
//!
//! [`AgentConfig`]: crate::agent_config::AgentConfig
//! [`SlamConfig`]: crate::offline_slam::SlamConfig
//! [`SessionsConfig`]: crate::lifelong_run::SessionsConfig

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;

/// Why a configuration file could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum ConfigFileError {
    /// The file could not be read.
    #[error("cannot read configuration {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The text is not TOML, or has unknown keys or values of the wrong type.
    #[error("invalid configuration {}: {source}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// Why.
        source: toml::de::Error,
    },
}

/// The TOML file at `path` as a `T`. The caller validates the values.
pub fn load_toml<T: DeserializeOwned>(path: &Path) -> Result<T, ConfigFileError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigFileError::Read {
        path: path.to_owned(),
        source,
    })?;
    toml::from_str(&text).map_err(|source| ConfigFileError::Parse {
        path: path.to_owned(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::agent_config::AgentConfig;
    use crate::lifelong_run::SessionsConfig;
    use crate::offline_slam::SlamConfig;

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    fn names_the_file(error: &ConfigFileError, path: &Path) {
        let message = error.to_string();
        assert!(message.contains(&path.display().to_string()), "{message}");
    }

    #[test]
    fn a_missing_file_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("absent.toml");
        let error = load_toml::<SlamConfig>(&path).unwrap_err();
        assert!(matches!(error, ConfigFileError::Read { .. }), "{error:?}");
        names_the_file(&error, &path);
        let source = std::error::Error::source(&error).expect("the io error");
        assert!(source.is::<std::io::Error>(), "{source:?}");
    }

    #[test]
    fn a_malformed_file_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = write(dir.path(), "malformed.toml", "[local\nx = ");
        let error = load_toml::<SessionsConfig>(&path).unwrap_err();
        assert!(matches!(error, ConfigFileError::Parse { .. }), "{error:?}");
        names_the_file(&error, &path);
        let source = std::error::Error::source(&error).expect("the toml error");
        assert!(source.is::<toml::de::Error>(), "{source:?}");
    }

    #[test]
    fn every_configuration_refuses_an_unknown_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = write(dir.path(), "unknown.toml", "no_such_field = 1\n");
        let errors = [
            load_toml::<AgentConfig>(&path).map(drop).unwrap_err(),
            load_toml::<SlamConfig>(&path).map(drop).unwrap_err(),
            load_toml::<SessionsConfig>(&path).map(drop).unwrap_err(),
        ];
        for error in &errors {
            assert!(matches!(error, ConfigFileError::Parse { .. }), "{error:?}");
            names_the_file(error, &path);
            assert!(error.to_string().contains("no_such_field"), "{error}");
        }
    }

    #[test]
    fn a_known_field_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = write(dir.path(), "policy.toml", "[lifelong]\npolicy = \"keep\"\n");
        let config = load_toml::<SessionsConfig>(&path).unwrap();
        assert_eq!(config.lifelong.policy, mapping::lifelong::TrimPolicy::Keep);
    }
}
