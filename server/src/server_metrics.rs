//! Server counters and their Prometheus text exposition.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use crate::site::SiteHandle;

/// Reads one per-site gauge.
type Gauge = fn(&SiteHandle) -> u64;

/// Counters shared by every front end and site task. Thread-safe.
#[derive(Debug, Default)]
pub struct ServerMetrics {
    bytes_in: AtomicU64,
    bytes_out: AtomicU64,
    uploads_applied: AtomicU64,
    uploads_duplicate: AtomicU64,
    sessions_opened: AtomicU64,
    sessions_timed_out: AtomicU64,
    pgr_runs: AtomicU64,
    pgr_micros: AtomicU64,
    refused: Mutex<BTreeMap<&'static str, u64>>,
}

impl ServerMetrics {
    /// Received payload bytes so far.
    pub fn bytes_in(&self) -> u64 {
        self.bytes_in.load(Ordering::Relaxed)
    }

    /// Sent payload bytes so far.
    pub fn bytes_out(&self) -> u64 {
        self.bytes_out.load(Ordering::Relaxed)
    }

    /// Back-end runs so far and their mean wall time, milliseconds.
    pub fn pgr_mean_ms(&self) -> (u64, f64) {
        let runs = self.pgr_runs.load(Ordering::Relaxed);
        let micros = self.pgr_micros.load(Ordering::Relaxed);
        (
            runs,
            if runs > 0 {
                micros as f64 / runs as f64 / 1e3
            } else {
                0.0
            },
        )
    }

    /// Counts received payload bytes.
    pub fn add_bytes_in(&self, bytes: usize) {
        self.bytes_in.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    /// Counts sent payload bytes.
    pub fn add_bytes_out(&self, bytes: usize) {
        self.bytes_out.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    /// Counts an applied upload.
    pub fn upload_applied(&self) {
        self.uploads_applied.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts a re-sent upload acknowledged without being applied.
    pub fn upload_duplicate(&self) {
        self.uploads_duplicate.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts a newly opened session.
    pub fn session_opened(&self) {
        self.sessions_opened.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts a session the server ended because its robot fell silent.
    pub fn session_timed_out(&self) {
        self.sessions_timed_out.fetch_add(1, Ordering::Relaxed);
    }

    /// Sessions ended by the server because their robot fell silent, so far.
    pub fn sessions_timed_out(&self) -> u64 {
        self.sessions_timed_out.load(Ordering::Relaxed)
    }

    /// Records one run of back-end work (GLM searches and optimization of one change).
    pub fn record_pgr(&self, elapsed: Duration) {
        self.pgr_runs.fetch_add(1, Ordering::Relaxed);
        self.pgr_micros.fetch_add(
            u64::try_from(elapsed.as_micros()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
    }

    /// Counts a refused request, by reason (a gRPC status code name).
    pub fn refused(&self, reason: &'static str) {
        if let Ok(mut refused) = self.refused.lock() {
            *refused.entry(reason).or_default() += 1;
        }
    }

    /// Refused requests of one reason so far.
    pub fn refused_count(&self, reason: &str) -> u64 {
        self.refused
            .lock()
            .ok()
            .and_then(|r| r.get(reason).copied())
            .unwrap_or(0)
    }

    /// Prometheus text exposition format (version 0.0.4) of the counters and of each site's gauges.
    pub fn render(&self, sites: &[SiteHandle]) -> String {
        let mut out = String::new();
        let mut counter = |name: &str, help: &str, value: u64| {
            let _ = write!(
                out,
                "# HELP {name} {help}\n# TYPE {name} counter\n{name} {value}\n"
            );
        };
        let load = |c: &AtomicU64| c.load(Ordering::Relaxed);
        counter(
            "evermap_bytes_in_total",
            "Payload bytes received.",
            load(&self.bytes_in),
        );
        counter(
            "evermap_bytes_out_total",
            "Payload bytes sent.",
            load(&self.bytes_out),
        );
        counter(
            "evermap_uploads_applied_total",
            "Upload batches applied.",
            load(&self.uploads_applied),
        );
        counter(
            "evermap_uploads_duplicate_total",
            "Re-sent upload batches acknowledged without being applied.",
            load(&self.uploads_duplicate),
        );
        counter(
            "evermap_sessions_opened_total",
            "Mapping sessions opened.",
            load(&self.sessions_opened),
        );
        counter(
            "evermap_sessions_timed_out_total",
            "Sessions the server ended because their robot was silent past the idle timeout.",
            load(&self.sessions_timed_out),
        );
        counter(
            "evermap_pgr_runs_total",
            "Back-end runs (GLM searches and optimization of one change).",
            load(&self.pgr_runs),
        );
        let _ = write!(
            out,
            "# HELP evermap_pgr_seconds_total Time spent in back-end runs.\n\
             # TYPE evermap_pgr_seconds_total counter\nevermap_pgr_seconds_total {}\n",
            load(&self.pgr_micros) as f64 * 1e-6
        );
        out.push_str(
            "# HELP evermap_requests_refused_total Requests refused, by gRPC status.\n\
             # TYPE evermap_requests_refused_total counter\n",
        );
        if let Ok(refused) = self.refused.lock() {
            for (reason, n) in refused.iter() {
                let _ = writeln!(
                    out,
                    "evermap_requests_refused_total{{reason=\"{reason}\"}} {n}"
                );
            }
        }
        let _ = write!(
            out,
            "# HELP evermap_sites Sites served.\n# TYPE evermap_sites gauge\nevermap_sites {}\n",
            sites.len()
        );
        let gauges: [(&str, &str, Gauge); 9] = [
            ("evermap_site_version", "Current map version.", |s| {
                s.current().version
            }),
            ("evermap_site_sessions", "Sessions of the site.", |s| {
                s.current().counts.sessions
            }),
            ("evermap_site_nodes", "Nodes of the site map.", |s| {
                s.current().counts.nodes
            }),
            (
                "evermap_site_submaps",
                "Finished submaps of the site map.",
                |s| s.current().counts.finished_submaps,
            ),
            (
                "evermap_site_constraints",
                "Pose-graph constraints of the site map.",
                |s| s.current().counts.constraints,
            ),
            (
                "evermap_site_trimmed_submaps",
                "Submaps trimmed from the site map since it began.",
                |s| s.current().counts.trimmed_submaps,
            ),
            (
                "evermap_site_dropped_sessions",
                "Sessions dropped because they ended without being placed in the map.",
                |s| s.current().counts.dropped_sessions,
            ),
            (
                "evermap_site_open_sessions",
                "Sessions opened and not ended yet.",
                |s| s.current().counts.open_sessions,
            ),
            (
                "evermap_site_queue_depth",
                "Requests waiting for the site task.",
                |s| s.queue_depth() as u64,
            ),
        ];
        for (name, help, value) in gauges {
            let _ = write!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n");
            for site in sites {
                let _ = writeln!(out, "{name}{{site=\"{}\"}} {}", site.site(), value(site));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counters_appear_in_the_exposition() {
        let metrics = ServerMetrics::default();
        metrics.add_bytes_in(100);
        metrics.add_bytes_in(23);
        metrics.refused("permission_denied");
        metrics.record_pgr(Duration::from_millis(1500));
        let text = metrics.render(&[]);
        assert!(text.contains("evermap_bytes_in_total 123\n"), "{text}");
        assert!(text.contains("evermap_requests_refused_total{reason=\"permission_denied\"} 1\n"));
        assert!(text.contains("evermap_pgr_seconds_total 1.5\n"));
        assert!(text.contains("evermap_sites 0\n"));
        assert_eq!(metrics.refused_count("permission_denied"), 1);
    }
}
