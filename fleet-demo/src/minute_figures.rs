//! The load benchmark's figures per minute of robot time, what a soak is judged by: the process's
//! resident memory and the allocator's live heap at the end of each minute with what holds it
//! ([`MemoryAttribution`]), the latency of the submaps finished in it (median and p95), and the
//! throughput (batches acknowledged, uplink bytes); the least-squares slopes of memory, heap and p95
//! over the minutes after a warm-up, and a chart of them against time.

use robot_agent::line_chart::{LineChart, Series};
use serde_json::json;

use crate::memory_attribution::MemoryAttribution;

/// Minutes of robot time left out of the slopes (the map of every site is still growing into its
/// steady state: robots start, submaps accumulate until the first trims).
pub const WARM_UP_MINUTES: usize = 5;

/// What was sampled at the end of a minute of robot time.
#[derive(Clone, Debug, Default)]
pub struct MinuteSample {
    /// Minute of robot time since the measured phase began.
    pub minute: f64,
    /// Resident set size of the process, MiB.
    pub rss_mb: Option<f64>,
    /// Uplink bytes the server had received since the measured phase began.
    pub uplink_bytes: u64,
    /// The live heap and what holds it.
    pub memory: MemoryAttribution,
}

/// What was measured during one run, in robot time (minutes since the measured phase began).
#[derive(Clone, Debug, Default)]
pub struct MinuteInputs {
    /// At the end of each minute.
    pub samples: Vec<MinuteSample>,
    /// Every finished submap: (minute of robot time it was finished, seconds until its version was in
    /// every cache of its site).
    pub submap_latencies: Vec<(f64, f64)>,
    /// Minute of robot time of every acknowledged batch.
    pub batch_acks: Vec<f64>,
}

/// The figures of one minute of robot time, `[minute, minute + 1)`.
#[derive(Clone, Debug, PartialEq)]
pub struct MinuteFigures {
    /// Index of the minute, from 0.
    pub minute: usize,
    /// Resident set size of the process at the minute's end, MiB.
    pub rss_mb: Option<f64>,
    /// The live heap at the minute's end and what holds it (`None`: no sample).
    pub memory: Option<MemoryAttribution>,
    /// Median latency (finished on a robot → in every cache of the site) of the submaps finished in
    /// the minute, seconds; `None` when none was.
    pub latency_p50_s: Option<f64>,
    /// The same, 95th percentile (nearest rank).
    pub latency_p95_s: Option<f64>,
    /// Submaps finished in the minute (delivered ones; the latencies' count).
    pub submaps: usize,
    /// Batches the server acknowledged in the minute.
    pub batches: usize,
    /// Uplink bytes the server received in the minute.
    pub uplink_bytes: u64,
}

/// The per-minute table of `minutes` whole minutes.
pub fn minute_figures(inputs: &MinuteInputs, minutes: usize) -> Vec<MinuteFigures> {
    let in_minute = |t: f64, m: usize| t >= m as f64 && t < (m + 1) as f64;
    let mut previous_bytes = 0;
    (0..minutes)
        .map(|m| {
            let sample = inputs
                .samples
                .iter()
                .filter(|s| (s.minute - (m + 1) as f64).abs() < 0.5)
                .min_by(|a, b| {
                    (a.minute - (m + 1) as f64)
                        .abs()
                        .total_cmp(&(b.minute - (m + 1) as f64).abs())
                });
            let uplink_bytes = sample.map_or(0, |s| s.uplink_bytes.saturating_sub(previous_bytes));
            if let Some(s) = sample {
                previous_bytes = s.uplink_bytes;
            }
            let mut latencies: Vec<f64> = inputs
                .submap_latencies
                .iter()
                .filter(|(t, _)| in_minute(*t, m))
                .map(|(_, l)| *l)
                .collect();
            latencies.sort_by(f64::total_cmp);
            MinuteFigures {
                minute: m,
                rss_mb: sample.and_then(|s| s.rss_mb),
                memory: sample.map(|s| s.memory.clone()),
                latency_p50_s: quantile(&latencies, 0.5),
                latency_p95_s: quantile(&latencies, 0.95),
                submaps: latencies.len(),
                batches: inputs
                    .batch_acks
                    .iter()
                    .filter(|t| in_minute(**t, m))
                    .count(),
                uplink_bytes,
            }
        })
        .collect()
}

/// Nearest-rank quantile of sorted values.
fn quantile(sorted: &[f64], q: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    Some(sorted[((sorted.len() - 1) as f64 * q).round() as usize])
}

/// Least-squares slope of `(x, y)` points, `None` with fewer than 2 distinct x.
pub fn slope(points: &[(f64, f64)]) -> Option<f64> {
    let n = points.len() as f64;
    if points.len() < 2 {
        return None;
    }
    let mean_x = points.iter().map(|p| p.0).sum::<f64>() / n;
    let mean_y = points.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = points.iter().map(|p| (p.0 - mean_x).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mean_x) * (p.1 - mean_y)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

/// The minutes after the warm-up as `(minute, value)` points (the minute's end, so minute 5 is the
/// first full minute after it).
fn after_warm_up(
    figures: &[MinuteFigures],
    value: impl Fn(&MinuteFigures) -> Option<f64>,
) -> Vec<(f64, f64)> {
    figures
        .iter()
        .filter(|f| f.minute >= WARM_UP_MINUTES)
        .filter_map(|f| Some(((f.minute + 1) as f64, value(f)?)))
        .collect()
}

/// The whole periods of `period` minutes after the warm-up, as `(first minute, figures)`.
fn whole_periods(figures: &[MinuteFigures], period: usize) -> Vec<(usize, &[MinuteFigures])> {
    let Some(first) = figures.iter().position(|f| f.minute >= WARM_UP_MINUTES) else {
        return Vec::new();
    };
    figures[first..]
        .chunks_exact(period.max(1))
        .map(|chunk| (chunk[0].minute, chunk))
        .collect()
}

/// One whole session period's figures.
struct PeriodFigures {
    /// Its first minute.
    first_minute: usize,
    /// Its middle, in minutes (the x of the slopes).
    middle: f64,
    /// Mean RSS, MiB (`None` when a minute has none).
    rss_mean_mb: Option<f64>,
    /// Mean live heap, MiB (`None` when a minute has none).
    live_heap_mean_mb: Option<f64>,
    /// Largest p95 latency, seconds.
    p95_max_s: Option<f64>,
}

/// Memory and latency per whole session period after the warm-up (the robots' sessions end every
/// `period` minutes, and each end trims: memory saws up and down with that period, so a least-squares
/// slope over minutes that start in a trough and end at a peak reads the saw's phase as growth). Per
/// period: mean RSS, mean live heap, largest p95; and the least-squares slopes of those over the
/// periods' middle minutes.
fn by_period(figures: &[MinuteFigures], period: usize) -> serde_json::Value {
    let mean = |chunk: &[MinuteFigures], value: &dyn Fn(&MinuteFigures) -> Option<f64>| {
        let values: Vec<f64> = chunk.iter().filter_map(value).collect();
        (values.len() == chunk.len()).then(|| values.iter().sum::<f64>() / values.len() as f64)
    };
    let periods: Vec<PeriodFigures> = whole_periods(figures, period)
        .into_iter()
        .map(|(first_minute, chunk)| PeriodFigures {
            first_minute,
            middle: first_minute as f64 + chunk.len() as f64 / 2.0,
            rss_mean_mb: mean(chunk, &|f| f.rss_mb),
            live_heap_mean_mb: mean(chunk, &|f| f.memory.as_ref()?.live_heap_mb),
            p95_max_s: chunk
                .iter()
                .filter_map(|f| f.latency_p95_s)
                .reduce(f64::max),
        })
        .collect();
    let slope_of = |value: fn(&PeriodFigures) -> Option<f64>| {
        slope(
            &periods
                .iter()
                .filter_map(|p| Some((p.middle, value(p)?)))
                .collect::<Vec<_>>(),
        )
    };
    json!({
        "period_minutes": period,
        "periods": periods.iter().map(|p| json!({
            "first_minute": p.first_minute,
            "rss_mean_mb": p.rss_mean_mb,
            "live_heap_mean_mb": p.live_heap_mean_mb,
            "p95_max_s": p.p95_max_s,
        })).collect::<Vec<_>>(),
        "rss_mean_slope_mb_per_minute": slope_of(|p| p.rss_mean_mb),
        "live_heap_mean_slope_mb_per_minute": slope_of(|p| p.live_heap_mean_mb),
        "p95_max_slope_s_per_minute": slope_of(|p| p.p95_max_s),
    })
}

/// The report's `minutes` array and its `after_warm_up` summary: slopes of RSS (MiB per minute) and of
/// p95 latency (s per minute) over the minutes after the warm-up, with their first and last values, and
/// with `session_period_minutes` (how often the robots' sessions end) the same per whole period.
pub fn report(
    figures: &[MinuteFigures],
    session_period_minutes: Option<usize>,
) -> serde_json::Value {
    let rss = after_warm_up(figures, |f| f.rss_mb);
    let heap = after_warm_up(figures, |f| f.memory.as_ref()?.live_heap_mb);
    let history = after_warm_up(figures, |f| Some(f.memory.as_ref()?.history_grids_mb()));
    let store = after_warm_up(figures, |f| Some(f.memory.as_ref()?.store_disk_mb));
    let store_held = after_warm_up(figures, |f| Some(f.memory.as_ref()?.store_held_mb));
    let p95 = after_warm_up(figures, |f| f.latency_p95_s);
    let rows: Vec<serde_json::Value> = figures
        .iter()
        .map(|f| {
            json!({
                "minute": f.minute,
                "rss_mb": f.rss_mb,
                "memory": f.memory.as_ref().map(MemoryAttribution::to_json),
                "latency_p50_s": f.latency_p50_s,
                "latency_p95_s": f.latency_p95_s,
                "submaps": f.submaps,
                "batches": f.batches,
                "uplink_bytes": f.uplink_bytes,
            })
        })
        .collect();
    json!({
        "minutes": rows,
        "after_warm_up": {
            "warm_up_minutes": WARM_UP_MINUTES,
            "rss_slope_mb_per_minute": slope(&rss),
            "rss_first_mb": rss.first().map(|p| p.1),
            "rss_last_mb": rss.last().map(|p| p.1),
            "rss_max_mb": rss.iter().map(|p| p.1).reduce(f64::max),
            "live_heap_slope_mb_per_minute": slope(&heap),
            "live_heap_first_mb": heap.first().map(|p| p.1),
            "live_heap_last_mb": heap.last().map(|p| p.1),
            "history_grids_slope_mb_per_minute": slope(&history),
            "store_disk_slope_mb_per_minute": slope(&store),
            "store_held_slope_mb_per_minute": slope(&store_held),
            "p95_slope_s_per_minute": slope(&p95),
            "p95_first_s": p95.first().map(|p| p.1),
            "p95_last_s": p95.last().map(|p| p.1),
            "p95_max_s": p95.iter().map(|p| p.1).reduce(f64::max),
            "by_session_period": session_period_minutes.map(|period| by_period(figures, period)),
        },
    })
}

/// Two charts stacked, `width` wide: resident memory per minute on top, median and p95 latency below.
/// Returns `(width, height, rgb pixels)`.
pub fn chart(figures: &[MinuteFigures], title: &str, width: u32) -> (u32, u32, Vec<u8>) {
    let points = |value: &dyn Fn(&MinuteFigures) -> Option<f64>| -> Vec<(f64, f64)> {
        figures
            .iter()
            .filter_map(|f| Some(((f.minute + 1) as f64, value(f)?)))
            .collect()
    };
    let memory = LineChart {
        title: format!("{title}: process RSS and live heap at the end of each minute"),
        x_label: "minute of robot time".into(),
        y_label: "MiB".into(),
        series: vec![
            Series {
                name: "RSS".into(),
                color: [30, 90, 200],
                points: points(&|f| f.rss_mb),
            },
            Series {
                name: "live heap".into(),
                color: [230, 140, 0],
                points: points(&|f| f.memory.as_ref()?.live_heap_mb),
            },
        ],
        y_min: Some(0.0),
    };
    let latency = LineChart {
        title: "submap finished -> in every cache of its site, by the minute it was finished"
            .into(),
        x_label: "minute of robot time".into(),
        y_label: "seconds".into(),
        series: vec![
            Series {
                name: "p95".into(),
                color: [200, 40, 40],
                points: points(&|f| f.latency_p95_s),
            },
            Series {
                name: "median".into(),
                color: [0, 150, 0],
                points: points(&|f| f.latency_p50_s),
            },
        ],
        y_min: Some(0.0),
    };
    let (w, h_top, mut pixels) = memory.render(width, 360);
    let (_, h_bottom, bottom) = latency.render(width, 360);
    pixels.extend_from_slice(&bottom);
    (w, h_top + h_bottom, pixels)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minutes_bucket_latencies_batches_and_bytes() {
        let inputs = MinuteInputs {
            samples: vec![
                MinuteSample {
                    minute: 1.0,
                    rss_mb: Some(100.0),
                    uplink_bytes: 1000,
                    memory: MemoryAttribution {
                        live_heap_mb: Some(80.0),
                        ..MemoryAttribution::default()
                    },
                },
                MinuteSample {
                    minute: 2.01,
                    rss_mb: Some(110.0),
                    uplink_bytes: 2500,
                    memory: MemoryAttribution::default(),
                },
            ],
            submap_latencies: vec![(0.2, 1.0), (0.9, 3.0), (0.5, 2.0), (1.5, 10.0)],
            batch_acks: vec![0.1, 0.2, 1.9],
        };
        let figures = minute_figures(&inputs, 3);
        assert_eq!(figures.len(), 3);
        assert_eq!(figures[0].rss_mb, Some(100.0));
        assert_eq!(
            figures[0].memory.as_ref().and_then(|m| m.live_heap_mb),
            Some(80.0)
        );
        assert_eq!(figures[0].latency_p50_s, Some(2.0));
        assert_eq!(figures[0].latency_p95_s, Some(3.0));
        assert_eq!((figures[0].submaps, figures[0].batches), (3, 2));
        assert_eq!(figures[0].uplink_bytes, 1000);
        assert_eq!(figures[1].rss_mb, Some(110.0));
        assert_eq!(figures[1].latency_p95_s, Some(10.0));
        assert_eq!((figures[1].batches, figures[1].uplink_bytes), (1, 1500));
        // No sample and no submap in the third minute.
        assert_eq!(figures[2].rss_mb, None);
        assert_eq!(figures[2].memory, None);
        assert_eq!(figures[2].latency_p95_s, None);
        assert_eq!(figures[2].uplink_bytes, 0);
    }

    #[test]
    fn slope_is_least_squares_and_needs_two_points() {
        let line: Vec<(f64, f64)> = (0..10)
            .map(|x| (f64::from(x), 3.0 + 0.5 * f64::from(x)))
            .collect();
        assert!((slope(&line).expect("slope") - 0.5).abs() < 1e-12);
        assert_eq!(slope(&line[..1]), None);
        assert_eq!(slope(&[(1.0, 1.0), (1.0, 2.0)]), None);
    }

    #[test]
    fn the_summary_ignores_the_warm_up() {
        // Memory grows 50 MiB a minute during the warm-up, then stays flat.
        let figures: Vec<MinuteFigures> = (0..12)
            .map(|m| MinuteFigures {
                minute: m,
                rss_mb: Some(if m < WARM_UP_MINUTES {
                    50.0 * m as f64
                } else {
                    300.0
                }),
                // The heap grows 2 MiB a minute throughout.
                memory: Some(MemoryAttribution {
                    live_heap_mb: Some(100.0 + 2.0 * m as f64),
                    ..MemoryAttribution::default()
                }),
                latency_p50_s: Some(1.0),
                latency_p95_s: Some(2.0 + m as f64),
                submaps: 1,
                batches: 1,
                uplink_bytes: 1,
            })
            .collect();
        let summary = &report(&figures, None)["after_warm_up"];
        assert_eq!(summary["rss_slope_mb_per_minute"].as_f64(), Some(0.0));
        assert_eq!(summary["rss_first_mb"].as_f64(), Some(300.0));
        let heap = summary["live_heap_slope_mb_per_minute"]
            .as_f64()
            .expect("heap");
        assert!((heap - 2.0).abs() < 1e-12, "{heap}");
        assert!((summary["p95_slope_s_per_minute"].as_f64().expect("p95") - 1.0).abs() < 1e-12);
        let (w, h, pixels) = chart(&figures, "test", 400);
        assert_eq!((w, h), (400, 720));
        assert_eq!(pixels.len(), 3 * 400 * 720);
        // Something other than the white background was drawn.
        assert!(pixels.iter().any(|&p| p != 255));
    }

    #[test]
    fn a_flat_saw_is_flat_by_period_however_the_minutes_fall() {
        // Memory saws between 1000 and 1400 MiB with a 5-minute period (a trim at every session end)
        // and p95 between 1 and 3 s; minutes 5..=23: starting in a trough, ending near a peak.
        let figures: Vec<MinuteFigures> = (0..24)
            .map(|m| MinuteFigures {
                minute: m,
                rss_mb: Some(1000.0 + 100.0 * (m % 5) as f64),
                memory: Some(MemoryAttribution {
                    live_heap_mb: Some(900.0 + 100.0 * (m % 5) as f64),
                    ..MemoryAttribution::default()
                }),
                latency_p50_s: Some(0.5),
                latency_p95_s: Some(1.0 + 0.5 * (m % 5) as f64),
                submaps: 1,
                batches: 1,
                uplink_bytes: 1,
            })
            .collect();
        let summary = &report(&figures, Some(5))["after_warm_up"];
        // Minute by minute the saw's phase reads as growth ...
        let by_minute = summary["rss_slope_mb_per_minute"].as_f64().expect("slope");
        assert!(by_minute > 2.0, "{by_minute}");
        // ... per whole period it is flat: three periods (minutes 5, 10, 15), the fourth not whole.
        let period = &summary["by_session_period"];
        assert_eq!(period["periods"].as_array().map(Vec::len), Some(3));
        assert_eq!(period["periods"][0]["first_minute"].as_u64(), Some(5));
        assert_eq!(period["periods"][0]["rss_mean_mb"].as_f64(), Some(1200.0));
        assert_eq!(period["periods"][2]["p95_max_s"].as_f64(), Some(3.0));
        for key in [
            "rss_mean_slope_mb_per_minute",
            "live_heap_mean_slope_mb_per_minute",
            "p95_max_slope_s_per_minute",
        ] {
            let slope = period[key].as_f64().expect(key);
            assert!(slope.abs() < 1e-9, "{key}: {slope}");
        }
        // Growth by period is still seen.
        let growing: Vec<MinuteFigures> = figures
            .iter()
            .map(|f| MinuteFigures {
                rss_mb: f.rss_mb.map(|r| r + 10.0 * f.minute as f64),
                ..f.clone()
            })
            .collect();
        let slope = report(&growing, Some(5))["after_warm_up"]["by_session_period"]
            ["rss_mean_slope_mb_per_minute"]
            .as_f64()
            .expect("slope");
        assert!((slope - 10.0).abs() < 1e-9, "{slope}");
    }
}
