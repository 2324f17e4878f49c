//! A robot catching up with its site after time offline, as the load benchmark measures it (issue 34):
//! the delta since the version it last saw against the whole map.

use std::time::Instant;

use robot_agent::uplink::{GrpcUplink, MapUplink as _};

/// What a robot that last saw `from_version` receives when it catches up: the delta since, its bytes and
/// time, and the whole map's (the delta since version 0) for comparison.
pub(crate) struct CatchUp {
    pub(crate) delta: proto::MapDelta,
    pub(crate) ms: f64,
    pub(crate) bytes: u64,
    pub(crate) whole_map_ms: f64,
    pub(crate) whole_map_bytes: u64,
}

/// Asks the server, as a robot would, for everything since `from_version`, then for the whole map,
/// counting the bytes the server sent for each (`metrics`) and the time each took.
pub(crate) async fn catch_up_since(
    mut uplink: GrpcUplink,
    metrics: &server::ServerMetrics,
    from_version: u64,
) -> anyhow::Result<CatchUp> {
    let before = metrics.bytes_out();
    let t = Instant::now();
    let delta = uplink.delta_since(from_version).await?;
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let bytes = metrics.bytes_out() - before;
    let before = metrics.bytes_out();
    let t = Instant::now();
    let _ = uplink.delta_since(0).await?;
    let whole_map_ms = t.elapsed().as_secs_f64() * 1e3;
    Ok(CatchUp {
        delta,
        ms,
        bytes,
        whole_map_ms,
        whole_map_bytes: metrics.bytes_out() - before,
    })
}
