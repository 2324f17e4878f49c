//! Live ROS 2 input over zenoh, with no ROS installed: the robot's `/scan`, `/odom` (and optionally an IMU),
//! `/tf` and `/tf_static` as rmw_zenoh publishes them (see [`super::rmw_zenoh`] for the wire format),
//! decoded by the same CDR decoders and the same [`RosCollector`] as a rosbag2 recording, and handed on
//! as the same [`SensorEvent`]s, in the order LLO takes them ([`LloCollator`]), through
//! [`SensorStream`]: the SLAM driver (`offline_slam::run_slam`) runs on a live robot exactly as on a file.
//!
//! What a live stream adds, and how it is handled:
//! - **Arrival order is not stamp order** across topics (and a laser driver may stamp late). Events wait
//!   in a reorder buffer until the newest stamp seen is `reorder_window_s` past theirs, then leave in
//!   stamp order, so within that window the stream is sorted as a recording is. An event that arrives
//!   later than that, or repeats its stream's last stamp, is dropped and counted (a recording's reader
//!   re-sorts or drops the same ones). The buffer holds at most `queue_capacity` events: past that the
//!   oldest leave early (deciding the mount if need be), so a robot whose clock stands still, or that sends
//!   odometry and no scan, cannot grow it without bound.
//! - **The laser's mounting pose** comes from `/tf_static` (or `/tf`), which may arrive after the first
//!   scans: nothing leaves the buffer until a transform to the first scan's frame is known, or
//!   `mount_wait_s` of stream time has passed (then identity, said in the stats).
//! - **Back-pressure**: zenoh's receive threads only push raw samples into a bounded queue
//!   (`queue_capacity`); when SLAM falls that far behind, new samples are dropped and counted, never
//!   blocking zenoh. Gaps in a publisher's sequence numbers (rmw_zenoh's attachment) are counted too:
//!   messages lost before they reached the agent.
//! - **The end**: the stream ends `until_idle_s` seconds (wall time) after the last scan arrived, or if no
//!   scan arrives within `start_timeout_s`; everything still buffered is then handed on.

mod arrival_counters;
mod live_decoder;

use std::collections::BTreeMap;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mapping::geometry::Rigid2;
use mapping::sensor::SensorEvent;
use serde::{Deserialize, Serialize};
use zenoh::Wait as _;

pub use arrival_counters::{ArrivalCounters, MAX_TRACKED_PUBLISHERS};
pub use live_decoder::{LiveDecoder, decode_samples};

use super::rmw_zenoh;
use super::sensor_stream::SensorStream;
use crate::uplink::ZenohLinkOptions;

/// Where and how the agent listens to a live ROS 2 robot (the agent config's `[ros2]` section).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Ros2LiveOptions {
    /// ROS domain id (`ROS_DOMAIN_ID`), 0..=232. Default 0.
    pub domain_id: u32,
    /// Laser scans (`sensor_msgs/msg/LaserScan`), fully qualified. Default `/scan`.
    pub scan_topic: String,
    /// Wheel odometry (`nav_msgs/msg/Odometry`). Default `/odom`.
    pub odom_topic: String,
    /// An IMU (`sensor_msgs/msg/Imu`), if LLO should use one. Default none.
    pub imu_topic: Option<String>,
    /// Transforms (`tf2_msgs/msg/TFMessage`). Default `/tf`.
    pub tf_topic: String,
    /// Static transforms. Default `/tf_static`.
    pub tf_static_topic: String,
    /// How to join the robot's zenoh network. Default: a peer connecting to the rmw_zenoh router on this
    /// machine, `tcp/127.0.0.1:7447`, multicast scouting off.
    pub zenoh: ZenohLinkOptions,
    /// Raw messages held between zenoh and SLAM before new ones are dropped (counted); also the most
    /// events the reorder buffer holds (past it the oldest leave, whatever the window). Default 4096.
    pub queue_capacity: usize,
    /// Seconds of stream time an event waits for earlier-stamped ones (see the module docs). Default 0.5.
    pub reorder_window_s: f64,
    /// Seconds of stream time the first scans wait for the laser's transform. Default 2.
    pub mount_wait_s: f64,
    /// `evermap-agent run`: the session ends this many seconds (wall time) after the last scan. Default 30.
    pub until_idle_s: f64,
    /// `evermap-agent run`: give up if no scan comes within this many seconds. Default 600.
    pub start_timeout_s: f64,
    /// What the agent publishes back (`[ros2.publish]`).
    pub publish: crate::ros2_publisher::Ros2PublisherOptions,
}

impl Default for Ros2LiveOptions {
    fn default() -> Self {
        Self {
            domain_id: 0,
            scan_topic: "/scan".into(),
            odom_topic: "/odom".into(),
            imu_topic: None,
            tf_topic: "/tf".into(),
            tf_static_topic: "/tf_static".into(),
            zenoh: ZenohLinkOptions {
                connect: vec!["tcp/127.0.0.1:7447".into()],
                ..ZenohLinkOptions::default()
            },
            queue_capacity: 4096,
            reorder_window_s: 0.5,
            mount_wait_s: 2.0,
            until_idle_s: 30.0,
            start_timeout_s: 600.0,
            publish: crate::ros2_publisher::Ros2PublisherOptions::default(),
        }
    }
}

/// Why a live ROS 2 source cannot start.
#[derive(Debug, thiserror::Error)]
pub enum Ros2LiveError {
    /// An option is out of range.
    #[error("invalid [ros2] option {field}: {reason}")]
    Invalid {
        /// The option.
        field: &'static str,
        /// Why.
        reason: String,
    },
    /// A topic name cannot be subscribed to.
    #[error(transparent)]
    Name(#[from] rmw_zenoh::RosNameError),
    /// The `[ros2.zenoh]` link options are invalid.
    #[error("invalid [ros2] option zenoh: {0}")]
    ZenohOptions(#[source] proto::ZenohLinkOptionsError),
    /// The `[ros2.publish]` options are invalid.
    #[error("invalid [ros2] option publish: {0}")]
    Publish(#[source] crate::ros2_publisher::Ros2PublishError),
    /// Zenoh refused the session or a subscription.
    #[error("zenoh: {what}: {source}")]
    Zenoh {
        /// What was asked of it.
        what: String,
        /// Why.
        source: zenoh::Error,
    },
}

fn invalid(field: &'static str, reason: impl Into<String>) -> Ros2LiveError {
    Ros2LiveError::Invalid {
        field,
        reason: reason.into(),
    }
}

impl Ros2LiveOptions {
    /// Checks every field (topic names against ROS's rules, the zenoh link, the numbers).
    pub fn validate(&self) -> Result<(), Ros2LiveError> {
        if self.domain_id > 232 {
            return Err(invalid(
                "domain_id",
                format!("{} is above 232, the largest ROS domain id", self.domain_id),
            ));
        }
        for (topic, ros_type) in self.topics() {
            rmw_zenoh::topic_key(self.domain_id, &topic, ros_type, "*")?;
        }
        self.zenoh.validate().map_err(Ros2LiveError::ZenohOptions)?;
        if self.queue_capacity == 0 || self.queue_capacity > 1 << 20 {
            return Err(invalid("queue_capacity", "must be in 1..=1048576 messages"));
        }
        for (field, value, max) in [
            ("reorder_window_s", self.reorder_window_s, 10.0),
            ("mount_wait_s", self.mount_wait_s, 60.0),
        ] {
            if !(0.0..=max).contains(&value) {
                return Err(invalid(
                    field,
                    format!("must be in 0..={max} seconds, got {value}"),
                ));
            }
        }
        self.stream_end().validate()?;
        self.publish.validate().map_err(Ros2LiveError::Publish)?;
        Ok(())
    }

    /// When `evermap-agent run` ends a live session (`until_idle_s`, `start_timeout_s`).
    pub fn stream_end(&self) -> StreamEnd {
        StreamEnd {
            until_idle_s: self.until_idle_s,
            start_timeout_s: self.start_timeout_s,
        }
    }

    /// The topics subscribed to, with their types, in the order of their indices (scan, odometry, tf,
    /// tf_static, then the IMU if any).
    pub fn topics(&self) -> Vec<(String, &'static str)> {
        let mut topics = vec![
            (self.scan_topic.clone(), rmw_zenoh::LASER_SCAN.name),
            (self.odom_topic.clone(), rmw_zenoh::ODOMETRY.name),
            (self.tf_topic.clone(), rmw_zenoh::TF_MESSAGE.name),
            (self.tf_static_topic.clone(), rmw_zenoh::TF_MESSAGE.name),
        ];
        if let Some(imu) = &self.imu_topic {
            topics.push((imu.clone(), rmw_zenoh::IMU.name));
        }
        topics
    }
}

/// When a live stream ends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamEnd {
    /// Seconds (wall time) without a scan after the last one, to end the stream.
    pub until_idle_s: f64,
    /// Seconds (wall time) to wait for the first scan before giving up.
    pub start_timeout_s: f64,
}

impl StreamEnd {
    /// Checks both durations are in (0, 86400] seconds.
    pub fn validate(&self) -> Result<(), Ros2LiveError> {
        for (field, value) in [
            ("until_idle_s", self.until_idle_s),
            ("start_timeout_s", self.start_timeout_s),
        ] {
            if !(value.is_finite() && value > 0.0 && value <= 86_400.0) {
                return Err(invalid(
                    field,
                    format!("must be in (0, 86400] seconds, got {value}"),
                ));
            }
        }
        Ok(())
    }
}

/// Counts of one topic.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct TopicCounts {
    /// Samples zenoh delivered.
    pub received: u64,
    /// Decoded into events or transforms.
    pub decoded: u64,
    /// Did not decode (see `problems`).
    pub malformed: u64,
    /// Dropped because the queue to SLAM was full.
    pub dropped_queue_full: u64,
    /// Messages the publishers' sequence numbers say were sent but never arrived.
    pub missed_by_sequence: u64,
    /// Samples without a readable rmw_zenoh attachment (still decoded).
    pub attachment_invalid: u64,
}

/// What a live source received, decoded and dropped.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct LiveStats {
    /// Per topic.
    pub topics: BTreeMap<String, TopicCounts>,
    /// Events dropped for arriving after the reorder window (stamped before their stream's last one).
    pub dropped_late: u64,
    /// Events dropped for repeating their stream's last stamp (a recording's reader drops them too).
    pub repeated_stamp: u64,
    /// Events handed on to SLAM.
    pub events_out: u64,
    /// Scans handed on to SLAM.
    pub scans_out: u64,
    /// Scans of a driver's backlog put back at the times they were taken (`mapping::sensor::ScanBacklog`).
    pub scans_retimed: u64,
    /// The newest stamp (nanoseconds) handed on to SLAM.
    pub newest_stamp_ns: Option<i64>,
    /// Where the laser's mounting pose came from.
    pub extrinsic_source: String,
    /// The first few decoding problems.
    pub problems: Vec<String>,
}

impl LiveStats {
    /// Samples received over every topic.
    pub fn received(&self) -> u64 {
        self.topics.values().map(|t| t.received).sum()
    }

    /// Samples decoded over every topic.
    pub fn decoded(&self) -> u64 {
        self.topics.values().map(|t| t.decoded).sum()
    }

    /// Samples lost on the way in (queue full, sequence gaps, too late to re-sort) or undecodable.
    pub fn dropped(&self) -> u64 {
        self.topics
            .values()
            .map(|t| t.dropped_queue_full + t.missed_by_sequence + t.malformed)
            .sum::<u64>()
            + self.dropped_late
    }
}

/// One raw sample, as zenoh's threads hand it over.
struct Incoming {
    topic: usize,
    payload: Vec<u8>,
}

/// A live ROS 2 robot as a [`SensorStream`] (see the module docs): zenoh's callbacks count each sample
/// ([`ArrivalCounters`]) and queue it; [`LiveDecoder`] decodes and re-sorts them on the caller's thread.
pub struct LiveRos2Source {
    session: zenoh::Session,
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    receiver: mpsc::Receiver<Incoming>,
    arrivals: Arc<Mutex<ArrivalCounters>>,
    decoder: LiveDecoder,
    end: StreamEnd,
    started: Instant,
    last_scan_at: Option<Instant>,
    finished: bool,
}

/// The latest odometry readings handed on (at most 512), shared with whoever needs `odom_from_base` at a
/// past stamp (the `map -> odom` publisher).
pub type OdometryHistory = Arc<Mutex<std::collections::VecDeque<mapping::sensor::OdometryReading>>>;

/// The first 12 bytes of every GID this session's publishers use (`ros2_publisher` builds them so).
pub fn own_gid_prefix(zid: &zenoh::session::ZenohId) -> [u8; 12] {
    let mut prefix = [0u8; 12];
    prefix.copy_from_slice(&zid.to_le_bytes()[..12]);
    prefix
}

/// How long one wait on the queue lasts at most (so the idle timeout is checked).
const POLL: Duration = Duration::from_millis(100);

impl LiveRos2Source {
    /// Joins the zenoh network and subscribes to the robot's topics. Blocks until the subscriptions are
    /// declared (not until data arrives). Do not call from inside an async runtime.
    pub fn open(options: &Ros2LiveOptions, end: StreamEnd) -> Result<Self, Ros2LiveError> {
        options.validate()?;
        end.validate()?;
        let config = options
            .zenoh
            .to_zenoh_config()
            .map_err(Ros2LiveError::ZenohOptions)?;
        let session = zenoh::open(config)
            .wait()
            .map_err(|source| Ros2LiveError::Zenoh {
                what: "cannot open a session".into(),
                source,
            })?;
        let (sender, receiver) = mpsc::sync_channel(options.queue_capacity);
        let topics = options.topics();
        let arrivals = Arc::new(Mutex::new(ArrivalCounters::new(topics.len())));
        let mut subscribers = Vec::with_capacity(topics.len());
        for (index, (topic, ros_type)) in topics.iter().enumerate() {
            let key = rmw_zenoh::topic_key(options.domain_id, topic, ros_type, "*")?;
            let sender = sender.clone();
            let arrivals = Arc::clone(&arrivals);
            let own = own_gid_prefix(&session.zid());
            let subscriber = session
                .declare_subscriber(key.clone())
                .callback(move |sample| {
                    let attachment = sample.attachment().map(|a| a.to_bytes());
                    let Ok(mut arrivals) = arrivals.lock() else {
                        return;
                    };
                    if !arrivals.arrive(index, attachment.as_deref(), &own) {
                        return;
                    }
                    let incoming = Incoming {
                        topic: index,
                        payload: sample.payload().to_bytes().into_owned(),
                    };
                    if let Err(mpsc::TrySendError::Full(_)) = sender.try_send(incoming) {
                        arrivals.dropped_queue_full(index);
                    }
                })
                .wait()
                .map_err(|source| Ros2LiveError::Zenoh {
                    what: format!("cannot subscribe to {key}"),
                    source,
                })?;
            subscribers.push(subscriber);
        }
        Ok(Self {
            session,
            _subscribers: subscribers,
            receiver,
            arrivals,
            decoder: LiveDecoder::new(options),
            end,
            started: Instant::now(),
            last_scan_at: None,
            finished: false,
        })
    }

    /// The zenoh session (cheap to clone): the agent publishes its map and pose back on it.
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// The odometry readings handed on lately (see [`OdometryHistory`]).
    pub fn odometry_history(&self) -> OdometryHistory {
        self.decoder.odometry_history()
    }

    /// What was received, decoded and dropped so far.
    pub fn stats(&self) -> LiveStats {
        let arrivals = self.arrivals.lock().ok();
        self.decoder.stats(arrivals.as_deref())
    }

    /// Whether the stream is over: idle since the last scan, or no first scan in time.
    fn timed_out(&self) -> bool {
        match self.last_scan_at {
            Some(at) => at.elapsed().as_secs_f64() >= self.end.until_idle_s,
            None => self.started.elapsed().as_secs_f64() >= self.end.start_timeout_s,
        }
    }
}

impl SensorStream for LiveRos2Source {
    fn next_event(&mut self) -> Option<SensorEvent> {
        loop {
            if let Some(event) = self.decoder.pop() {
                return Some(event);
            }
            if self.finished {
                return None;
            }
            match self.receiver.recv_timeout(POLL) {
                Ok(incoming) => {
                    if self.decoder.ingest(incoming.topic, &incoming.payload) {
                        self.last_scan_at = Some(Instant::now());
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    if self.timed_out() {
                        self.finished = true;
                        self.decoder.finish();
                    }
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    self.finished = true;
                    self.decoder.finish();
                }
            }
        }
    }

    fn base_from_laser(&self) -> Rigid2 {
        self.decoder.base_from_laser()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_are_checked() {
        let options = Ros2LiveOptions::default();
        options.validate().unwrap();
        let bad = |o: Ros2LiveOptions| o.validate().unwrap_err().to_string();
        assert!(
            bad(Ros2LiveOptions {
                domain_id: 233,
                ..options.clone()
            })
            .contains("domain_id")
        );
        assert!(
            bad(Ros2LiveOptions {
                scan_topic: "scan".into(),
                ..options.clone()
            })
            .contains("fully qualified")
        );
        assert!(
            bad(Ros2LiveOptions {
                queue_capacity: 0,
                ..options.clone()
            })
            .contains("queue_capacity")
        );
        assert!(
            bad(Ros2LiveOptions {
                reorder_window_s: f64::NAN,
                ..options
            })
            .contains("reorder_window_s")
        );
        let parsed: Ros2LiveOptions =
            toml::from_str("domain_id = 3\nscan_topic = \"/robot/scan\"\n[zenoh]\nconnect = [\"tcp/127.0.0.1:7448\"]\n")
                .unwrap();
        parsed.validate().unwrap();
        assert_eq!(parsed.domain_id, 3);
        assert!(toml::from_str::<Ros2LiveOptions>("scan = \"/x\"").is_err());
    }
}
