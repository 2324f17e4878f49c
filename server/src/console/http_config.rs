//! The `[http]` section of the server's configuration: the web console and its JSON API.

use std::net::SocketAddr;

use serde::Deserialize;

/// Shortest operator token accepted, characters.
pub const MIN_OPERATOR_TOKEN_CHARS: usize = 8;

/// The web console (TOML section `[http]`; the console is off when the section is absent).
///
/// ```toml
/// [http]
/// listen = "127.0.0.1:8080"
/// operator_token = "a-long-random-secret"   # required when robots have tokens
/// map_resolution_m = 0.05
/// ```
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HttpConfig {
    /// Listen address of the console (page, `/api/`, `/health`, `/metrics`). Default `127.0.0.1:8080`;
    /// port 0 picks a free port.
    pub listen: SocketAddr,
    /// The read-only operator token: every request but `/health` must carry it (`authorization: Bearer
    /// <token>`, `?token=<token>`, or the `evermap_token` cookie the page sets when opened with
    /// `?token=`). Required when any site has robots (whose tokens guard gRPC and zenoh): the console
    /// shows every site. At least 8 characters and no robot's token. Default none: an open console, for
    /// a server without robot tokens only.
    pub operator_token: Option<String>,
    /// Cell size of the console's map and change images, metres (0.02..=1). Default 0.05 (the submaps'
    /// own).
    pub map_resolution_m: f64,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            operator_token: None,
            map_resolution_m: 0.05,
        }
    }
}

/// An invalid [`HttpConfig`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HttpConfigError {
    /// The operator token is too short or holds spaces or control characters.
    #[error(
        "operator_token must be at least {MIN_OPERATOR_TOKEN_CHARS} characters, without spaces or control characters"
    )]
    WeakOperatorToken,
    /// The console's map resolution is outside 0.02..=1 m.
    #[error("map_resolution_m must be in 0.02..=1 m, got {got}")]
    MapResolution {
        /// The resolution configured, metres per pixel.
        got: f64,
    },
}

impl HttpConfig {
    /// Checks the fields on their own (the server's config checks the token against the robots').
    pub fn validate(&self) -> Result<(), HttpConfigError> {
        if let Some(token) = &self.operator_token
            && (token.chars().count() < MIN_OPERATOR_TOKEN_CHARS
                || token.chars().any(|c| c.is_control() || c.is_whitespace()))
        {
            return Err(HttpConfigError::WeakOperatorToken);
        }
        if !(0.02..=1.0).contains(&self.map_resolution_m) {
            return Err(HttpConfigError::MapResolution {
                got: self.map_resolution_m,
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_values_are_named() {
        assert_eq!(HttpConfig::default().validate(), Ok(()));
        let short = HttpConfig {
            operator_token: Some("short".into()),
            ..HttpConfig::default()
        };
        assert_eq!(short.validate(), Err(HttpConfigError::WeakOperatorToken));
        assert!(
            short
                .validate()
                .unwrap_err()
                .to_string()
                .contains("operator_token")
        );
        let spaced = HttpConfig {
            operator_token: Some("with a space".into()),
            ..HttpConfig::default()
        };
        assert_eq!(spaced.validate(), Err(HttpConfigError::WeakOperatorToken));
        for bad in [0.0, f64::NAN, 5.0] {
            let config = HttpConfig {
                map_resolution_m: bad,
                ..HttpConfig::default()
            };
            let error = config.validate().unwrap_err();
            assert!(
                matches!(error, HttpConfigError::MapResolution { got } if got.to_bits() == bad.to_bits()),
                "{bad}"
            );
            assert!(error.to_string().contains("map_resolution_m"), "{bad}");
        }
    }
}
