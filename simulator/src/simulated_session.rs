//! One simulated session: the robot drives its route; LiDAR, wheel odometry and gyro observe it.

use mapping::geometry::{Rigid2, Rigid2Ext as _, normalize_angle, rigid2};
use mapping::sensor::{ImuReading, LaserScan, OdometryReading, SensorEvent, Timestamp};
use nalgebra::{Point2, Vector2};
use rand::Rng as _;
use rand_pcg::Pcg64;

use super::ray_caster::{RayCaster, intersect_disc};
use super::store::{Store, WalkerShape};
use super::{SessionOptions, SimulationError};

/// Stamps of session `k` start on day `k` of the simulated calendar at 06:00 (2026-01-05 is day 0), so
/// stamps never repeat across sessions.
const DAY_ZERO_S: i64 = 1_767_571_200 + 6 * 3600;
/// Ground truth is integrated at this rate, Hz.
const TRUTH_RATE_HZ: f64 = 100.0;

/// What a simulated session produced.
#[derive(Clone, Debug)]
pub struct SimulatedSession {
    /// The session index (0 = the mapping run).
    pub index: u32,
    /// Time-ordered scans, odometry and IMU readings, exactly like a recording.
    pub events: Vec<SensorEvent>,
    /// `base_from_laser`.
    pub base_from_laser: Rigid2,
    /// `world_from_base` at every scan time (truth; not for SLAM).
    pub ground_truth: Vec<(Timestamp, Rigid2)>,
    /// Distance driven, metres.
    pub distance_m: f64,
    /// `world_from_base` at the start (truth; not for SLAM).
    pub start_pose: Rigid2,
    /// Whether it starts exactly where the previous session ended ([`SessionOptions::dock_starts`]).
    pub starts_at_previous_end: bool,
    /// Duration, seconds.
    pub duration_s: f64,
}

fn gaussian(rng: &mut Pcg64) -> f64 {
    // Box–Muller.
    let u1: f64 = rng.random::<f64>().max(f64::MIN_POSITIVE);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// The truth trajectory at [`TRUTH_RATE_HZ`]: turn in place toward each waypoint, then drive to it.
fn drive(route: &[Point2<f64>], options: &SessionOptions, max_duration_s: f64) -> Vec<Rigid2> {
    let dt = 1.0 / TRUTH_RATE_HZ;
    let Some(first) = route.first() else {
        return Vec::new();
    };
    let mut heading = route
        .get(1)
        .map_or(0.0, |p| (p.y - first.y).atan2(p.x - first.x));
    let mut position = *first;
    let max_steps = if max_duration_s > 0.0 {
        (max_duration_s * TRUTH_RATE_HZ) as usize
    } else {
        usize::MAX
    };
    let mut poses = vec![rigid2(position.x, position.y, heading)];
    for target in &route[1..] {
        let delta = target - position;
        if delta.norm() < 1e-9 {
            continue;
        }
        let goal = delta.y.atan2(delta.x);
        loop {
            let error = normalize_angle(goal - heading);
            if error.abs() < 1e-9 || poses.len() >= max_steps {
                break;
            }
            heading += error.signum() * error.abs().min(options.turn_rate * dt);
            poses.push(rigid2(position.x, position.y, heading));
        }
        heading = goal;
        loop {
            let remaining = target - position;
            if remaining.norm() < 1e-9 || poses.len() >= max_steps {
                break;
            }
            let step = remaining.norm().min(options.speed * dt);
            position += remaining.normalize() * step;
            poses.push(rigid2(position.x, position.y, heading));
        }
        if poses.len() >= max_steps {
            break;
        }
    }
    poses
}

/// Interpolates the truth at `t` seconds after the start.
fn truth_at(poses: &[Rigid2], t: f64) -> Rigid2 {
    let s = (t * TRUTH_RATE_HZ).max(0.0);
    let i = (s.floor() as usize).min(poses.len() - 1);
    let j = (i + 1).min(poses.len() - 1);
    let f = s - i as f64;
    let (a, b) = (poses[i], poses[j]);
    let translation = a.translation.vector * (1.0 - f) + b.translation.vector * f;
    let theta = a.theta() + f * normalize_angle(b.theta() - a.theta());
    rigid2(translation.x, translation.y, theta)
}

/// Runs session `index` of `store`.
pub(crate) fn simulate(
    store: &Store,
    index: u32,
    options: &SessionOptions,
    mut rng: Pcg64,
) -> Result<SimulatedSession, SimulationError> {
    let max_duration = if index == 0 {
        options.mapping_max_duration_s
    } else {
        options.max_duration_s
    };
    let laps = if index == 0 { 1 } else { 8 };
    let chain_start = dock_chain_start(store, index, options);
    let truth = if chain_start == index {
        drive(&store.route(index, laps), options, max_duration)
    } else {
        // One robot cleaning on from where it stopped: the sessions since the chain's start are one
        // drive along the chain's first route, cut into sessions of `max_duration` each.
        let sessions = f64::from(index - chain_start + 1);
        let all = drive(
            &store.route(chain_start, laps * (index - chain_start + 1) as usize),
            options,
            max_duration * sessions,
        );
        // The sessions before it drove as many steps as `drive` gives their chain (the same rounding);
        // this one starts at their last pose.
        let skip = ((max_duration * (sessions - 1.0)) * TRUTH_RATE_HZ) as usize - 1;
        all.get(skip..).map(<[Rigid2]>::to_vec).unwrap_or_default()
    };
    if truth.len() < 2 {
        return Err(SimulationError::EmptyRoute);
    }
    let duration = (truth.len() - 1) as f64 / TRUTH_RATE_HZ;
    let start = Timestamp(DAY_ZERO_S * 1_000_000_000).offset_by(86_400.0 * f64::from(index));
    let stamp = |t: f64| start.offset_by(t);
    let mut events = Vec::new();

    // IMU: truth yaw rate + per-session bias + white noise.
    let bias = options.imu_bias_sigma * gaussian(&mut rng);
    let imu_dt = 1.0 / options.imu_rate_hz;
    let mut t = imu_dt;
    while t <= duration {
        let rate =
            normalize_angle(truth_at(&truth, t).theta() - truth_at(&truth, t - imu_dt).theta())
                / imu_dt;
        events.push(SensorEvent::Imu(ImuReading {
            time: stamp(t),
            yaw_rate: rate + bias + options.imu_noise_sigma * gaussian(&mut rng),
        }));
        t += imu_dt;
    }

    // Wheel odometry: truth increments with per-session scale errors and random-walk noise.
    let scale = 1.0 + options.odometry_scale_sigma * gaussian(&mut rng);
    let yaw_scale = 1.0 + options.odometry_yaw_scale_sigma * gaussian(&mut rng);
    let odom_dt = 1.0 / options.odometry_rate_hz;
    let mut odom = Rigid2::identity();
    let mut previous = truth[0];
    let mut distance = 0.0;
    events.push(SensorEvent::Odometry(OdometryReading {
        time: stamp(0.0),
        pose: odom,
    }));
    let mut t = odom_dt;
    while t <= duration {
        let now = truth_at(&truth, t);
        let delta = previous.inverse() * now;
        let (dx, dy, dtheta) = (
            delta.translation.x,
            delta.translation.y,
            normalize_angle(delta.theta()),
        );
        let moved = dx.hypot(dy);
        distance += moved;
        let measured = rigid2(
            dx * scale + options.odometry_translation_noise * moved.sqrt() * gaussian(&mut rng),
            dy * scale,
            dtheta * yaw_scale
                + options.odometry_rotation_noise * dtheta.abs().sqrt() * gaussian(&mut rng),
        );
        odom *= measured;
        events.push(SensorEvent::Odometry(OdometryReading {
            time: stamp(t),
            pose: odom,
        }));
        previous = now;
        t += odom_dt;
    }

    // LiDAR.
    let caster = RayCaster::new(store.obstacles(index), 1.0);
    let walkers = store.walkers(index);
    let base_from_laser = rigid2(options.lidar_forward_offset, 0.0, 0.0);
    let beams = (options.lidar_fov / options.lidar_angle_increment).floor() as usize + 1;
    let angle_min = -0.5 * options.lidar_fov;
    let range_max = options.lidar_range_max;
    let scan_dt = 1.0 / options.lidar_rate_hz;
    let mut ground_truth = Vec::new();
    let mut t = 0.0;
    while t <= duration {
        let world_from_base = truth_at(&truth, t);
        let world_from_laser = world_from_base * base_from_laser;
        let origin = Point2::from(world_from_laser.translation.vector);
        let near: Vec<WalkerShape> = walkers
            .iter()
            .filter(|w| (w.position(t) - origin).norm() < range_max + 1.0)
            .map(|w| w.shape(t))
            .collect();
        let heading = world_from_laser.theta();
        let ranges = (0..beams)
            .map(|k| {
                let a = heading + angle_min + k as f64 * options.lidar_angle_increment;
                let direction = Vector2::new(a.cos(), a.sin());
                let mut range = caster
                    .cast(&origin, &direction, range_max)
                    .unwrap_or(f64::INFINITY);
                for shape in &near {
                    let hit = match shape {
                        WalkerShape::Disc(c, r) => intersect_disc(c, *r, &origin, &direction),
                        WalkerShape::Box(b) => b.intersect(&origin, &direction),
                    };
                    if let Some(h) = hit {
                        range = range.min(h);
                    }
                }
                if rng.random::<f64>() < options.lidar_dropout {
                    f32::NAN
                } else if range > range_max {
                    f32::INFINITY
                } else {
                    let noisy = range + options.lidar_range_sigma * gaussian(&mut rng);
                    (noisy.clamp(0.05, range_max)) as f32
                }
            })
            .collect();
        events.push(SensorEvent::Scan(LaserScan {
            time: stamp(t),
            angle_min: angle_min as f32,
            angle_increment: options.lidar_angle_increment as f32,
            time_increment: 0.0,
            range_min: 0.05,
            range_max: range_max as f32,
            ranges,
        }));
        ground_truth.push((stamp(t), world_from_base));
        t += scan_dt;
    }
    events.sort_by_key(SensorEvent::time);
    Ok(SimulatedSession {
        index,
        events,
        base_from_laser,
        ground_truth,
        distance_m: distance,
        start_pose: truth[0],
        starts_at_previous_end: chain_start != index,
        duration_s: duration,
    })
}

/// The session whose seeded start the robot of session `index` has been cleaning on from: `index` itself
/// unless [`SessionOptions::dock_starts`] chains it to the sessions before it. Sessions 0 and 1 and
/// carried sessions start chains.
fn dock_chain_start(store: &Store, index: u32, options: &SessionOptions) -> u32 {
    if !options.dock_starts {
        return index;
    }
    let carried = |session: u32| {
        session <= 1
            || super::store::seeded(store.seed(), 950_000 + u64::from(session))
                .random_bool(options.carried_fraction)
    };
    (1..=index).rev().find(|&s| carried(s)).unwrap_or(index)
}
