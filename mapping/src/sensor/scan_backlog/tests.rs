use super::*;
use crate::sensor::test_support::{odometry_event, scan_event};

fn at(t: f64) -> Timestamp {
    Timestamp::from_secs_f64(t)
}

/// Scans every 0.1 s taken over `0..seconds`, odometry every 0.05 s; the scans taken in `stall` are
/// stamped at its end (0.5 ms apart), and so is the odometry if `odometry_stalls`. Returns the events
/// in stamp order and each scan's time taken, in order.
fn recording(
    seconds: f64,
    stall: (f64, f64),
    odometry_stalls: bool,
) -> (Vec<SensorEvent>, Vec<f64>) {
    let mut events = Vec::new();
    let mut taken = Vec::new();
    let ticks = (seconds * 20.0).round() as u32;
    let in_stall = |t: f64| t >= stall.0 && t < stall.1;
    let mut held = Vec::new();
    for i in 0..ticks {
        let t = f64::from(i) * 0.05;
        let is_scan = i % 2 == 0;
        if is_scan {
            taken.push(t);
        }
        let event = if is_scan {
            scan_event(t)
        } else {
            odometry_event(t)
        };
        if in_stall(t) && (is_scan || odometry_stalls) {
            held.push(event);
            continue;
        }
        if t >= stall.1 && !held.is_empty() {
            let n = held.len();
            for (k, mut e) in held.drain(..).enumerate() {
                let stamp = at(stall.1 - 0.04).offset_by(-((n - 1 - k) as f64) * 0.0005);
                match &mut e {
                    SensorEvent::Scan(s) => s.time = stamp,
                    SensorEvent::Odometry(o) => o.time = stamp,
                    SensorEvent::Imu(r) => r.time = stamp,
                }
                events.push(e);
            }
        }
        events.push(event);
    }
    events.sort_by_key(SensorEvent::time);
    (events, taken)
}

fn scan_times(events: &[SensorEvent]) -> Vec<f64> {
    events
        .iter()
        .filter(|e| matches!(e, SensorEvent::Scan(_)))
        .map(|e| e.time().seconds_since(at(0.0)))
        .collect()
}

#[test]
fn a_backlog_after_a_gap_the_odometry_kept_coming_through_is_put_back_where_it_was_taken() {
    let (events, taken) = recording(4.0, (1.0, 2.0), false);
    let stamped = scan_times(&events);
    let (out, retimed) = ScanBacklog::retime(&events);
    assert_eq!(out.len(), events.len());
    assert_eq!(retimed.len(), 10, "{retimed:?}");
    let times = scan_times(&out);
    assert!(times.windows(2).all(|w| w[0] < w[1]), "{times:?}");
    // Stamped up to 0.96 s late; re-timed within a period (the burst's last stamp is its anchor, and
    // that scan was read 0.06 s after it was taken).
    let worst_stamp = stamped
        .iter()
        .zip(&taken)
        .map(|(s, t)| s - t)
        .fold(0.0, f64::max);
    assert!(worst_stamp > 0.9);
    for ((got, truth), stamp) in times.iter().zip(&taken).zip(&stamped) {
        assert!(
            (got - truth).abs() <= 0.07,
            "taken {truth:.3} s, stamped {stamp:.4} s, re-timed to {got:.4} s"
        );
    }
    // The stamps the scans came with are kept beside the times they are given.
    assert!(retimed.iter().all(|r| r.stamped >= r.taken));
}

#[test]
fn a_burst_the_odometry_shares_is_left_as_it_came() {
    // One logger stalled for both streams: their order in the burst is already right.
    let (events, _) = recording(4.0, (1.0, 2.0), true);
    let (out, retimed) = ScanBacklog::retime(&events);
    assert!(retimed.is_empty(), "{retimed:?}");
    assert_eq!(out, events);
}

#[test]
fn scans_lost_in_a_gap_are_not_a_backlog() {
    // A 1-s gap the odometry kept coming through, then only two scans close together: the rest of the
    // gap's scans were lost, not held back.
    let (mut events, _) = recording(4.0, (1.0, 2.0), false);
    let mut burst_scans = 0;
    events.retain(|e| match e {
        SensorEvent::Scan(s) if s.time > at(1.5) && s.time < at(2.0) => {
            burst_scans += 1;
            burst_scans > 8
        }
        _ => true,
    });
    let (out, retimed) = ScanBacklog::retime(&events);
    assert!(retimed.is_empty(), "{retimed:?}");
    assert_eq!(out, events);
}

#[test]
fn a_recording_without_bursts_or_without_odometry_goes_through_unchanged() {
    let (steady, _) = recording(3.0, (10.0, 10.0), false);
    assert_eq!(ScanBacklog::retime(&steady).0, steady);
    let (with_burst, _) = recording(4.0, (1.0, 2.0), false);
    let scans_only: Vec<SensorEvent> = with_burst
        .into_iter()
        .filter(|e| matches!(e, SensorEvent::Scan(_)))
        .collect();
    assert_eq!(ScanBacklog::retime(&scans_only).0, scans_only);
}

#[test]
fn odometry_is_held_no_longer_than_the_bound_when_the_scans_stop() {
    // The scanner stops at 1 s; the odometry goes on.
    let (events, _) = recording(10.0, (0.0, 0.0), false);
    let events: Vec<SensorEvent> = events
        .into_iter()
        .filter(|e| matches!(e, SensorEvent::Odometry(_)) || e.time() < at(1.0))
        .collect();
    let mut stage = ScanBacklog::default();
    let mut out = Vec::new();
    for e in events.iter().cloned() {
        let now = e.time();
        stage.push(e, &mut out);
        let newest_out = out.last().map_or(at(0.0), SensorEvent::time);
        assert!(now.seconds_since(newest_out) <= MAX_BACKLOG_HOLD_S + 0.1);
    }
    stage.finish(&mut out);
    assert_eq!(out, events);
}
