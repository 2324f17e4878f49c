//! `evermap-agent run`'s TOML configuration: parsed and validated here, in the library, so the binary and
//! the decoder fuzz harness (`tests::fuzz`, target `agent_config`) go through the same code.
//!
//! ```toml
//! server_url = "http://127.0.0.1:50051"
//! site = "store-1"
//! robot_id = "robot-1"
//! token = "change-me"
//! source = "../shared/datasets/rosbag1/mit-csail.orig.bag"
//! replay_speed = 1.0        # multiple of real time; 0 = as fast as possible
//! outbox_dir = "./evermap-outbox"
//! dock_starts = true        # check first where the robot's last session in the site ended
//!
//! # Optional, gRPC over TLS: server_url = "https://..." and the CA that signed the server's certificate.
//! # tls_ca_pem = "/etc/evermap/ca.pem"
//!
//! # Optional: reach the server through zenoh (routers or its zenoh endpoint) instead of gRPC.
//! [zenoh]
//! connect = ["tcp/127.0.0.1:7447"]
//!
//! # Optional, instead of `source`: a live ROS 2 robot over zenoh (rmw_zenoh, no ROS install); the
//! # session ends `until_idle_s` after the last scan (and `run` with it). Each new site map version is
//! # published back on /map, and, once the session is placed on the site map, each node's global pose
//! # (`[ros2.publish]`: pose topic, frames). See `robot_agent::source::Ros2LiveOptions` for every field.
//! [ros2]
//! domain_id = 0
//! scan_topic = "/scan"
//! odom_topic = "/odom"
//! [ros2.zenoh]
//! connect = ["tcp/127.0.0.1:7447"]   # the robot's rmw_zenoh router
//! ```

use std::path::PathBuf;
use std::time::Duration;

use mapping::local_slam::LocalTrajectoryBuilderOptions;
use serde::Deserialize;

use crate::source::Ros2LiveOptions;
use crate::uplink::ZenohLinkOptions;

/// Why an [`AgentConfig`] cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum AgentConfigError {
    /// The text is not TOML, or has unknown keys or values of the wrong type.
    #[error(transparent)]
    Parse(#[from] toml::de::Error),
    /// A field is missing or out of range.
    #[error("{field}: {reason}")]
    Invalid {
        /// The field (dotted path).
        field: &'static str,
        /// Why.
        reason: String,
    },
    /// A section's own check refused it.
    #[error("{field}: {source}")]
    Refused {
        /// The section.
        field: &'static str,
        /// Why.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

fn refused(
    field: &'static str,
    source: impl std::error::Error + Send + Sync + 'static,
) -> AgentConfigError {
    AgentConfigError::Refused {
        field,
        source: Box::new(source),
    }
}

fn invalid(field: &'static str, reason: impl Into<String>) -> AgentConfigError {
    AgentConfigError::Invalid {
        field,
        reason: reason.into(),
    }
}

/// Everything `evermap-agent run` reads from its TOML file.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AgentConfig {
    /// The map server's gRPC URL. Default `http://127.0.0.1:50051`.
    pub server_url: String,
    /// The site (store) this robot maps. Required.
    pub site: String,
    /// This robot's id. Required.
    pub robot_id: String,
    /// This robot's bearer token for the site. Required.
    pub token: String,
    /// The recording to replay: a ROS1 bag, a ROS 2 recording (rosbag2 folder, `metadata.yaml`, `.mcap`
    /// or `.db3`) or a CARMEN log. Required unless `[ros2]` is given.
    pub source: PathBuf,
    /// A live ROS 2 robot over zenoh instead of `source` (`[ros2]`). Default none.
    pub ros2: Option<Ros2LiveOptions>,
    /// Replay pace as a multiple of real time; 0 = as fast as possible. Default 1.
    pub replay_speed: f64,
    /// Stop after this many scans (all by default).
    pub max_scans: Option<usize>,
    /// Outbox database directory. Default `./evermap-outbox`. It also keeps the robot's dock per site
    /// (see `dock_starts`).
    pub outbox_dir: PathBuf,
    /// Start each session where the robot's last session in the site ended (its dock, as it estimated it
    /// then): the session's first nodes check that pose against the site map and place it there at once
    /// where they agree; elsewhere (carried, the dock moved, the last session never placed) it searches
    /// the whole map. `false`: every session searches. Default true.
    pub dock_starts: bool,
    /// Session uuid; a random one by default. A uuid is used once: a session interrupted by a crash is
    /// ended by the next run, which maps a new one.
    pub session_uuid: Option<String>,
    /// Nodes per upload batch. Default 10.
    pub nodes_per_batch: usize,
    /// Largest gRPC message, bytes (match the server's). Default 64 MiB.
    pub max_message_bytes: usize,
    /// Timeout of one gRPC call, seconds. Default 30.
    pub call_timeout_s: f64,
    /// Pause between retries while the server is unreachable, seconds. Default 1.
    pub retry_interval_s: f64,
    /// After the recording, how long to keep trying to deliver the outbox, seconds. Default 300.
    pub final_flush_timeout_s: f64,
    /// LLO settings.
    pub local: LocalTrajectoryBuilderOptions,
    /// The CA certificate (PEM file) that signed the server's TLS certificate: gRPC over TLS (use an
    /// `https://` `server_url`). Default none: plaintext.
    pub tls_ca_pem: Option<PathBuf>,
    /// The server name in its certificate, when it differs from `server_url`'s host. Default none.
    pub tls_domain: Option<String>,
    /// Reach the server through zenoh with these settings (`[zenoh]`: `mode`, `listen`, `connect`,
    /// `multicast_scouting`, and `[zenoh.tls]` for mutual TLS) instead of gRPC at `server_url`.
    /// Default none: gRPC.
    pub zenoh: Option<ZenohLinkOptions>,
}

impl Default for AgentConfig {
    fn default() -> Self {
        Self {
            server_url: "http://127.0.0.1:50051".into(),
            site: String::new(),
            robot_id: String::new(),
            token: String::new(),
            source: PathBuf::new(),
            replay_speed: 1.0,
            max_scans: None,
            outbox_dir: PathBuf::from("./evermap-outbox"),
            dock_starts: true,
            session_uuid: None,
            nodes_per_batch: 10,
            max_message_bytes: 64 << 20,
            call_timeout_s: 30.0,
            retry_interval_s: 1.0,
            final_flush_timeout_s: 300.0,
            local: LocalTrajectoryBuilderOptions::default(),
            tls_ca_pem: None,
            tls_domain: None,
            zenoh: None,
            ros2: None,
        }
    }
}

/// A positive, finite number of seconds as a duration.
fn seconds(field: &'static str, value: f64) -> Result<Duration, AgentConfigError> {
    Duration::try_from_secs_f64(value)
        .ok()
        .filter(|d| !d.is_zero())
        .ok_or_else(|| {
            invalid(
                field,
                format!("must be a positive number of seconds, got {value}"),
            )
        })
}

impl AgentConfig {
    /// Parses TOML text (unknown keys are errors); [`Self::validate`] checks the values.
    pub fn from_toml(text: &str) -> Result<Self, AgentConfigError> {
        Ok(toml::from_str(text)?)
    }

    /// Checks every field.
    pub fn validate(&self) -> Result<(), AgentConfigError> {
        for (field, value) in [
            ("site", &self.site),
            ("robot_id", &self.robot_id),
            ("token", &self.token),
        ] {
            if value.is_empty() {
                return Err(invalid(field, "is required"));
            }
        }
        match &self.ros2 {
            Some(ros2) => {
                if !self.source.as_os_str().is_empty() {
                    return Err(invalid(
                        "source",
                        "give either source (a recording) or [ros2] (a live robot), not both",
                    ));
                }
                ros2.validate().map_err(|e| refused("ros2", e))?;
            }
            None => {
                if self.source.as_os_str().is_empty() {
                    return Err(invalid(
                        "source",
                        "is required (or a [ros2] section for a live robot)",
                    ));
                }
            }
        }
        if !(self.replay_speed.is_finite() && self.replay_speed >= 0.0) {
            return Err(invalid(
                "replay_speed",
                format!("must be a finite number ≥ 0, got {}", self.replay_speed),
            ));
        }
        if self.nodes_per_batch == 0 {
            return Err(invalid("nodes_per_batch", "must be at least 1"));
        }
        if self.max_message_bytes < 1 << 20 {
            return Err(invalid(
                "max_message_bytes",
                "must be at least 1 MiB (1048576)",
            ));
        }
        self.call_timeout()?;
        self.retry_interval()?;
        self.final_flush_timeout()?;
        self.local.validate().map_err(|e| refused("local", e))?;
        if let Some(zenoh) = &self.zenoh {
            zenoh.validate().map_err(|e| refused("zenoh", e))?;
        }
        Ok(())
    }

    /// [`Self::call_timeout_s`] as a duration.
    pub fn call_timeout(&self) -> Result<Duration, AgentConfigError> {
        seconds("call_timeout_s", self.call_timeout_s)
    }

    /// [`Self::retry_interval_s`] as a duration.
    pub fn retry_interval(&self) -> Result<Duration, AgentConfigError> {
        seconds("retry_interval_s", self.retry_interval_s)
    }

    /// [`Self::final_flush_timeout_s`] as a duration.
    pub fn final_flush_timeout(&self) -> Result<Duration, AgentConfigError> {
        seconds("final_flush_timeout_s", self.final_flush_timeout_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configs_need_their_identity_and_parse_strictly() {
        let text = "site = \"s\"\nrobot_id = \"r\"\ntoken = \"t0k3n-t0k3n\"\nsource = \"x.bag\"\n";
        let config = AgentConfig::from_toml(text).unwrap();
        config.validate().unwrap();
        assert!(AgentConfig::default().validate().is_err());
        assert!(AgentConfig::from_toml("sight = \"s\"").is_err());
        let error = AgentConfig::from_toml(&format!("{text}call_timeout_s = 1e300\n"))
            .unwrap()
            .validate()
            .unwrap_err()
            .to_string();
        assert!(error.contains("call_timeout_s"), "{error}");
    }

    // Reference: issue 35 item 6 — a section's own error stays the source of the config's error.
    #[test]
    fn a_refused_section_keeps_its_error_as_the_source() {
        let text = "site = \"s\"\nrobot_id = \"r\"\ntoken = \"t0k3n-t0k3n\"\nsource = \"x.bag\"\n\
                    [local]\ncorrelative_max_range = -1.0\n";
        let error = AgentConfig::from_toml(text)
            .unwrap()
            .validate()
            .unwrap_err();
        let source = std::error::Error::source(&error).expect("the section's error");
        assert!(
            source.is::<mapping::local_slam::LocalTrajectoryBuilderOptionsError>(),
            "{source:?}"
        );
        assert_eq!(error.to_string(), format!("local: {source}"));
    }

    #[test]
    fn a_ros2_section_replaces_the_source() {
        let identity = "site = \"s\"\nrobot_id = \"r\"\ntoken = \"t0k3n-t0k3n\"\n";
        let live = format!(
            "{identity}[ros2]\ndomain_id = 7\nscan_topic = \"/base/scan\"\n[ros2.publish]\npose_topic = \"/amcl_pose\"\n"
        );
        let config = AgentConfig::from_toml(&live).unwrap();
        config.validate().unwrap();
        let ros2 = config.ros2.unwrap();
        assert_eq!(
            (ros2.domain_id, ros2.scan_topic.as_str()),
            (7, "/base/scan")
        );
        assert_eq!(ros2.publish.pose_topic, "/amcl_pose");
        let both = format!("{identity}source = \"x.bag\"\n[ros2]\n");
        let config = AgentConfig::from_toml(&both).unwrap();
        assert!(
            config
                .validate()
                .unwrap_err()
                .to_string()
                .contains("not both")
        );
        let bad_topic = format!("{identity}[ros2]\nodom_topic = \"odom\"\n");
        let config = AgentConfig::from_toml(&bad_topic).unwrap();
        assert!(config.validate().is_err());
    }

    #[test]
    fn deploy_agent_configs_are_valid() {
        for n in 1..=2 {
            let path = format!("{}/../deploy/agent-{n}.toml", env!("CARGO_MANIFEST_DIR"));
            let text = std::fs::read_to_string(&path).unwrap();
            let config = AgentConfig::from_toml(&text).unwrap();
            config.validate().unwrap();
            assert_eq!(config.robot_id, format!("robot-{n}"));
            assert!(
                config.zenoh.is_some(),
                "the deployed agents go through zenohd"
            );
        }
    }
}
