//! # robot-agent — the robot side of evermap
//!
//! Data sources (ROS1 bags, ROS 2 recordings, CARMEN logs), the offline tools built on the `mapping`
//! core, and the uplink to the fleet map server (durable outbox, gRPC, the global submap cache).

pub mod agent_config;
pub mod config_file;
pub mod lifelong_run;
pub mod line_chart;
pub mod map_image;
pub mod map_probes;
pub mod offline_slam;
pub mod outbox;
pub mod perturbation;
pub mod process_stats;
pub mod ros2_publisher;
pub mod source;
pub mod uplink;
