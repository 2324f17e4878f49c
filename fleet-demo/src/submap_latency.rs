//! The load benchmark's headline figure: the latency from a submap finished on a robot to the server's
//! acknowledgement and to its version in every cache of its site.

use std::time::Instant;

use serde_json::json;

use crate::load_fleet::{Robot, site_id};
use crate::prepared_stream::StreamOutcome;

/// Every timed submap's latencies.
pub(crate) struct SubmapLatencies {
    /// To the acknowledgement of the batch holding it, seconds.
    pub to_ack: Vec<f64>,
    /// To its version in every cache of its site, seconds (delivered submaps only).
    pub to_every_robot: Vec<f64>,
    /// Submaps whose version never reached every robot of the site.
    pub undelivered: usize,
    /// (when the submap was finished, its latency to every robot of the site).
    pub by_finish: Vec<(Instant, f64)>,
    /// `submap_latencies.csv`: a header, then one line per submap (when it was finished, seconds after
    /// `stream_started`; its site and version; its latencies).
    pub csv_lines: Vec<String>,
}

impl SubmapLatencies {
    /// The latencies of every submap the robots' `outcomes` timed, against when each robot's cache
    /// received each version.
    pub fn measure(outcomes: &[StreamOutcome], robots: &[Robot], stream_started: Instant) -> Self {
        let arrivals: Vec<Vec<(u64, Instant)>> = robots
            .iter()
            .map(|r| r.arrivals.lock().map(|a| a.clone()).unwrap_or_default())
            .collect();
        let mut latencies = Self {
            to_ack: Vec::new(),
            to_every_robot: Vec::new(),
            undelivered: 0,
            by_finish: Vec::new(),
            csv_lines: vec!["finished_s,site,version,to_ack_s,to_every_robot_s".to_owned()],
        };
        for timing in outcomes.iter().flat_map(|o| &o.submaps) {
            latencies
                .to_ack
                .push(timing.acked.duration_since(timing.finished).as_secs_f64());
            let reached: Option<Vec<Instant>> = robots
                .iter()
                .zip(&arrivals)
                .filter(|(r, _)| r.site == timing.site)
                .map(|(_, a)| {
                    a.iter()
                        .find(|(v, _)| *v >= timing.version)
                        .map(|(_, at)| *at)
                })
                .collect();
            let to_every_robot = reached.and_then(|r| r.into_iter().max()).map(|last| {
                last.saturating_duration_since(timing.finished)
                    .as_secs_f64()
            });
            match to_every_robot {
                Some(latency) => {
                    latencies.to_every_robot.push(latency);
                    latencies.by_finish.push((timing.finished, latency));
                }
                None => latencies.undelivered += 1,
            }
            latencies.csv_lines.push(format!(
                "{:.3},{},{},{:.3},{}",
                timing
                    .finished
                    .saturating_duration_since(stream_started)
                    .as_secs_f64(),
                site_id(timing.site),
                timing.version,
                timing.acked.duration_since(timing.finished).as_secs_f64(),
                to_every_robot.map_or_else(|| "undelivered".to_owned(), |l| format!("{l:.3}"))
            ));
        }
        latencies
    }

    /// Submaps timed, delivered or not.
    pub fn submaps(&self) -> usize {
        self.to_every_robot.len() + self.undelivered
    }

    /// The report's `submap_latency_s`.
    pub fn report(&self) -> serde_json::Value {
        json!({
            "submaps": self.submaps(),
            "undelivered": self.undelivered,
            "to_ack": quantiles(&mut self.to_ack.clone()),
            "to_every_robot_of_the_site": quantiles(&mut self.to_every_robot.clone()),
        })
    }
}

/// p50, p95 and max of `values` (sorted in place), `null` when empty.
fn quantiles(values: &mut [f64]) -> serde_json::Value {
    if values.is_empty() {
        return serde_json::Value::Null;
    }
    values.sort_by(f64::total_cmp);
    let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
    json!({ "p50": at(0.5), "p95": at(0.95), "max": values[values.len() - 1], "count": values.len() })
}

#[cfg(test)]
mod tests {
    use super::quantiles;

    #[test]
    fn quantiles_are_the_nearest_ranks_and_null_when_empty() {
        assert!(quantiles(&mut []).is_null());
        let mut values: Vec<f64> = (0..=100).rev().map(f64::from).collect();
        let q = quantiles(&mut values);
        assert_eq!(q["p50"], 50.0);
        assert_eq!(q["p95"], 95.0);
        assert_eq!(q["max"], 100.0);
        assert_eq!(q["count"], 101);
    }
}
