//! Back to the robot's navigation over ROS 2 (rmw_zenoh, no ROS install): the map as
//! `nav_msgs/msg/OccupancyGrid` on `/map`, the global pose as the `map -> odom` transform on `/tf` and as
//! `geometry_msgs/msg/PoseWithCovarianceStamped` on a configurable topic, CDR-encoded
//! (`source::ros2_nav_messages`) under rmw_zenoh's key expressions with its attachment
//! (`source::rmw_zenoh`), and announced in the ROS graph by liveliness tokens.
//!
//! **`/map` as a latched topic.** Nav2's map server publishes `/map` with durability `TRANSIENT_LOCAL`,
//! depth 1: a subscriber that starts later still gets the current map. rmw_zenoh implements that with
//! zenoh-ext (a publication cache answering the queries of querying subscribers; an advanced publisher's
//! cache in later releases), which this agent does not link (it would add zenoh-ext and zenoh's
//! `unstable` API to the build). The agent approximates it in two ways any zenoh subscriber
//! sees: (1) a queryable on the map's key answers every query with the latest map (a late joiner that
//! queries the key on start — as a querying subscriber does — gets it at once), and (2) the latest map
//! is published again every `map_republish_s` seconds, so a plain late subscriber has it within that
//! time. Whether Nav2 on rmw_zenoh's own transient-local subscription takes the map on start through
//! (1) has not been checked here (there is no ROS on this machine); through (2) it does, as for any
//! subscriber.
//!
//! **The pose.** At each scan LLO matches, `map_from_base` is global SLAM's latest `map_from_local`
//! times LLO's `local_from_base`; with `odom_from_base` the robot's odometry interpolated at the scan's
//! stamp, the transform sent is `map_from_odom = map_from_base · odom_from_base⁻¹` (what AMCL or
//! Cartographer publish, so that `map -> odom -> base_link` gives the robot's pose). The covariance is
//! a nominal one from the options, not an estimate.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;
use mapping::sensor::{OdometryReading, Timestamp};
use serde::{Deserialize, Serialize};
use zenoh::Wait as _;

use crate::offline_slam::SlamObserver;
use crate::source::rmw_zenoh::{self, Attachment, Durability, RosType};
use crate::source::ros2_nav_messages::{self, StampedTransform};

/// What the agent publishes back to ROS 2, and where (the `[ros2.publish]` section).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Ros2PublisherOptions {
    /// Publish at all. Default true.
    pub enabled: bool,
    /// The map (`nav_msgs/msg/OccupancyGrid`). Default `/map`.
    pub map_topic: String,
    /// The global pose (`geometry_msgs/msg/PoseWithCovarianceStamped`). Default `/evermap/pose`.
    pub pose_topic: String,
    /// Where `map -> odom` goes (`tf2_msgs/msg/TFMessage`). Default `/tf`.
    pub tf_topic: String,
    /// The map's frame id. Default `map`.
    pub map_frame: String,
    /// The odometry frame id. Default `odom`.
    pub odom_frame: String,
    /// The node name the agent shows in the ROS graph. Default `evermap_agent`.
    pub node_name: String,
    /// Seconds between re-publications of the latest map (see the module docs); 0: never. Default 5.
    pub map_republish_s: f64,
    /// Cell size of the published map, metres. Default 0.05.
    pub map_resolution_m: f64,
    /// Nominal standard deviation of the published pose's x and y, metres. Default 0.05.
    pub pose_sigma_xy_m: f64,
    /// Nominal standard deviation of the published pose's yaw, radians. Default 0.02.
    pub pose_sigma_yaw_rad: f64,
}

impl Default for Ros2PublisherOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            map_topic: "/map".into(),
            pose_topic: "/evermap/pose".into(),
            tf_topic: "/tf".into(),
            map_frame: "map".into(),
            odom_frame: "odom".into(),
            node_name: "evermap_agent".into(),
            map_republish_s: 5.0,
            map_resolution_m: 0.05,
            pose_sigma_xy_m: 0.05,
            pose_sigma_yaw_rad: 0.02,
        }
    }
}

/// Why the publisher cannot start.
#[derive(Debug, thiserror::Error)]
pub enum Ros2PublishError {
    /// An option is out of range.
    #[error("invalid [ros2.publish] option {field}: {reason}")]
    Invalid {
        /// The option.
        field: &'static str,
        /// Why.
        reason: String,
    },
    /// A topic name cannot be published on.
    #[error(transparent)]
    Name(#[from] rmw_zenoh::RosNameError),
    /// Zenoh refused a declaration.
    #[error("zenoh: {what}: {source}")]
    Zenoh {
        /// What was declared.
        what: String,
        /// Why.
        source: zenoh::Error,
    },
}

impl Ros2PublisherOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), Ros2PublishError> {
        let invalid = |field, reason: String| Ros2PublishError::Invalid { field, reason };
        for topic in [&self.map_topic, &self.pose_topic, &self.tf_topic] {
            rmw_zenoh::topic_key(0, topic, rmw_zenoh::TF_MESSAGE.name, "*")?;
        }
        for (field, frame) in [
            ("map_frame", &self.map_frame),
            ("odom_frame", &self.odom_frame),
            ("node_name", &self.node_name),
        ] {
            if frame.is_empty()
                || !frame
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'_')
            {
                return Err(invalid(
                    field,
                    format!("{frame:?} must be letters, digits and underscores"),
                ));
            }
        }
        if !(self.map_republish_s.is_finite() && (0.0..=3600.0).contains(&self.map_republish_s)) {
            return Err(invalid(
                "map_republish_s",
                "must be in 0..=3600 seconds".into(),
            ));
        }
        if !(self.map_resolution_m.is_finite() && (0.01..=1.0).contains(&self.map_resolution_m)) {
            return Err(invalid(
                "map_resolution_m",
                "must be in 0.01..=1 metres".into(),
            ));
        }
        for (field, v) in [
            ("pose_sigma_xy_m", self.pose_sigma_xy_m),
            ("pose_sigma_yaw_rad", self.pose_sigma_yaw_rad),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(
                    field,
                    format!("must be a positive number, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

/// What was published.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct PublishStats {
    /// Map versions published (re-publications not counted).
    pub map_versions: u64,
    /// Map publications, re-publications included.
    pub map_publications: u64,
    /// Map queries answered.
    pub map_queries_answered: u64,
    /// Poses (and as many `map -> odom` transforms) published.
    pub poses: u64,
    /// Publications zenoh refused.
    pub failed: u64,
}

/// One rmw_zenoh publisher: its key, GID and sequence number.
struct Topic {
    publisher: zenoh::pubsub::Publisher<'static>,
    gid: [u8; 16],
    sequence: i64,
}

fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

impl Topic {
    fn attachment(&mut self) -> Vec<u8> {
        self.sequence += 1;
        Attachment {
            sequence_number: self.sequence,
            source_timestamp_ns: now_ns(),
            source_gid: self.gid,
        }
        .encode()
    }

    fn put(&mut self, payload: Vec<u8>) -> bool {
        let attachment = self.attachment();
        self.publisher
            .put(payload)
            .attachment(attachment)
            .wait()
            .is_ok()
    }
}

/// A GID for the entity `entity_id` of the session `zid`: 12 bytes of the session id (by which the
/// live source recognises the agent's own publications), then the entity id.
fn gid(zid: &zenoh::session::ZenohId, entity_id: u32) -> [u8; 16] {
    let mut gid = [0u8; 16];
    gid[..12].copy_from_slice(&crate::source::own_gid_prefix(zid));
    gid[12..].copy_from_slice(&entity_id.to_le_bytes());
    gid
}

/// The latest map's payload, shared with the queryable.
type LatestMap = Arc<Mutex<Option<(Vec<u8>, [u8; 16])>>>;

/// Publishes the map and the pose (see the module docs).
pub struct Ros2Publisher {
    options: Ros2PublisherOptions,
    map: Topic,
    tf: Topic,
    pose: Topic,
    latest_map: LatestMap,
    map_sent_at: Option<Instant>,
    queries: Arc<Mutex<u64>>,
    stats: PublishStats,
    _queryable: zenoh::query::Queryable<()>,
    _tokens: Vec<zenoh::liveliness::LivelinessToken>,
}

impl Ros2Publisher {
    /// Declares the publishers, the map's queryable and the liveliness tokens on `session`, in
    /// `domain_id`. Do not call from inside an async runtime.
    pub fn open(
        session: &zenoh::Session,
        domain_id: u32,
        options: &Ros2PublisherOptions,
    ) -> Result<Self, Ros2PublishError> {
        options.validate()?;
        let zid = session.zid();
        let zid_text = zid.to_string();
        let node_id = 0;
        let zenoh_error = |what: &str, source: zenoh::Error| Ros2PublishError::Zenoh {
            what: what.to_owned(),
            source,
        };
        let mut tokens = vec![
            session
                .liveliness()
                .declare_token(rmw_zenoh::node_token(
                    domain_id,
                    &zid_text,
                    node_id,
                    "/",
                    &options.node_name,
                ))
                .wait()
                .map_err(|e| zenoh_error("node liveliness token", e))?,
        ];
        let mut declare = |entity_id: u32,
                           topic: &str,
                           ros_type: &RosType,
                           durability: Durability|
         -> Result<Topic, Ros2PublishError> {
            let key = rmw_zenoh::topic_key(domain_id, topic, ros_type.name, ros_type.hash)?;
            // The map waits for a congested link (it is sent rarely and must arrive, as a reliable
            // depth-1 topic); the pose and `/tf` are dropped under congestion, the newer one supersedes
            // them (zenoh's default, and rmw_zenoh's for keep-last topics).
            let congestion = if durability == Durability::TransientLocal {
                zenoh::qos::CongestionControl::Block
            } else {
                zenoh::qos::CongestionControl::Drop
            };
            let publisher = session
                .declare_publisher(key.clone())
                .congestion_control(congestion)
                .wait()
                .map_err(|e| zenoh_error(&format!("publisher on {key}"), e))?;
            let token = rmw_zenoh::publisher_token(
                domain_id,
                &zid_text,
                node_id,
                entity_id,
                &options.node_name,
                topic,
                ros_type,
                durability,
                if durability == Durability::TransientLocal {
                    1
                } else {
                    10
                },
            )?;
            tokens.push(
                session
                    .liveliness()
                    .declare_token(token)
                    .wait()
                    .map_err(|e| zenoh_error("publisher liveliness token", e))?,
            );
            Ok(Topic {
                publisher,
                gid: gid(&zid, entity_id),
                sequence: 0,
            })
        };
        let map = declare(
            1,
            &options.map_topic,
            &rmw_zenoh::OCCUPANCY_GRID,
            Durability::TransientLocal,
        )?;
        let tf = declare(
            2,
            &options.tf_topic,
            &rmw_zenoh::TF_MESSAGE,
            Durability::Volatile,
        )?;
        let pose = declare(
            3,
            &options.pose_topic,
            &rmw_zenoh::POSE_WITH_COVARIANCE_STAMPED,
            Durability::Volatile,
        )?;
        let latest_map: LatestMap = Arc::new(Mutex::new(None));
        let queries = Arc::new(Mutex::new(0u64));
        let map_key = map.publisher.key_expr().clone().into_owned();
        let queryable = {
            let latest_map = Arc::clone(&latest_map);
            let queries = Arc::clone(&queries);
            let reply_key = map_key.clone();
            session
                .declare_queryable(map_key.clone())
                .callback(move |query| {
                    let latest = latest_map.lock().ok().and_then(|m| m.clone());
                    if let Some((payload, gid)) = latest {
                        let attachment = Attachment {
                            sequence_number: 1,
                            source_timestamp_ns: now_ns(),
                            source_gid: gid,
                        }
                        .encode();
                        if query
                            .reply(reply_key.clone(), payload)
                            .attachment(attachment)
                            .wait()
                            .is_ok()
                            && let Ok(mut n) = queries.lock()
                        {
                            *n += 1;
                        }
                    }
                })
                .wait()
                .map_err(|e| zenoh_error(&format!("queryable on {map_key}"), e))?
        };
        Ok(Self {
            options: options.clone(),
            map,
            tf,
            pose,
            latest_map,
            map_sent_at: None,
            queries,
            stats: PublishStats::default(),
            _queryable: queryable,
            _tokens: tokens,
        })
    }

    /// What was published so far.
    pub fn stats(&self) -> PublishStats {
        let mut stats = self.stats.clone();
        stats.map_queries_answered = self.queries.lock().map_or(0, |n| *n);
        stats
    }

    /// Publishes a new map version (and keeps it for late joiners).
    pub fn publish_map(&mut self, grid: &ProbabilityGrid, stamp: Timestamp) {
        let payload = ros2_nav_messages::occupancy_grid(grid, stamp, &self.options.map_frame);
        if let Ok(mut latest) = self.latest_map.lock() {
            *latest = Some((payload.clone(), self.map.gid));
        }
        self.stats.map_versions += 1;
        self.send_map(payload);
    }

    fn send_map(&mut self, payload: Vec<u8>) {
        self.map_sent_at = Some(Instant::now());
        if self.map.put(payload) {
            self.stats.map_publications += 1;
        } else {
            self.stats.failed += 1;
        }
    }

    /// Publishes the latest map again if `map_republish_s` has passed since it was last sent.
    pub fn republish_map_if_due(&mut self) {
        let Ok(period) = Duration::try_from_secs_f64(self.options.map_republish_s) else {
            return;
        };
        if period.is_zero() || self.map_sent_at.is_none_or(|at| at.elapsed() < period) {
            return;
        }
        let latest = self.latest_map.lock().ok().and_then(|m| m.clone());
        if let Some((payload, _)) = latest {
            self.send_map(payload);
        }
    }

    /// Publishes the robot's global pose at `stamp`: `map_from_base` on the pose topic and, when
    /// known, `map_from_odom` on `/tf`.
    pub fn publish_pose(
        &mut self,
        stamp: Timestamp,
        map_from_base: &Rigid2,
        map_from_odom: Option<&Rigid2>,
    ) {
        let tf = map_from_odom.map(|map_from_odom| {
            ros2_nav_messages::tf_message(&[StampedTransform {
                stamp,
                parent: self.options.map_frame.clone(),
                child: self.options.odom_frame.clone(),
                parent_from_child: *map_from_odom,
            }])
        });
        let pose = ros2_nav_messages::pose_with_covariance_stamped(
            stamp,
            &self.options.map_frame,
            map_from_base,
            self.options.pose_sigma_xy_m,
            self.options.pose_sigma_yaw_rad,
        );
        if tf.is_none_or(|tf| self.tf.put(tf)) && self.pose.put(pose) {
            self.stats.poses += 1;
        } else {
            self.stats.failed += 1;
        }
    }
}

/// `a` and `b` interpolated at `t` in [0, 1] (translation linearly, rotation along the shorter arc).
fn interpolate(a: &Rigid2, b: &Rigid2, t: f64) -> Rigid2 {
    let translation = a.translation.vector + (b.translation.vector - a.translation.vector) * t;
    let turn = (b.rotation * a.rotation.inverse()).angle();
    Rigid2::new(translation, a.rotation.angle() + turn * t)
}

/// The odometry pose at `time` from the two latest readings (interpolated between them, or the nearest
/// one outside them).
fn odom_at(previous: Option<&OdometryReading>, last: &OdometryReading, time: Timestamp) -> Rigid2 {
    match previous {
        Some(p) if p.time < last.time && time > p.time && time < last.time => {
            let t = time.seconds_since(p.time) / last.time.seconds_since(p.time);
            interpolate(&p.pose, &last.pose, t)
        }
        Some(p) if time <= p.time => p.pose,
        _ => last.pose,
    }
}

/// `odom_from_base` at `time` from `history` (readings in stamp order): interpolated between the
/// readings on either side, `None` outside them.
pub fn odom_from_base_at(
    history: &std::collections::VecDeque<OdometryReading>,
    time: Timestamp,
) -> Option<Rigid2> {
    let after = history.iter().position(|r| r.time >= time)?;
    let next = &history[after];
    if next.time == time {
        return Some(next.pose);
    }
    let previous = history.get(after.checked_sub(1)?)?;
    Some(odom_at(Some(previous), next, time))
}

/// A [`SlamObserver`] that publishes SLAM's map and pose live (see the module docs).
pub struct Ros2SlamPublisher {
    publisher: Ros2Publisher,
    odometry: [Option<OdometryReading>; 2],
    last_stamp: Option<Timestamp>,
}

impl Ros2SlamPublisher {
    /// Publishes through `publisher`.
    pub fn new(publisher: Ros2Publisher) -> Self {
        Self {
            publisher,
            odometry: [None, None],
            last_stamp: None,
        }
    }

    /// The publisher (for its stats, or a last map).
    pub fn publisher_mut(&mut self) -> &mut Ros2Publisher {
        &mut self.publisher
    }
}

impl SlamObserver for Ros2SlamPublisher {
    fn odometry(&mut self, reading: &OdometryReading) {
        self.odometry = [self.odometry[1].take(), Some(reading.clone())];
    }

    fn scan_matched(&mut self, time: Timestamp, local_from_base: &Rigid2, map_from_local: &Rigid2) {
        let map_from_base = map_from_local * local_from_base;
        // Without odometry, LLO's local frame stands in for `odom`.
        let map_from_odom = match &self.odometry {
            [previous, Some(last)] => {
                map_from_base * odom_at(previous.as_ref(), last, time).inverse()
            }
            _ => *map_from_local,
        };
        self.last_stamp = Some(time);
        self.publisher
            .publish_pose(time, &map_from_base, Some(&map_from_odom));
        self.publisher.republish_map_if_due();
    }

    fn optimized(&mut self, _optimizations: usize, map: Option<&ProbabilityGrid>) {
        if let Some(map) = map {
            let stamp = self.last_stamp.unwrap_or(Timestamp(0));
            self.publisher.publish_map(map, stamp);
        }
    }

    fn map_resolution(&self) -> Option<f64> {
        Some(self.publisher.options.map_resolution_m)
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    #[test]
    fn odometry_is_interpolated_at_the_scan() {
        let a = OdometryReading {
            time: Timestamp::from_secs_f64(1.0),
            pose: rigid2(0.0, 0.0, 3.0),
        };
        let b = OdometryReading {
            time: Timestamp::from_secs_f64(2.0),
            pose: rigid2(2.0, 0.0, -3.1), // across ±π: the short way round
        };
        let mid = odom_at(Some(&a), &b, Timestamp::from_secs_f64(1.5));
        assert!((mid.translation.x - 1.0).abs() < 1e-12);
        let expected = 3.0 + (2.0 * std::f64::consts::PI - 6.1) / 2.0;
        assert!(
            (mid.rotation.angle() - expected).abs() < 1e-9,
            "{}",
            mid.rotation.angle()
        );
        assert_eq!(odom_at(Some(&a), &b, Timestamp::from_secs_f64(0.5)), a.pose);
        assert_eq!(odom_at(Some(&a), &b, Timestamp::from_secs_f64(2.5)), b.pose);
        assert_eq!(odom_at(None, &b, Timestamp::from_secs_f64(0.5)), b.pose);
    }

    #[test]
    fn odometry_history_is_interpolated_inside_and_refused_outside() {
        let history: std::collections::VecDeque<OdometryReading> = (0..3)
            .map(|i| OdometryReading {
                time: Timestamp::from_secs_f64(f64::from(i)),
                pose: rigid2(f64::from(i), 0.0, 0.0),
            })
            .collect();
        let at = |t| odom_from_base_at(&history, Timestamp::from_secs_f64(t));
        assert!((at(1.25).unwrap().translation.x - 1.25).abs() < 1e-12);
        assert_eq!(at(2.0).unwrap(), history[2].pose);
        assert!(at(-0.5).is_none() && at(2.5).is_none());
    }

    #[test]
    fn options_are_checked() {
        Ros2PublisherOptions::default().validate().unwrap();
        for bad in [
            Ros2PublisherOptions {
                map_topic: "map".into(),
                ..Ros2PublisherOptions::default()
            },
            Ros2PublisherOptions {
                odom_frame: "od om".into(),
                ..Ros2PublisherOptions::default()
            },
            Ros2PublisherOptions {
                map_republish_s: -1.0,
                ..Ros2PublisherOptions::default()
            },
            Ros2PublisherOptions {
                pose_sigma_xy_m: 0.0,
                ..Ros2PublisherOptions::default()
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }
}
