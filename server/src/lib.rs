//! # server — the evermap fleet map server
//!
//! Hosts many sites (stores). Each site is one task ([`site::SiteTask`]) owning its multi-session map,
//! fed through a bounded channel so its changes are applied in order; heavy work runs on tokio's blocking
//! pool. Every accepted change is stored durably through a [`storage::MapStore`] before it is
//! acknowledged, makes a new monotonic site version, and is published to watchers. The gRPC front end
//! ([`grpc`]) only authenticates, converts and forwards, so other transports can feed the same tasks.
//!
//! Start everything with [`RunningServer::start`]; the `evermap-server serve` command does that with a
//! [`ServerConfig`] read from TOML and a sled store.

pub mod console;
pub mod fleet_server;
pub mod grpc;
pub mod map_image_bytes;
pub mod metrics_endpoint;
pub mod server_config;
pub mod server_metrics;
pub mod site;
#[cfg(test)]
mod testing;
pub mod zenoh_front;

pub use console::HttpConfig;
pub use fleet_server::{RunningServer, ServeError};
pub use proto::logging::{LogOutput, init_logging};
pub use server_config::{RobotConfig, ServerConfig, ServerConfigError, SiteConfig, TlsConfig};
pub use server_metrics::ServerMetrics;
