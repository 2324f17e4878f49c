//! How a process joins the zenoh network: the key expressions of the fleet protocol and the few settings
//! evermap exposes, turned into a `zenoh::Config`. Shared by the agent's `ZenohUplink` and the server's
//! zenoh front end, so it lives here beside the wire types both speak (neither side links the other).

use serde::Deserialize;

use crate::ZenohTlsOptions;

/// Key expression of a site's request/reply queryable (the uplink and map reads).
pub fn zenoh_api_key(site: &str) -> String {
    format!("evermap/{site}/api")
}

/// Key expression on which the server publishes a site's new versions.
pub fn zenoh_version_key(site: &str) -> String {
    format!("evermap/{site}/version")
}

/// A zenoh session's settings. Everything else keeps zenoh's defaults.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohLinkOptions {
    /// `peer` (talks to routers and other peers) or `client` (talks to one router). Default `peer`.
    pub mode: String,
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447`. Default none.
    pub listen: Vec<String>,
    /// Endpoints to connect to (a `zenohd` router, or the server's listen endpoint), e.g.
    /// `tcp/zenohd:7447`. Default none.
    pub connect: Vec<String>,
    /// Discover peers and routers by UDP multicast on the LAN. Default false: endpoints are explicit, which
    /// is what a store network with several fleets (and a CI machine) needs.
    pub multicast_scouting: bool,
    /// Mutual TLS on `tls/...` endpoints (TOML section `[zenoh.tls]`: `root_ca_pem`, `cert_pem`,
    /// `key_pem`). Default none: `tcp/...` endpoints only.
    pub tls: Option<ZenohTlsOptions>,
}

impl Default for ZenohLinkOptions {
    fn default() -> Self {
        Self {
            mode: "peer".into(),
            listen: Vec::new(),
            connect: Vec::new(),
            multicast_scouting: false,
            tls: None,
        }
    }
}

/// Invalid [`ZenohLinkOptions`].
#[derive(Debug, thiserror::Error)]
#[error("zenoh option {field}: {reason}")]
pub struct ZenohLinkOptionsError {
    /// The offending option.
    pub field: &'static str,
    /// Why.
    pub reason: String,
    /// The underlying error (zenoh's, or the JSON encoder's), where there is one.
    #[source]
    pub source: Option<Box<dyn std::error::Error + Send + Sync>>,
}

impl ZenohLinkOptions {
    /// Checks the fields (endpoint syntax is checked by zenoh when the session opens).
    pub fn validate(&self) -> Result<(), ZenohLinkOptionsError> {
        if !matches!(self.mode.as_str(), "peer" | "client") {
            return Err(ZenohLinkOptionsError {
                field: "mode",
                reason: format!("{:?} is neither \"peer\" nor \"client\"", self.mode),
                source: None,
            });
        }
        if self.mode == "client" && self.connect.is_empty() {
            return Err(ZenohLinkOptionsError {
                field: "connect",
                reason: "a client needs at least one endpoint to connect to".into(),
                source: None,
            });
        }
        if self.listen.is_empty() && self.connect.is_empty() && !self.multicast_scouting {
            return Err(ZenohLinkOptionsError {
                field: "listen/connect",
                reason: "with multicast scouting off, give at least one endpoint to listen on or connect to"
                    .into(),
                source: None,
            });
        }
        let tls_endpoint = self
            .listen
            .iter()
            .chain(&self.connect)
            .find(|e| e.starts_with("tls/"));
        if let (Some(endpoint), None) = (tls_endpoint, &self.tls) {
            return Err(ZenohLinkOptionsError {
                field: "tls",
                reason: format!("endpoint {endpoint:?} needs the certificates of [zenoh.tls]"),
                source: None,
            });
        }
        Ok(())
    }

    /// The zenoh configuration: mode, endpoints, scouting (multicast and gossip follow
    /// `multicast_scouting`).
    pub fn to_zenoh_config(&self) -> Result<zenoh::Config, ZenohLinkOptionsError> {
        self.validate()?;
        let mut config = zenoh::Config::default();
        let json = |v: serde_json::Result<String>| v.unwrap_or_default();
        let mut entries: Vec<(&'static str, String)> = vec![
            ("mode", json(serde_json::to_string(&self.mode))),
            (
                "listen/endpoints",
                json(serde_json::to_string(&self.listen)),
            ),
            (
                "connect/endpoints",
                json(serde_json::to_string(&self.connect)),
            ),
            (
                "scouting/multicast/enabled",
                self.multicast_scouting.to_string(),
            ),
            (
                "scouting/gossip/enabled",
                self.multicast_scouting.to_string(),
            ),
        ];
        if let Some(tls) = &self.tls {
            entries.extend(tls.entries()?);
        }
        for (key, value) in entries {
            config
                .insert_json5(key, &value)
                .map_err(|e| ZenohLinkOptionsError {
                    field: key,
                    reason: e.to_string(),
                    source: Some(e),
                })?;
        }
        Ok(config)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn explicit_endpoints_make_a_config_and_bad_options_are_named() {
        let options = ZenohLinkOptions {
            listen: vec!["tcp/127.0.0.1:0".into()],
            ..ZenohLinkOptions::default()
        };
        assert!(options.to_zenoh_config().is_ok());
        let nothing = ZenohLinkOptions::default();
        assert_eq!(nothing.validate().unwrap_err().field, "listen/connect");
        let bad_mode = ZenohLinkOptions {
            mode: "router".into(),
            ..options.clone()
        };
        assert_eq!(bad_mode.validate().unwrap_err().field, "mode");
        let tls_without_certificates = ZenohLinkOptions {
            connect: vec!["tls/127.0.0.1:7447".into()],
            ..ZenohLinkOptions::default()
        };
        assert_eq!(
            tls_without_certificates.validate().unwrap_err().field,
            "tls"
        );
        let with_certificates = ZenohLinkOptions {
            tls: Some(ZenohTlsOptions {
                root_ca_pem: "ca.pem".into(),
                cert_pem: "robot.pem".into(),
                key_pem: "robot.key".into(),
            }),
            ..tls_without_certificates
        };
        assert!(with_certificates.to_zenoh_config().is_ok());
        let bad_endpoint = ZenohLinkOptions {
            connect: vec!["not an endpoint".into()],
            ..options
        };
        assert!(bad_endpoint.to_zenoh_config().is_err());
    }
}
