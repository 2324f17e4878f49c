//! Sensor collation for LLO: each scan is handed over only once odometry covers its time.
//!
//! Recordings (and live robots) often stamp an odometry message just after the scan it belongs with (ACES:
//! about 0.1 s into a 0.16 s scan period). Taken in stamp order, a scan then finds only odometry older
//! than itself, and the pose extrapolator must hold the last reading: every prediction falls short of
//! the robot's motion (ACES: by 40 % on average), and along a corridor, where the scan cannot see the
//! motion, the shortfall is what the scan matcher keeps. Extrapolating odometry at its own velocity
//! instead is no cure: recordings with bursts of odometry stamps (Intel) give velocities that are noise.
//! So, like Cartographer's collator, a scan waits until an odometry reading stamped at or after it has
//! been handed over (at most [`MAX_ODOMETRY_WAIT_S`] of recording time), and the extrapolator then
//! interpolates odometry between the readings on either side of the scan.

use std::collections::VecDeque;

use super::SensorEvent;

/// Longest a scan waits (seconds of recording time) for an odometry reading stamped at or after it; a
/// scan still waiting then is handed over as it is (odometry stopped or lags), and a live robot whose
/// odometry stops localizes this much late. 3 s spans every odometry gap of the recordings (Intel: up to
/// 1.3 s, some in fast turns, where a prediction carried across the gap at the matched poses' velocity
/// missed 56° of a turn in the `thin` variant; 0.5 s until session 37, see docs/BENCHMARK-HISTORY.md
/// "Session 37").
pub const MAX_ODOMETRY_WAIT_S: f64 = 3.0;

/// `events` (in stamp order) in the order LLO should take them: each scan moved after the first
/// odometry reading stamped at or after it, if one comes within [`MAX_ODOMETRY_WAIT_S`]. Scans keep their
/// order among themselves, as does every other kind of event. A recording without odometry is returned
/// as it is.
pub fn collate_for_llo(events: &[SensorEvent]) -> Vec<&SensorEvent> {
    if !events.iter().any(|e| matches!(e, SensorEvent::Odometry(_))) {
        return events.iter().collect();
    }
    let mut collator = LloCollator::default();
    let mut out = Vec::with_capacity(events.len());
    for event in events {
        collator.push(event, &mut out);
    }
    collator.finish(&mut out);
    out
}

/// [`collate_for_llo`] one event at a time, for a live stream: events pushed in stamp order come out
/// (into `out`) in the order LLO should take them. `E` is a [`SensorEvent`] or a reference to one.
/// Holds at most the scans of [`MAX_ODOMETRY_WAIT_S`] of stream time.
pub struct LloCollator<E> {
    waiting: VecDeque<E>,
}

impl<E> Default for LloCollator<E> {
    fn default() -> Self {
        Self {
            waiting: VecDeque::new(),
        }
    }
}

impl<E: std::borrow::Borrow<SensorEvent>> LloCollator<E> {
    /// Takes the next event (in stamp order) and appends to `out` what LLO can take now.
    pub fn push(&mut self, event: E, out: &mut Vec<E>) {
        let time = event.borrow().time();
        while let Some(front) = self.waiting.front()
            && time.seconds_since(front.borrow().time()) > MAX_ODOMETRY_WAIT_S
        {
            out.extend(self.waiting.pop_front());
        }
        match event.borrow() {
            SensorEvent::Scan(_) => self.waiting.push_back(event),
            SensorEvent::Odometry(reading) => {
                let reading_time = reading.time;
                out.push(event);
                while let Some(front) = self.waiting.front()
                    && front.borrow().time() <= reading_time
                {
                    out.extend(self.waiting.pop_front());
                }
            }
            SensorEvent::Imu(_) => out.push(event),
        }
    }

    /// The end of the stream: appends the scans still waiting.
    pub fn finish(&mut self, out: &mut Vec<E>) {
        out.extend(self.waiting.drain(..));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::Timestamp;
    use crate::sensor::test_support::{odometry_event, scan_event};

    fn kinds(events: &[&SensorEvent]) -> String {
        events
            .iter()
            .map(|e| match e {
                SensorEvent::Scan(_) => 's',
                SensorEvent::Odometry(_) => 'o',
                SensorEvent::Imu(_) => 'i',
            })
            .collect()
    }

    #[test]
    fn a_scan_waits_for_the_odometry_stamped_after_it() {
        // ACES-like: odometry 0.1 s after each scan.
        let events = vec![
            odometry_event(0.0),
            scan_event(0.1),
            odometry_event(0.2),
            scan_event(0.3),
            odometry_event(0.4),
            scan_event(0.5),
        ];
        let collated = collate_for_llo(&events);
        assert_eq!(kinds(&collated), "oososs");
        // Every scan but the last now has odometry on both sides.
        let times: Vec<f64> = collated
            .iter()
            .map(|e| e.time().seconds_since(Timestamp(0)))
            .collect();
        assert!((times[2] - 0.1).abs() < 1e-9 && (times[1] - 0.2).abs() < 1e-9);
        assert_eq!(collated.len(), events.len());
    }

    #[test]
    fn a_scan_is_not_held_past_the_wait_nor_without_odometry() {
        let late = 0.2 + MAX_ODOMETRY_WAIT_S + 0.1;
        let events = vec![
            odometry_event(0.0),
            scan_event(0.1),
            scan_event(0.2),
            scan_event(late),
            odometry_event(late + 0.05),
        ];
        let collated = collate_for_llo(&events);
        // The scans at 0.1 and 0.2 s are released when the next scan shows they waited too long.
        assert_eq!(kinds(&collated), "ossos");
        let no_odometry = vec![scan_event(0.1), scan_event(0.2)];
        assert_eq!(kinds(&collate_for_llo(&no_odometry)), "ss");
    }

    #[test]
    fn the_streaming_collator_gives_the_same_order_as_the_whole_recording() {
        let events = vec![
            odometry_event(0.0),
            scan_event(0.1),
            odometry_event(0.2),
            scan_event(0.3),
            scan_event(0.35),
            scan_event(1.2),
            odometry_event(1.25),
            scan_event(1.3),
        ];
        let whole = collate_for_llo(&events);
        let mut collator = LloCollator::default();
        let mut streamed = Vec::new();
        for e in events.clone() {
            collator.push(e, &mut streamed);
        }
        // Before the end, the last scan is still held (no odometry after it yet).
        assert_eq!(streamed.len(), events.len() - 1);
        collator.finish(&mut streamed);
        assert_eq!(streamed.len(), whole.len());
        for (a, b) in streamed.iter().zip(&whole) {
            assert_eq!(a, *b);
        }
    }
}
