//! Robot, route and sensor models of a simulated session.

use serde::{Deserialize, Serialize};

use super::SimulationError;

/// How a simulated session is driven and sensed. Defaults model the paper's cleaning robot with a SICK
/// TiM571 LiDAR.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionOptions {
    /// Driving speed on straight segments, m/s. Default 1.0.
    pub speed: f64,
    /// Turning rate when turning in place at corners, rad/s. Default 0.8.
    pub turn_rate: f64,
    /// Longest session 0 (the mapping run), seconds; 0 = sweep the whole store once. Default 0.
    pub mapping_max_duration_s: f64,
    /// Longest later session (a cleaning run), seconds. Default 300 s.
    pub max_duration_s: f64,
    /// LiDAR field of view, radians. Default 270°.
    pub lidar_fov: f64,
    /// Angle between beams, radians. Default 0.33°.
    pub lidar_angle_increment: f64,
    /// Scans per second. Default 15.
    pub lidar_rate_hz: f64,
    /// Largest range, metres; beams hitting nothing closer read `+inf`. Default 25 m.
    pub lidar_range_max: f64,
    /// Standard deviation of the range noise, metres. Default 0.015.
    pub lidar_range_sigma: f64,
    /// Probability that a beam fails (reads NaN). Default 0.02.
    pub lidar_dropout: f64,
    /// Forward offset of the LiDAR from the base, metres. Default 0.2.
    pub lidar_forward_offset: f64,
    /// Odometry readings per second. Default 50.
    pub odometry_rate_hz: f64,
    /// Standard deviation of the per-session wheel scale error (fraction). Default 0.01.
    pub odometry_scale_sigma: f64,
    /// Standard deviation of the per-session yaw scale error (fraction). Default 0.01.
    pub odometry_yaw_scale_sigma: f64,
    /// Random-walk noise of odometry translation, m per √m travelled. Default 0.01.
    pub odometry_translation_noise: f64,
    /// Random-walk noise of odometry yaw, rad per √rad turned. Default 0.01.
    pub odometry_rotation_noise: f64,
    /// IMU readings per second. Default 100.
    pub imu_rate_hz: f64,
    /// Standard deviation of the per-session gyro bias, rad/s. Default 0.002.
    pub imu_bias_sigma: f64,
    /// Standard deviation of the gyro noise, rad/s. Default 0.01.
    pub imu_noise_sigma: f64,
    /// Later sessions start where the previous one ended (the robot docks there and cleans on from it the
    /// next day), except those carried elsewhere (`carried_fraction`). Session 1 always starts elsewhere
    /// (the robot is put on its route after the mapping run). Default false: every later session starts
    /// at a seeded random place on the route.
    pub dock_starts: bool,
    /// With `dock_starts`, the share of later sessions that start at a seeded random place instead
    /// (the robot was carried), 0–1. Default 0.2.
    pub carried_fraction: f64,
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            speed: 1.0,
            turn_rate: 0.8,
            mapping_max_duration_s: 0.0,
            max_duration_s: 300.0,
            lidar_fov: 270f64.to_radians(),
            lidar_angle_increment: 0.33f64.to_radians(),
            lidar_rate_hz: 15.0,
            lidar_range_max: 25.0,
            lidar_range_sigma: 0.015,
            lidar_dropout: 0.02,
            lidar_forward_offset: 0.2,
            odometry_rate_hz: 50.0,
            odometry_scale_sigma: 0.01,
            odometry_yaw_scale_sigma: 0.01,
            odometry_translation_noise: 0.01,
            odometry_rotation_noise: 0.01,
            imu_rate_hz: 100.0,
            imu_bias_sigma: 0.002,
            imu_noise_sigma: 0.01,
            dock_starts: false,
            carried_fraction: 0.2,
        }
    }
}

impl SessionOptions {
    /// Checks that rates, speeds and ranges are positive and noise levels non-negative.
    pub fn validate(&self) -> Result<(), SimulationError> {
        let positive = [
            ("speed", self.speed),
            ("turn_rate", self.turn_rate),
            ("max_duration_s", self.max_duration_s),
            ("lidar_fov", self.lidar_fov),
            ("lidar_angle_increment", self.lidar_angle_increment),
            ("lidar_rate_hz", self.lidar_rate_hz),
            ("lidar_range_max", self.lidar_range_max),
            ("odometry_rate_hz", self.odometry_rate_hz),
            ("imu_rate_hz", self.imu_rate_hz),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(SimulationError::InvalidOption {
                    field,
                    reason: "must be finite and > 0".into(),
                });
            }
        }
        let non_negative = [
            ("mapping_max_duration_s", self.mapping_max_duration_s),
            ("lidar_range_sigma", self.lidar_range_sigma),
            ("lidar_forward_offset", self.lidar_forward_offset),
            ("odometry_scale_sigma", self.odometry_scale_sigma),
            ("odometry_yaw_scale_sigma", self.odometry_yaw_scale_sigma),
            (
                "odometry_translation_noise",
                self.odometry_translation_noise,
            ),
            ("odometry_rotation_noise", self.odometry_rotation_noise),
            ("imu_bias_sigma", self.imu_bias_sigma),
            ("imu_noise_sigma", self.imu_noise_sigma),
        ];
        if !(0.0..=1.0).contains(&self.carried_fraction) {
            return Err(SimulationError::InvalidOption {
                field: "carried_fraction",
                reason: "must be in [0, 1]".into(),
            });
        }
        for (field, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(SimulationError::InvalidOption {
                    field,
                    reason: "must be finite and >= 0".into(),
                });
            }
        }
        if !(0.0..1.0).contains(&self.lidar_dropout) {
            return Err(SimulationError::InvalidOption {
                field: "lidar_dropout",
                reason: "must be in [0, 1)".into(),
            });
        }
        if self.lidar_fov > std::f64::consts::TAU {
            return Err(SimulationError::InvalidOption {
                field: "lidar_fov",
                reason: "must be at most 2π".into(),
            });
        }
        Ok(())
    }
}
