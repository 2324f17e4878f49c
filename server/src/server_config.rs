//! The server's TOML configuration (`evermap-server serve --config server.toml`).
//!
//! ```toml
//! listen = "127.0.0.1:50051"          # gRPC
//! metrics_listen = "127.0.0.1:9464"   # Prometheus text at /metrics (the default; port 0: any free port)
//! max_message_bytes = 67108864
//! session_idle_timeout_s = 3600.0    # end a session whose robot has been silent this long; 0 = never
//! site_unload_after_s = 600.0        # drop an idle site's map from memory (restored at its next request); 0 = never
//!
//! [checkpoints]                      # optional: a site starts from its newest checkpoint + the log after it
//! enabled = true
//! every_n_versions = 200             # besides every session end
//! keep = 2                           # checkpoints kept (at least 2); the log after the oldest is kept
//! keep_log_entries = 0               # log entries kept before that, for audit
//!
//! [storage]
//! path = "./evermap-data"
//!
//! [tls]                              # optional: gRPC over TLS (rustls)
//! cert_pem = "/etc/evermap/server.pem"
//! key_pem = "/etc/evermap/server.key"
//!
//! [auth]                             # optional: failed authentications per peer and site
//! max_failures = 10                  # per window; then RESOURCE_EXHAUSTED unchecked; 0 = no limit
//! window_s = 60.0
//!
//! [zenoh]                            # optional: the zenoh front end (agents' uplink, version pushes)
//! listen = ["tcp/127.0.0.1:7447"]
//!
//! [http]                             # optional: the web console and its JSON API (console::HttpConfig)
//! listen = "127.0.0.1:8080"
//! operator_token = "change-me-operator"  # read-only; required when robots have tokens
//!
//! [map]                              # optional: every site's lifelong map (mapping::lifelong::LifelongOptions)
//! policy = "clt"                     # clt | delete | keep | frozen
//!
//! [[sites]]
//! id = "store-1"
//! robots = [{ id = "robot-1", token = "change-me" }]
//! ```

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use mapping::lifelong::LifelongOptions;
use proto::ZenohLinkOptions;
use serde::Deserialize;
use storage::SledStoreOptions;

use crate::console::HttpConfig;
use crate::grpc::AuthLimitOptions;
use crate::site::CheckpointOptions;

/// Invalid [`ServerConfig`].
#[derive(Debug, thiserror::Error)]
pub enum ServerConfigError {
    /// A field is out of range.
    #[error("{field}: {reason}")]
    Invalid {
        /// The field (dotted path).
        field: String,
        /// Why.
        reason: String,
    },
    /// A section's (or a field's) own check refused it.
    #[error("{field}: {source}")]
    Refused {
        /// The section or field (dotted path).
        field: &'static str,
        /// Why.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// Two sites share an id, or two robots a token.
    #[error("duplicate {what} {value:?}")]
    Duplicate {
        /// "site id", "robot token" or "robot id".
        what: &'static str,
        /// The duplicated value (for tokens, only its length is shown).
        value: String,
    },
}

/// A robot allowed to upload to, and read, one site.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    /// The robot's id; uploads must name it.
    pub id: String,
    /// Its bearer token (`authorization: Bearer <token>`), valid for this site only.
    pub token: String,
}

/// gRPC over TLS: the server's certificate chain and private key, PEM files.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// The certificate chain (PEM), leaf first.
    pub cert_pem: PathBuf,
    /// The private key of the leaf certificate (PEM: PKCS#8, PKCS#1 or SEC1).
    pub key_pem: PathBuf,
}

/// One site (store) the server hosts.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SiteConfig {
    /// Site id (1..=255 bytes, no control characters).
    pub id: String,
    /// Robots of the site.
    #[serde(default)]
    pub robots: Vec<RobotConfig>,
}

/// Everything `evermap-server serve` can be configured with; every field has a default.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServerConfig {
    /// gRPC listen address. Default `127.0.0.1:50051`; port 0 picks a free port.
    pub listen: SocketAddr,
    /// Prometheus metrics listen address (`GET /metrics`); `None` disables. Default `127.0.0.1:9464`.
    pub metrics_listen: Option<SocketAddr>,
    /// Largest gRPC message accepted or sent, bytes (tonic's default is 4 MiB, too small for big batches).
    /// Default 64 MiB; at least 1 MiB.
    pub max_message_bytes: usize,
    /// Target size of one streamed `MapDelta` message, bytes; at most `max_message_bytes`. Default 4 MiB.
    pub delta_chunk_bytes: usize,
    /// Commands queued per site before callers wait (backpressure), count. Default 64.
    pub site_queue_depth: usize,
    /// End a session whose robot has sent nothing of it (no open, upload or close) for this long,
    /// seconds, as if the robot had ended it: a robot that dies and never comes back must not hold its
    /// session (and the trimming its end brings) open for ever. Counted from the last request, or from
    /// the server's start for sessions open across a restart. Must be longer than the link outages
    /// robots ride out with their outbox: the rest of a session ended this way is refused. 0 = never.
    /// Default 3600 (one hour).
    pub session_idle_timeout_s: f64,
    /// Unload a site that has had no open session and no request (a robot's, a map query, the
    /// console's) for this long, seconds: its map leaves memory once a checkpoint covering its version
    /// is durable, and the next request restores it from that checkpoint first (it waits for the
    /// restore: 0.4–0.7 s for sites of 16–36 sessions, docs/BENCHMARK-HISTORY.md). Versions, counts and
    /// the session list stay answerable without it. Never with `[checkpoints] enabled = false`. 0 = never.
    /// Default 600 (10 minutes).
    pub site_unload_after_s: f64,
    /// On-disk storage.
    pub storage: SledStoreOptions,
    /// Site checkpoints and log compaction (TOML section `[checkpoints]`: `enabled`,
    /// `every_n_versions`, `keep`, `keep_log_entries`; see [`CheckpointOptions`]). Default: enabled,
    /// at every session end and every 200 versions, two kept.
    pub checkpoints: CheckpointOptions,
    /// The multi-session map of every site: GLM, PGR, the session start (`[map.relocalization]`,
    /// `[map.session_start]`: the server searches for a session its robot could not place, and holds every
    /// placement on probation), trimming policy and sparsification (the `mapping` crate's
    /// `LifelongOptions`, TOML section `[map]`). Default: `LifelongOptions::default()`.
    pub map: LifelongOptions,
    /// gRPC over TLS (rustls) with these certificates (TOML section `[tls]`: `cert_pem`, `key_pem`).
    /// Default none: plaintext gRPC, for loopback and private networks only. (The zenoh front end's links
    /// take mutual TLS from `[zenoh.tls]`.)
    pub tls: Option<TlsConfig>,
    /// Limits on failed authentications per peer and site (TOML section `[auth]`: `max_failures`,
    /// `window_s`, `max_tracked`; see `grpc::AuthLimitOptions`). Default 10 failures per 60 s.
    pub auth: AuthLimitOptions,
    /// The zenoh front end (TOML section `[zenoh]`: `mode`, `listen`, `connect`, `multicast_scouting`,
    /// `[zenoh.tls]` for mutual TLS; see
    /// `proto::ZenohLinkOptions`). Default none: gRPC only.
    pub zenoh: Option<ZenohLinkOptions>,
    /// The web console (TOML section `[http]`: `listen`, `operator_token`, `map_resolution_m`; see
    /// [`HttpConfig`]). Default none: no console.
    pub http: Option<HttpConfig>,
    /// The sites and their robots.
    pub sites: Vec<SiteConfig>,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 50051)),
            metrics_listen: Some(SocketAddr::from(([127, 0, 0, 1], 9464))),
            max_message_bytes: 64 << 20,
            delta_chunk_bytes: 4 << 20,
            site_queue_depth: 64,
            session_idle_timeout_s: 3600.0,
            site_unload_after_s: 600.0,
            storage: SledStoreOptions::default(),
            checkpoints: CheckpointOptions::default(),
            map: LifelongOptions::default(),
            tls: None,
            auth: AuthLimitOptions::default(),
            zenoh: None,
            http: None,
            sites: Vec::new(),
        }
    }
}

impl ServerConfig {
    /// Parses TOML text (unknown keys are errors).
    pub fn from_toml(text: &str) -> Result<Self, toml::de::Error> {
        toml::from_str(text)
    }

    /// [`Self::session_idle_timeout_s`] as a duration; `None` when 0 (never).
    pub fn session_idle_timeout(&self) -> Result<Option<Duration>, ServerConfigError> {
        match Duration::try_from_secs_f64(self.session_idle_timeout_s) {
            Ok(d) if d.is_zero() => Ok(None),
            Ok(d) => Ok(Some(d)),
            Err(e) => Err(ServerConfigError::Refused {
                field: "session_idle_timeout_s",
                source: e.into(),
            }),
        }
    }

    /// [`Self::site_unload_after_s`] as a duration; `None` when 0 (never).
    pub fn site_unload_after(&self) -> Result<Option<Duration>, ServerConfigError> {
        match Duration::try_from_secs_f64(self.site_unload_after_s) {
            Ok(d) if d.is_zero() => Ok(None),
            Ok(d) => Ok(Some(d)),
            Err(e) => Err(ServerConfigError::Refused {
                field: "site_unload_after_s",
                source: e.into(),
            }),
        }
    }

    /// Checks every field.
    pub fn validate(&self) -> Result<(), ServerConfigError> {
        let invalid = |field: &str, reason: &str| {
            Err(ServerConfigError::Invalid {
                field: field.to_owned(),
                reason: reason.to_owned(),
            })
        };
        if self.max_message_bytes < 1 << 20 {
            return invalid("max_message_bytes", "must be at least 1 MiB (1048576)");
        }
        if self.delta_chunk_bytes == 0 || self.delta_chunk_bytes > self.max_message_bytes {
            return invalid("delta_chunk_bytes", "must be in 1..=max_message_bytes");
        }
        if self.site_queue_depth == 0 {
            return invalid("site_queue_depth", "must be at least 1");
        }
        if self.session_idle_timeout().is_err() {
            return invalid(
                "session_idle_timeout_s",
                "must be a number of seconds ≥ 0 (0 = never)",
            );
        }
        if self.site_unload_after().is_err() {
            return invalid(
                "site_unload_after_s",
                "must be a number of seconds ≥ 0 (0 = never)",
            );
        }
        let refused = |field, source: Box<dyn std::error::Error + Send + Sync>| {
            Err(ServerConfigError::Refused { field, source })
        };
        if let Err(e) = self.storage.validate() {
            return refused("storage", e.into());
        }
        if let Err(e) = self.auth.validate() {
            return refused("auth", e.into());
        }
        if let Err(e) = self.checkpoints.validate() {
            return refused("checkpoints", e.into());
        }
        if let Some(Err(e)) = self.zenoh.as_ref().map(ZenohLinkOptions::validate) {
            return refused("zenoh", e.into());
        }
        if let Err(e) = self.map.validate() {
            return refused("map", e.into());
        }
        if let Some(http) = &self.http {
            if let Err(e) = http.validate() {
                return refused("http", e.into());
            }
            let robots_have_tokens = self.sites.iter().any(|s| !s.robots.is_empty());
            if robots_have_tokens && http.operator_token.is_none() {
                return invalid(
                    "http.operator_token",
                    "required when robots have tokens: the console shows every site's map",
                );
            }
        }
        let mut sites = BTreeSet::new();
        let mut tokens = BTreeSet::new();
        for site in &self.sites {
            if let Err(e) = storage::validate_site_id(&site.id) {
                return refused("sites.id", e.into());
            }
            if !sites.insert(site.id.as_str()) {
                return Err(ServerConfigError::Duplicate {
                    what: "site id",
                    value: site.id.clone(),
                });
            }
            let mut robots = BTreeSet::new();
            for robot in &site.robots {
                if robot.id.is_empty() || robot.token.len() < 8 {
                    return invalid(
                        &format!("sites.{}.robots", site.id),
                        "robot ids must be non-empty and tokens at least 8 characters",
                    );
                }
                if !robots.insert(robot.id.as_str()) {
                    return Err(ServerConfigError::Duplicate {
                        what: "robot id",
                        value: robot.id.clone(),
                    });
                }
                if !tokens.insert(robot.token.as_str()) {
                    return Err(ServerConfigError::Duplicate {
                        what: "robot token",
                        value: format!("<{} characters>", robot.token.len()),
                    });
                }
            }
        }
        if let Some(token) = self.http.as_ref().and_then(|h| h.operator_token.as_ref())
            && tokens.contains(token.as_str())
        {
            return invalid(
                "http.operator_token",
                "must differ from every robot's token (it is read-only)",
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn documented_example_parses_and_defaults_are_valid() {
        ServerConfig::default().validate().unwrap();
        let text = "listen = \"127.0.0.1:50051\"\nmetrics_listen = \"127.0.0.1:9464\"\n\
            max_message_bytes = 67108864\n[storage]\npath = \"./evermap-data\"\n\
            [zenoh]\nlisten = [\"tcp/127.0.0.1:7447\"]\n[map]\npolicy = \"clt\"\n[[sites]]\nid = \"store-1\"\n\
            robots = [{ id = \"robot-1\", token = \"change-me\" }]\n";
        let config = ServerConfig::from_toml(text).unwrap();
        config.validate().unwrap();
        assert_eq!(config.sites[0].robots[0].id, "robot-1");
        assert_eq!(config.map.policy, mapping::lifelong::TrimPolicy::Clt);
        assert_eq!(
            config.map.global.unanchored_search_every_n_nodes, 0,
            "no single-scan whole-submap placement: the session start places sessions"
        );
        assert_eq!(ServerConfig::default().map, LifelongOptions::default());
        assert!(ServerConfig::from_toml("lisen = \"x\"").is_err());
    }

    #[test]
    fn bad_configs_are_named() {
        let robot = |id: &str, token: &str| RobotConfig {
            id: id.into(),
            token: token.into(),
        };
        let site = |id: &str, robots| SiteConfig {
            id: id.into(),
            robots,
        };
        let with = |sites| ServerConfig {
            sites,
            ..ServerConfig::default()
        };
        assert!(matches!(
            with(vec![site("a", vec![]), site("a", vec![])]).validate(),
            Err(ServerConfigError::Duplicate {
                what: "site id",
                ..
            })
        ));
        assert!(matches!(
            with(vec![
                site("a", vec![robot("r", "tokentoken")]),
                site("b", vec![robot("r", "tokentoken")])
            ])
            .validate(),
            Err(ServerConfigError::Duplicate {
                what: "robot token",
                ..
            })
        ));
        assert!(
            with(vec![site("a", vec![robot("r", "short")])])
                .validate()
                .is_err()
        );
        assert!(with(vec![site("", vec![])]).validate().is_err());
        let small = ServerConfig {
            max_message_bytes: 1000,
            ..ServerConfig::default()
        };
        assert!(small.validate().is_err());
        for bad in [-1.0, f64::NAN, f64::INFINITY] {
            let config = ServerConfig {
                session_idle_timeout_s: bad,
                ..ServerConfig::default()
            };
            assert!(
                matches!(config.validate(), Err(ServerConfigError::Invalid { field, .. }) if field == "session_idle_timeout_s"),
                "{bad}"
            );
            let config = ServerConfig {
                site_unload_after_s: bad,
                ..ServerConfig::default()
            };
            assert!(
                matches!(config.validate(), Err(ServerConfigError::Invalid { field, .. }) if field == "site_unload_after_s"),
                "{bad}"
            );
        }
        assert_eq!(
            ServerConfig::from_toml("site_unload_after_s = 0.0")
                .unwrap()
                .site_unload_after()
                .unwrap(),
            None
        );
        assert_eq!(
            ServerConfig::default().site_unload_after().unwrap(),
            Some(Duration::from_secs(600))
        );
        let never = ServerConfig {
            session_idle_timeout_s: 0.0,
            ..ServerConfig::default()
        };
        assert_eq!(never.session_idle_timeout().unwrap(), None);
        assert_eq!(
            ServerConfig::default().session_idle_timeout().unwrap(),
            Some(Duration::from_secs(3600))
        );
    }

    // Reference: issue 35 item 6 — a section's own error stays in the chain, down from ServeError.
    #[test]
    fn a_refused_section_keeps_its_error_as_the_source() {
        let mut config = ServerConfig::default();
        config.map.session_start.hold_back_nodes = 0;
        let error = crate::ServeError::from(config.validate().unwrap_err());
        let chain: Vec<&(dyn std::error::Error + 'static)> =
            std::iter::successors(Some(&error as &(dyn std::error::Error + 'static)), |e| {
                e.source()
            })
            .collect();
        assert_eq!(chain.len(), 3, "serve, config, map options: {error:?}");
        assert!(chain[1].is::<ServerConfigError>());
        assert!(chain[2].is::<mapping::lifelong::LifelongOptionsError>());
        assert_eq!(chain[1].to_string(), format!("map: {}", chain[2]));
    }

    #[test]
    fn the_console_needs_an_operator_token_when_robots_have_tokens() {
        let text = "[http]\nlisten = \"127.0.0.1:0\"\n[[sites]]\nid = \"a\"\n\
            robots = [{ id = \"r\", token = \"robot-token\" }]\n";
        let mut config = ServerConfig::from_toml(text).unwrap();
        assert!(matches!(
            config.validate(),
            Err(ServerConfigError::Invalid { field, .. }) if field == "http.operator_token"
        ));
        config.http.as_mut().unwrap().operator_token = Some("robot-token".into());
        assert!(matches!(
            config.validate(),
            Err(ServerConfigError::Invalid { field, .. }) if field == "http.operator_token"
        ));
        config.http.as_mut().unwrap().operator_token = Some("operator-token".into());
        config.validate().unwrap();
        // The section's own check: its error is the source, as the other sections' are.
        config.http.as_mut().unwrap().map_resolution_m = 5.0;
        let error = config.validate().unwrap_err();
        assert!(
            matches!(&error, ServerConfigError::Refused { field: "http", source }
                if source.is::<crate::console::HttpConfigError>()),
            "{error:?}"
        );
        assert_eq!(
            error.to_string(),
            "http: map_resolution_m must be in 0.02..=1 m, got 5"
        );
        config.http.as_mut().unwrap().map_resolution_m = 0.05;
        config.sites[0].robots.clear();
        config.http.as_mut().unwrap().operator_token = None;
        // No tokens anywhere: an open console.
        config.validate().unwrap();
        assert!(ServerConfig::from_toml("[http]\nport = 1\n").is_err());
    }
}
