//! The live ROS 2 path without a network: what zenoh's callbacks do with each sample
//! (`source::ArrivalCounters`: the rmw_zenoh attachment, sequence gaps, the agent's own publications) and
//! what `source::LiveRos2Source` then does with it (`source::LiveDecoder`: CDR decoding, the reorder
//! buffer, the mount, the LLO collation), fed a stream of hostile samples.

use std::path::Path;

use mapping::sensor::{SensorEvent, Timestamp};
use robot_agent::source::rmw_zenoh::Attachment;
use robot_agent::source::{ArrivalCounters, LiveDecoder, Ros2LiveOptions};

use super::super::fuzz_target::{FuzzTarget, Verdict};
use super::SetupError;
use super::recordings::finite;
use super::rosbag2::csail_cut;

/// The agent's own GID prefix in this target: samples whose attachment carries it are not input.
const OWN_GID_PREFIX: [u8; 12] = [0xA5; 12];

/// The options the target decodes with: every topic including an IMU, and a small queue so the
/// reorder buffer's bound is reached.
fn options() -> Ros2LiveOptions {
    Ros2LiveOptions {
        imu_topic: Some("/imu".into()),
        queue_capacity: 64,
        ..Ros2LiveOptions::default()
    }
}

/// One sample: the topic index (`Ros2LiveOptions::topics` order), the attachment, the payload.
struct Sample<'a> {
    topic: usize,
    attachment: Option<&'a [u8]>,
    payload: &'a [u8],
}

/// A sample as the seeds hold it: topic index, attachment, payload.
type OwnedSample = (usize, Option<Vec<u8>>, Vec<u8>);

/// Samples in the form mutations work on: per sample a topic byte, a flags byte (bit 0: has an
/// attachment), the attachment as a u16 little-endian length and its bytes, the payload as a u32
/// little-endian length and its bytes; a length past the end takes what is left.
fn encode(samples: &[OwnedSample]) -> Vec<u8> {
    let mut out = Vec::new();
    for (topic, attachment, payload) in samples {
        out.push(u8::try_from(*topic).unwrap_or(u8::MAX));
        out.push(u8::from(attachment.is_some()));
        let attachment = attachment.as_deref().unwrap_or_default();
        out.extend_from_slice(
            &u16::try_from(attachment.len())
                .unwrap_or(u16::MAX)
                .to_le_bytes(),
        );
        out.extend_from_slice(attachment);
        out.extend_from_slice(
            &u32::try_from(payload.len())
                .unwrap_or(u32::MAX)
                .to_le_bytes(),
        );
        out.extend_from_slice(payload);
    }
    out
}

fn decode(mut input: &[u8]) -> Vec<Sample<'_>> {
    fn take<'a>(input: &mut &'a [u8], n: usize) -> &'a [u8] {
        let (head, tail) = input.split_at(n.min(input.len()));
        *input = tail;
        head
    }
    let mut samples = Vec::new();
    while input.len() >= 2 {
        let head = take(&mut input, 2);
        let (topic, flags) = (head[0], head[1]);
        let mut two = [0u8; 2];
        let bytes = take(&mut input, 2);
        two[..bytes.len()].copy_from_slice(bytes);
        let attachment = take(&mut input, usize::from(u16::from_le_bytes(two)));
        let mut four = [0u8; 4];
        let bytes = take(&mut input, 4);
        four[..bytes.len()].copy_from_slice(bytes);
        let payload = take(&mut input, u32::from_le_bytes(four) as usize);
        samples.push(Sample {
            topic: usize::from(topic),
            attachment: (flags & 1 == 1).then_some(attachment),
            payload,
        });
    }
    samples
}

/// The live ROS 2 decoding path on sample streams cut from the MCAP copy of MIT CSAIL.
pub fn ros2_live(datasets: &Path) -> Result<FuzzTarget, SetupError> {
    let options = options();
    let topics = options.topics();
    let index_of = |topic: &str| topics.iter().position(|(t, _)| t == topic);
    let mut samples = Vec::new();
    let mut keyed_samples = Vec::new();
    for (i, m) in csail_cut(datasets, 4)?.iter().enumerate() {
        let Some(topic) = index_of(&m.topic) else {
            continue;
        };
        let attachment = Attachment {
            sequence_number: i64::try_from(i).unwrap_or(i64::MAX) + 1,
            source_timestamp_ns: i64::try_from(m.log_time).unwrap_or(i64::MAX),
            source_gid: [u8::try_from(topic).unwrap_or(0); 16],
        }
        .encode();
        // The keyed form of the first zenoh-1.0 releases of rmw_zenoh.
        let mut keyed = Vec::new();
        for (key, value) in [
            ("sequence_number", &attachment[..8]),
            ("source_timestamp", &attachment[8..16]),
        ] {
            keyed.push(u8::try_from(key.len()).unwrap_or(0));
            keyed.extend_from_slice(key.as_bytes());
            keyed.extend_from_slice(value);
        }
        keyed.push(10);
        keyed.extend_from_slice(b"source_gid");
        keyed.extend_from_slice(&attachment[16..]);
        samples.push((topic, Some(attachment), m.data.clone()));
        keyed_samples.push((topic, Some(keyed), m.data.clone()));
    }
    // Late-arriving transforms: the scans wait for the mount.
    let mut tf_last = samples.clone();
    tf_last.sort_by_key(|(topic, _, _)| usize::from(*topic == 2 || *topic == 3));
    let seeds = vec![
        encode(&samples),
        encode(&keyed_samples),
        encode(&tf_last),
        encode(&samples[..samples.len().min(6)]),
    ];
    Ok(FuzzTarget::new(
        "ros2_live",
        "live ROS 2 samples (rmw_zenoh attachment, CDR payload) through the live source's counters and decoder",
        seeds,
        false,
        Box::new(move |input| {
            let samples = decode(input);
            let mut decoder = LiveDecoder::new(&options);
            let mut arrivals = ArrivalCounters::new(decoder.topic_count());
            let mut events = Vec::new();
            let mut ingested = vec![0_u64; decoder.topic_count()];
            for sample in &samples {
                // As the callbacks and the source's loop do; one index past the topics reaches the
                // decoder's refusal of unknown topics.
                let topic = sample.topic % (decoder.topic_count() + 1);
                if !arrivals.arrive(topic, sample.attachment, &OWN_GID_PREFIX) {
                    continue;
                }
                decoder.ingest(topic, sample.payload);
                if let Some(n) = ingested.get_mut(topic) {
                    *n += 1;
                }
                events.extend(std::iter::from_fn(|| decoder.pop()));
            }
            decoder.finish();
            events.extend(std::iter::from_fn(|| decoder.pop()));
            check_live(&events, &decoder, &arrivals, &ingested, &options)
        }),
    ))
}

/// What the live source guarantees SLAM: each stream's stamps strictly increase, values are finite, and
/// its counts add up.
fn check_live(
    events: &[SensorEvent],
    decoder: &LiveDecoder,
    arrivals: &ArrivalCounters,
    ingested: &[u64],
    options: &Ros2LiveOptions,
) -> Verdict {
    let mut last: [Option<Timestamp>; 3] = [None; 3];
    for event in events {
        let stream = match event {
            SensorEvent::Scan(scan) => {
                assert!(
                    scan.angle_min.is_finite()
                        && scan.angle_increment.is_finite()
                        && scan.range_max.is_finite(),
                    "invariant: non-finite scan geometry"
                );
                0
            }
            SensorEvent::Odometry(o) => {
                assert!(finite(&o.pose), "invariant: non-finite odometry");
                1
            }
            SensorEvent::Imu(i) => {
                assert!(i.yaw_rate.is_finite(), "invariant: non-finite yaw rate");
                2
            }
        };
        let time = event.time();
        if let Some(previous) = last[stream] {
            assert!(
                time > previous,
                "invariant: stream {stream} not strictly increasing ({previous:?} then {time:?})"
            );
        }
        last[stream] = Some(time);
    }
    assert!(
        finite(&decoder.base_from_laser()),
        "invariant: non-finite base_from_laser"
    );
    let stats = decoder.stats(Some(arrivals));
    assert_eq!(
        stats.events_out,
        events.len() as u64,
        "invariant: events counted"
    );
    let mut malformed = 0;
    for (i, (topic, _)) in options.topics().iter().enumerate() {
        let counts = &stats.topics[topic];
        assert_eq!(
            counts.decoded + counts.malformed,
            ingested[i],
            "invariant: {topic}: every sample decoded or counted malformed"
        );
        assert_eq!(counts.received, ingested[i], "invariant: {topic}: received");
        malformed += counts.malformed;
    }
    if malformed == 0 {
        Verdict::Accepted
    } else {
        Verdict::Rejected(format!("{malformed} samples did not decode"))
    }
}
