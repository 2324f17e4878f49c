//! The network-free half of [`super::LiveRos2Source`]: raw samples (a topic index and its CDR payload)
//! in, [`SensorEvent`]s out in the order LLO takes them — decoded by the same CDR decoders and
//! [`RosCollector`] as a rosbag2 recording, held in the reorder buffer until the reorder window (and the
//! laser's mount) lets them go, then through the [`LloCollator`] (see the parent module's docs for the
//! rules). The live source feeds it what zenoh delivers; the fuzz harness (`tests::fuzz`, target
//! `ros2_live`) feeds it hostile samples with no network.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;

use mapping::geometry::Rigid2;
use mapping::sensor::{LloCollator, ScanBacklog, SensorEvent, Timestamp};

use super::super::rmw_zenoh;
use super::super::ros_collector::{RosCollector, RosKind};
use super::super::rosbag2::CDR_DECODERS;
use super::arrival_counters::ArrivalCounters;
use super::{LiveStats, OdometryHistory, Ros2LiveOptions};

/// Readings kept in an [`OdometryHistory`].
const ODOMETRY_HISTORY: usize = 512;

fn stream_of(event: &SensorEvent) -> usize {
    match event {
        SensorEvent::Scan(_) => 0,
        SensorEvent::Odometry(_) => 1,
        SensorEvent::Imu(_) => 2,
    }
}

/// Decodes, re-sorts and hands on a live robot's samples (see the module docs).
pub struct LiveDecoder {
    topics: Vec<(String, RosKind)>,
    decoded: Vec<u64>,
    malformed: Vec<u64>,
    collector: RosCollector,
    reorder_window: Timestamp,
    mount_wait_s: f64,
    /// Events held at most (`queue_capacity`); past it the oldest leave whatever the window says.
    max_buffered: usize,
    /// Events by (stamp, arrival), waiting for the reorder window.
    buffer: BTreeMap<(Timestamp, u64), SensorEvent>,
    arrivals: u64,
    newest: Option<Timestamp>,
    first_scan: Option<Timestamp>,
    mount: Option<(Rigid2, String)>,
    last_out: [Option<Timestamp>; 3],
    backlog: ScanBacklog,
    scans_retimed: u64,
    collator: LloCollator<SensorEvent>,
    ready: VecDeque<SensorEvent>,
    dropped_late: u64,
    repeated_stamp: u64,
    events_out: u64,
    scans_out: u64,
    newest_out: Option<Timestamp>,
    odometry: OdometryHistory,
}

impl LiveDecoder {
    /// A decoder of the topics `options` subscribes to (topic index `i` is the `i`-th of
    /// [`Ros2LiveOptions::topics`]). `options` should be valid ([`Ros2LiveOptions::validate`]).
    pub fn new(options: &Ros2LiveOptions) -> Self {
        let topics = options
            .topics()
            .into_iter()
            .map(|(topic, ros_type)| {
                let kind = match ros_type {
                    t if t == rmw_zenoh::LASER_SCAN.name => RosKind::Scan,
                    t if t == rmw_zenoh::ODOMETRY.name => RosKind::Odometry,
                    t if t == rmw_zenoh::IMU.name => RosKind::Imu,
                    _ => RosKind::Tf,
                };
                (topic, kind)
            })
            .collect::<Vec<_>>();
        Self {
            decoded: vec![0; topics.len()],
            malformed: vec![0; topics.len()],
            topics,
            collector: RosCollector::default(),
            reorder_window: Timestamp::from_secs_f64(options.reorder_window_s),
            mount_wait_s: options.mount_wait_s,
            max_buffered: options.queue_capacity.max(1),
            buffer: BTreeMap::new(),
            arrivals: 0,
            newest: None,
            first_scan: None,
            mount: None,
            last_out: [None; 3],
            backlog: ScanBacklog::default(),
            scans_retimed: 0,
            collator: LloCollator::default(),
            ready: VecDeque::new(),
            dropped_late: 0,
            repeated_stamp: 0,
            events_out: 0,
            scans_out: 0,
            newest_out: None,
            odometry: Arc::default(),
        }
    }

    /// How many topics samples may come from (indices `0..topic_count()`).
    pub fn topic_count(&self) -> usize {
        self.topics.len()
    }

    /// Decodes one sample of topic `topic` and buffers what it gives; returns whether it was a laser
    /// scan's topic (the live source's idle timeout counts from the last one). A topic index out of
    /// range is ignored.
    pub fn ingest(&mut self, topic: usize, payload: &[u8]) -> bool {
        let Some((name, kind)) = self.topics.get(topic).cloned() else {
            return false;
        };
        let malformed_before = self.collector.report.skipped_malformed;
        let malformed = if kind == RosKind::Tf && self.mount.is_some() {
            // The mount is decided: transforms are only counted, not kept (a robot's /tf never ends).
            (CDR_DECODERS.tf_message)(payload).is_err()
        } else {
            self.collector.add(kind, payload, &name, &CDR_DECODERS);
            self.collector.report.skipped_malformed > malformed_before
        };
        if malformed {
            self.malformed[topic] += 1;
        } else {
            self.decoded[topic] += 1;
        }
        for event in self.collector.take_events() {
            let time = event.time();
            if matches!(event, SensorEvent::Scan(_)) && self.first_scan.is_none() {
                self.first_scan = Some(time);
            }
            self.newest = Some(self.newest.map_or(time, |n| n.max(time)));
            self.arrivals += 1;
            self.buffer.insert((time, self.arrivals), event);
        }
        if self.mount.is_none() {
            self.mount = self.collector.laser_mount();
        }
        self.release(false);
        kind == RosKind::Scan
    }

    /// The stream is over: hands on everything still buffered.
    pub fn finish(&mut self) {
        self.release(true);
    }

    /// The next event for SLAM, if one is ready.
    pub fn pop(&mut self) -> Option<SensorEvent> {
        self.ready.pop_front()
    }

    /// The laser's mounting pose (identity until decided).
    pub fn base_from_laser(&self) -> Rigid2 {
        self.mount
            .as_ref()
            .map_or_else(Rigid2::identity, |(m, _)| *m)
    }

    /// The odometry readings handed on lately (see [`OdometryHistory`]).
    pub fn odometry_history(&self) -> OdometryHistory {
        Arc::clone(&self.odometry)
    }

    /// What was decoded and dropped so far, with what the callbacks counted (`arrivals`), if given.
    pub fn stats(&self, arrivals: Option<&ArrivalCounters>) -> LiveStats {
        let mut stats = LiveStats {
            dropped_late: self.dropped_late,
            repeated_stamp: self.repeated_stamp,
            events_out: self.events_out,
            scans_out: self.scans_out,
            scans_retimed: self.scans_retimed,
            newest_stamp_ns: self.newest_out.map(|t| t.0),
            extrinsic_source: self
                .mount
                .as_ref()
                .map_or_else(|| "not decided yet".into(), |(_, s)| s.clone()),
            problems: self.collector.report.problems.clone(),
            ..LiveStats::default()
        };
        for (i, (topic, _)) in self.topics.iter().enumerate() {
            let counts = stats.topics.entry(topic.clone()).or_default();
            counts.decoded += self.decoded[i];
            counts.malformed += self.malformed[i];
            if let Some(arrivals) = arrivals {
                let at = |v: &Vec<u64>| v.get(i).copied().unwrap_or(0);
                counts.received += at(&arrivals.received);
                counts.dropped_queue_full += at(&arrivals.dropped_queue_full);
                counts.missed_by_sequence += at(&arrivals.missed_by_sequence);
                counts.attachment_invalid += at(&arrivals.attachment_invalid);
            }
        }
        stats
    }

    /// Hands on the buffered events the reorder window (or the end of the stream, `all`) lets go; past
    /// `max_buffered` events the oldest leave regardless (deciding the mount if it is not yet), so a
    /// robot whose clock stands still cannot grow the buffer without bound.
    fn release(&mut self, all: bool) {
        let overfull = self.buffer.len() > self.max_buffered;
        if self.mount.is_none() {
            let waited = match (self.first_scan, self.newest) {
                (Some(first), Some(newest)) => newest.seconds_since(first) > self.mount_wait_s,
                _ => false,
            };
            if !(waited || all || overfull) {
                return;
            }
            self.mount = Some(self.collector.laser_mount_or_identity());
        }
        let mut staged = Vec::new();
        let mut out = Vec::new();
        loop {
            let overfull = self.buffer.len() > self.max_buffered;
            let Some(entry) = self.buffer.first_entry() else {
                break;
            };
            let (time, _) = *entry.key();
            let within_window = self
                .newest
                .is_none_or(|n| time.0 > n.0.saturating_sub(self.reorder_window.0));
            if !all && within_window && !overfull {
                break;
            }
            let event = entry.remove();
            let stream = stream_of(&event);
            if let Some(last) = self.last_out[stream]
                && time <= last
            {
                if time == last {
                    self.repeated_stamp += 1;
                } else {
                    self.dropped_late += 1;
                }
                continue;
            }
            self.last_out[stream] = Some(time);
            self.backlog.push(event, &mut staged);
        }
        if all {
            self.backlog.finish(&mut staged);
        }
        // A live robot's scans go on at the times they were taken; the stamps they came with are only counted.
        self.scans_retimed += self.backlog.take_retimed().len() as u64;
        for event in staged {
            self.collator.push(event, &mut out);
        }
        if all {
            self.collator.finish(&mut out);
        }
        for event in out {
            self.events_out += 1;
            let time = event.time();
            self.newest_out = Some(self.newest_out.map_or(time, |n| n.max(time)));
            if let SensorEvent::Odometry(reading) = &event
                && let Ok(mut history) = self.odometry.lock()
            {
                if history.len() >= ODOMETRY_HISTORY {
                    history.pop_front();
                }
                history.push_back(reading.clone());
            }
            if matches!(event, SensorEvent::Scan(_)) {
                self.scans_out += 1;
            }
            self.ready.push_back(event);
        }
    }
}

/// The events a decoder hands on for `samples` (topic index, payload), the stream then ended: what
/// [`super::LiveRos2Source`] gives SLAM for the same samples arriving in that order.
pub fn decode_samples<'a>(
    options: &Ros2LiveOptions,
    samples: impl IntoIterator<Item = (usize, &'a [u8])>,
) -> (Vec<SensorEvent>, LiveDecoder) {
    let mut decoder = LiveDecoder::new(options);
    let mut events = Vec::new();
    for (topic, payload) in samples {
        decoder.ingest(topic, payload);
        events.extend(std::iter::from_fn(|| decoder.pop()));
    }
    decoder.finish();
    events.extend(std::iter::from_fn(|| decoder.pop()));
    (events, decoder)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::CdrWriter;

    fn odometry(sec: i32) -> Vec<u8> {
        let mut w = CdrWriter::new();
        w.u32(sec.cast_unsigned());
        w.u32(0);
        w.string("odom");
        w.string("base_link");
        for v in [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        for _ in 0..36 {
            w.f64(0.0);
        }
        w.finish()
    }

    /// Regression (found while writing the `ros2_live` fuzz target): odometry stamped the same instant
    /// over and over (a robot whose clock stands still) and no scan kept every event in the reorder
    /// buffer, one more per sample, for as long as the stream lasted.
    #[test]
    fn a_clock_that_stands_still_cannot_grow_the_buffer() {
        let options = Ros2LiveOptions {
            queue_capacity: 16,
            ..Ros2LiveOptions::default()
        };
        let mut decoder = LiveDecoder::new(&options);
        let payload = odometry(5);
        for _ in 0..1000 {
            decoder.ingest(1, &payload);
            while decoder.pop().is_some() {}
            assert!(decoder.buffer.len() <= 17, "{}", decoder.buffer.len());
        }
        let stats = decoder.stats(None);
        assert_eq!(stats.topics["/odom"].decoded, 1000);
        assert!(stats.repeated_stamp >= 900, "{stats:?}");
    }

    #[test]
    fn samples_of_unknown_topics_are_ignored() {
        let (events, decoder) = decode_samples(
            &Ros2LiveOptions::default(),
            [(9, &b"x"[..]), (1, &odometry(1)[..])],
        );
        assert_eq!(events.len(), 1);
        assert_eq!(decoder.stats(None).topics["/odom"].decoded, 1);
    }
}
