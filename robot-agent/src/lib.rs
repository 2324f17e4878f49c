//! # robot-agent — the robot side of evermap
//!
//! Data sources (ROS1 bags, CARMEN logs) and the offline tools built on the `mapping` core.

pub mod line_chart;
pub mod map_image;
pub mod offline_slam;
pub mod process_stats;
pub mod source;
