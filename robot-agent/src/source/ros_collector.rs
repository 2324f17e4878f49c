//! What the ROS1 and the rosbag2 readers share once a message is decoded: the events, the TF transforms
//! seen, the laser's frame, and the choice of `base_from_laser` at the end. One place, so both formats
//! give the same recording from the same messages.

use mapping::geometry::Rigid2;
use mapping::sensor::SensorEvent;

use super::recording::{ReadReport, Recording};
use super::ros_messages::{DecodeError, PlanarTransform};

/// The message types evermap reads, whatever the ROS version.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RosKind {
    /// `sensor_msgs/LaserScan`.
    Scan,
    /// `nav_msgs/Odometry`.
    Odometry,
    /// `sensor_msgs/Imu`.
    Imu,
    /// `tf2_msgs/TFMessage`.
    Tf,
    /// Anything else (skipped).
    Other,
}

/// Collects decoded messages in file order.
#[derive(Default)]
pub struct RosCollector {
    events: Vec<SensorEvent>,
    transforms: Vec<PlanarTransform>,
    laser_frame: Option<String>,
    /// What was read and skipped so far.
    pub report: ReadReport,
}

impl RosCollector {
    /// Decodes one message of `kind` with the format's decoders and keeps what it gives; a message that
    /// does not decode is counted and described in the report (`at`: where it was), not an error.
    pub fn add(
        &mut self,
        kind: RosKind,
        data: &[u8],
        at: &dyn std::fmt::Display,
        decoders: &Decoders,
    ) {
        let decoded = match kind {
            RosKind::Scan => (decoders.laser_scan)(data).map(|(scan, frame)| {
                self.laser_frame.get_or_insert(frame);
                self.events.push(SensorEvent::Scan(scan));
            }),
            RosKind::Odometry => {
                (decoders.odometry)(data).map(|o| self.events.push(SensorEvent::Odometry(o)))
            }
            RosKind::Imu => (decoders.imu)(data).map(|i| self.events.push(SensorEvent::Imu(i))),
            RosKind::Tf => (decoders.tf_message)(data).map(|t| {
                self.report.tf += 1;
                self.transforms.extend(t);
            }),
            RosKind::Other => {
                self.report.skipped_other += 1;
                Ok(())
            }
        };
        if let Err(e) = decoded {
            self.report.skipped_malformed += 1;
            self.report
                .problem(format!("{kind:?} message at {at}: {}", e.0));
        }
    }

    /// Takes the events decoded since the last call, in arrival order (a live source's way of draining
    /// the collector as messages come; [`Self::finish`] is the recording's).
    pub fn take_events(&mut self) -> Vec<SensorEvent> {
        std::mem::take(&mut self.events)
    }

    /// `base_from_laser` and where it came from, once both the first scan's frame and a transform to it
    /// have been seen (`None` before).
    pub fn laser_mount(&self) -> Option<(Rigid2, String)> {
        let frame = self.laser_frame.as_ref()?;
        let t = self.transforms.iter().find(|t| &t.child == frame)?;
        Some((
            t.parent_from_child,
            format!("tf {} -> {}", t.parent, t.child),
        ))
    }

    /// `base_from_laser` as [`Self::finish`] chooses it: the transform to the first scan's frame, or
    /// identity (said in the returned source).
    pub fn laser_mount_or_identity(&self) -> (Rigid2, String) {
        self.laser_mount().unwrap_or_else(|| {
            let why = match &self.laser_frame {
                Some(frame) => format!("no tf to frame {frame:?}: identity"),
                None => "no laser scans: identity".into(),
            };
            (Rigid2::identity(), why)
        })
    }

    /// The recording: events in time order and `base_from_laser` from the first transform whose child
    /// is the first scan's frame (identity, said in the report, when there is none).
    pub fn finish(self) -> Recording {
        let (base_from_laser, source) = self.laser_mount_or_identity();
        let Self {
            events, mut report, ..
        } = self;
        report.extrinsic_source = source;
        Recording::from_unsorted(events, base_from_laser, report)
    }
}

/// A scan and its frame id, or why the message does not decode.
pub type ScanResult = Result<(mapping::sensor::LaserScan, String), DecodeError>;

/// The decoders of one serialization (ROS1 or CDR).
pub struct Decoders {
    /// `sensor_msgs/LaserScan` and its frame id.
    pub laser_scan: fn(&[u8]) -> ScanResult,
    /// `nav_msgs/Odometry`.
    pub odometry: fn(&[u8]) -> Result<mapping::sensor::OdometryReading, DecodeError>,
    /// `sensor_msgs/Imu`.
    pub imu: fn(&[u8]) -> Result<mapping::sensor::ImuReading, DecodeError>,
    /// `tf2_msgs/TFMessage`.
    pub tf_message: fn(&[u8]) -> Result<Vec<PlanarTransform>, DecodeError>,
}
