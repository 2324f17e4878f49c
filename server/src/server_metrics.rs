//! Server counters and their Prometheus text exposition.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use crate::site::SiteHandle;

/// Reads one per-site gauge or counter.
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
    site_unloads: AtomicU64,
    site_restores: AtomicU64,
    site_restore_micros: AtomicU64,
    site_restore_max_micros: AtomicU64,
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

    /// Counts a site map dropped from memory (idle, or loaded at the start only to store its summary).
    pub fn site_unloaded(&self) {
        self.site_unloads.fetch_add(1, Ordering::Relaxed);
    }

    /// Records the restore of an unloaded site (its checkpoint read, the log after it replayed).
    pub fn site_restored(&self, elapsed: Duration) {
        let micros = u64::try_from(elapsed.as_micros()).unwrap_or(u64::MAX);
        self.site_restores.fetch_add(1, Ordering::Relaxed);
        self.site_restore_micros
            .fetch_add(micros, Ordering::Relaxed);
        self.site_restore_max_micros
            .fetch_max(micros, Ordering::Relaxed);
    }

    /// Sites unloaded and unloaded sites restored so far.
    pub fn site_unloads_and_restores(&self) -> (u64, u64) {
        (
            self.site_unloads.load(Ordering::Relaxed),
            self.site_restores.load(Ordering::Relaxed),
        )
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
        let loaded = sites.iter().filter(|s| s.is_loaded()).count();
        let _ = write!(
            out,
            "# HELP evermap_sites_loaded Sites whose map is in memory.\n\
             # TYPE evermap_sites_loaded gauge\nevermap_sites_loaded {loaded}\n\
             # HELP evermap_sites_unloaded Sites whose map is out of memory: idle, or not asked for since the \
             start (restored at their next request).\n\
             # TYPE evermap_sites_unloaded gauge\nevermap_sites_unloaded {}\n",
            sites.len() - loaded
        );
        let _ = write!(
            out,
            "# HELP evermap_site_unloads_total Site maps dropped from memory: idle, or loaded at the start \
             for want of a summary.\n\
             # TYPE evermap_site_unloads_total counter\nevermap_site_unloads_total {}\n\
             # HELP evermap_site_restore_seconds Restores of unloaded sites (checkpoint read, log after it \
             replayed) and their time.\n\
             # TYPE evermap_site_restore_seconds summary\n\
             evermap_site_restore_seconds_sum {}\nevermap_site_restore_seconds_count {}\n\
             # HELP evermap_site_restore_seconds_max The longest restore of an unloaded site.\n\
             # TYPE evermap_site_restore_seconds_max gauge\nevermap_site_restore_seconds_max {}\n",
            load(&self.site_unloads),
            load(&self.site_restore_micros) as f64 * 1e-6,
            load(&self.site_restores),
            load(&self.site_restore_max_micros) as f64 * 1e-6,
        );
        let gauges: [(&str, &str, Gauge); 12] = [
            ("evermap_site_version", "Current map version.", |s| {
                s.current().version
            }),
            (
                "evermap_site_loaded",
                "1 while the site's map is in memory, 0 while it is unloaded (idle).",
                |s| u64::from(s.is_loaded()),
            ),
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
            (
                "evermap_site_loop_closures_beyond_drift",
                "Matches refused because they moved their node farther than the drift since its last \
                 loop explains, not confirmed by other matches since.",
                |s| s.current().counts.loop_closures_beyond_drift,
            ),
            (
                "evermap_site_loop_closures_retracted",
                "Accepted loop closures out of the graph now because the optimized graph refuses them.",
                |s| s.current().counts.loop_closures_retracted,
            ),
        ];
        for (name, help, value) in gauges {
            let _ = write!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n");
            for site in sites {
                let _ = writeln!(out, "{name}{{site=\"{}\"}} {}", site.site(), value(site));
            }
        }
        // What each site's map counted since the site began (rebuilt by replay after a restart).
        let counters: [(&str, &str, Gauge); 4] = [
            (
                "evermap_site_loop_closures_total",
                "Loop closures accepted (those of trimmed submaps included).",
                |s| s.current().counts.loop_closures,
            ),
            (
                "evermap_site_loop_closure_searches_total",
                "Loop-closure searches queued.",
                |s| s.current().counts.loop_closure_searches,
            ),
            (
                "evermap_site_loop_closures_outvoted_total",
                "Matches refused because other matches of their node disagreed with them.",
                |s| s.current().counts.loop_closures_outvoted,
            ),
            (
                "evermap_site_session_start_retries_total",
                "Whole-map searches for a session's start after its first one.",
                |s| s.current().counts.session_starts.retries,
            ),
        ];
        for (name, help, value) in counters {
            let _ = write!(out, "# HELP {name} {help}\n# TYPE {name} counter\n");
            for site in sites {
                let _ = writeln!(out, "{name}{{site=\"{}\"}} {}", site.site(), value(site));
            }
        }
        out.push_str(
            "# HELP evermap_site_session_starts_total Session-start decisions, by decision: prior (a \
             robot's placement taken on probation), placed and refused (the server's whole-map \
             searches), committed, revoked, gave_up.\n\
             # TYPE evermap_site_session_starts_total counter\n",
        );
        for site in sites {
            let starts = site.current().counts.session_starts;
            for (decision, n) in [
                ("prior", starts.priors),
                ("placed", starts.placed),
                ("refused", starts.refused),
                ("committed", starts.committed),
                ("revoked", starts.revoked),
                ("gave_up", starts.gave_up),
            ] {
                let _ = writeln!(
                    out,
                    "evermap_site_session_starts_total{{site=\"{}\",decision=\"{decision}\"}} {n}",
                    site.site()
                );
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use mapping::geometry::Rigid2;
    use mapping::lifelong::LifelongOptions;
    use proto::{UploadBatch, UploadItem};
    use storage::{MapStore, MemStore};
    use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

    use super::*;
    use crate::metrics_endpoint::{bind_metrics, serve_metrics};
    use crate::site::{SiteTask, SiteTaskOptions};
    use crate::testing::{grid, match_to_submap, node};

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

    /// Node `k` of a straight route (x = 0.1 k), inserted into submap `k`, with that submap finished.
    fn node_and_submap(k: u32) -> [UploadItem; 2] {
        [
            node(k, &[k]),
            UploadItem::SubmapFinished {
                index: k,
                grid: grid(),
            },
        ]
    }

    fn batch(session: &str, items: Vec<UploadItem>) -> UploadBatch {
        UploadBatch {
            site: "s".into(),
            robot_id: "r".into(),
            session_uuid: session.into(),
            seq: 1,
            items,
        }
    }

    // Reference: issue 35 item 6 — the loop-closure and session-start counters reach /metrics.
    #[tokio::test]
    async fn metrics_serve_each_sites_loop_closure_and_session_start_counters() {
        let mut options = LifelongOptions::default();
        options.session_start.probation_matches = 2;
        options.session_start.probation_min_separation_m = 0.15;
        options.session_start.hold_back_nodes = 1;
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let metrics = Arc::new(ServerMetrics::default());
        let (site, _task) = SiteTask::spawn(
            "s",
            options,
            store,
            Arc::clone(&metrics),
            SiteTaskOptions::default(),
        )
        .await
        .unwrap();
        // a maps a route; b drives it with its robot's prior, and its robot matches its nodes to a's
        // submaps where they are: loop closures, which commit b's prior.
        site.open_session("r", "a").await.unwrap();
        let mut a: Vec<UploadItem> = (0..6).flat_map(node_and_submap).collect();
        a.push(UploadItem::SessionEnd);
        site.upload(batch("a", a)).await.unwrap();
        site.open_session("r", "b").await.unwrap();
        let mut b = vec![UploadItem::SessionStartPrior {
            global_from_local: Rigid2::identity(),
            glm_on_robot: true,
            at_dock: false,
            fitted: None,
        }];
        for k in 0..6 {
            b.extend(node_and_submap(k));
            if k % 2 == 0 {
                b.push(match_to_submap(k));
            }
        }
        site.upload(batch("b", b)).await.unwrap();
        let counts = site.current().counts;
        assert!(counts.loop_closures >= 2, "{counts:?}");

        // Scraped over HTTP, as Prometheus does.
        let listener = bind_metrics(([127, 0, 0, 1], 0).into()).await.unwrap();
        let addr = listener.local_addr().unwrap();
        let endpoint = tokio::spawn(serve_metrics(listener, metrics, Arc::new(vec![site])));
        let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
        stream
            .write_all(b"GET /metrics HTTP/1.1\r\nhost: evermap\r\n\r\n")
            .await
            .unwrap();
        let mut text = String::new();
        stream.read_to_string(&mut text).await.unwrap();
        endpoint.abort();
        let expected = [
            "# TYPE evermap_site_loop_closures_total counter".to_owned(),
            format!(
                "evermap_site_loop_closures_total{{site=\"s\"}} {}",
                counts.loop_closures
            ),
            format!(
                "evermap_site_loop_closure_searches_total{{site=\"s\"}} {}",
                counts.loop_closure_searches
            ),
            format!(
                "evermap_site_loop_closures_outvoted_total{{site=\"s\"}} {}",
                counts.loop_closures_outvoted
            ),
            "# TYPE evermap_site_loop_closures_beyond_drift gauge".to_owned(),
            format!(
                "evermap_site_loop_closures_beyond_drift{{site=\"s\"}} {}",
                counts.loop_closures_beyond_drift
            ),
            format!(
                "evermap_site_loop_closures_retracted{{site=\"s\"}} {}",
                counts.loop_closures_retracted
            ),
            "# TYPE evermap_site_session_starts_total counter".to_owned(),
            "evermap_site_session_starts_total{site=\"s\",decision=\"prior\"} 1".to_owned(),
            "evermap_site_session_starts_total{site=\"s\",decision=\"committed\"} 1".to_owned(),
            "evermap_site_session_starts_total{site=\"s\",decision=\"revoked\"} 0".to_owned(),
            "evermap_site_session_start_retries_total{site=\"s\"} 0".to_owned(),
        ];
        for line in expected {
            assert!(
                text.lines().any(|l| l == line),
                "{line:?} missing from\n{text}"
            );
        }
    }
}
