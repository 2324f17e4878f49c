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

impl HttpConfig {
    /// Checks the fields on their own (the server's config checks the token against the robots').
    pub fn validate(&self) -> Result<(), String> {
        if let Some(token) = &self.operator_token
            && (token.chars().count() < MIN_OPERATOR_TOKEN_CHARS
                || token.chars().any(|c| c.is_control() || c.is_whitespace()))
        {
            return Err(format!(
                "operator_token must be at least {MIN_OPERATOR_TOKEN_CHARS} characters, without spaces or control characters"
            ));
        }
        if !(0.02..=1.0).contains(&self.map_resolution_m) {
            return Err(format!(
                "map_resolution_m must be in 0.02..=1 m, got {}",
                self.map_resolution_m
            ));
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
        assert!(short.validate().unwrap_err().contains("operator_token"));
        let spaced = HttpConfig {
            operator_token: Some("with a space".into()),
            ..HttpConfig::default()
        };
        assert!(spaced.validate().is_err());
        for bad in [0.0, f64::NAN, 5.0] {
            let config = HttpConfig {
                map_resolution_m: bad,
                ..HttpConfig::default()
            };
            assert!(
                config.validate().unwrap_err().contains("map_resolution_m"),
                "{bad}"
            );
        }
    }
}
