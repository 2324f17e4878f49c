//! Reading speed of the recording readers: reads each recording given on the command line `--repeat`
//! times (default 5) and prints one JSON line per recording with the best time, the messages kept and
//! the time per message kept (scans + odometry + IMU + TF messages).
//!
//!     cargo run --release --example read_recording -- [--repeat N] RECORDING...

use std::time::Instant;

use robot_agent::source::read_recording;

fn main() -> anyhow::Result<()> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut repeat = 5usize;
    if let Some(i) = args.iter().position(|a| a == "--repeat") {
        anyhow::ensure!(i + 1 < args.len(), "--repeat needs a number");
        repeat = args[i + 1].parse()?;
        args.drain(i..=i + 1);
    }
    anyhow::ensure!(
        !args.is_empty() && repeat > 0,
        "usage: read_recording [--repeat N] RECORDING..."
    );
    for path in &args {
        let mut best = f64::INFINITY;
        let mut messages = 0;
        for _ in 0..repeat {
            let start = Instant::now();
            let recording = read_recording(std::path::Path::new(path))?;
            best = best.min(start.elapsed().as_secs_f64());
            let r = &recording.report;
            messages =
                r.scans + r.odometry + r.imu + r.tf + r.duplicates_dropped + r.same_stamp_dropped;
        }
        println!(
            "{}",
            serde_json::json!({
                "recording": path,
                "best_of": repeat,
                "read_s": best,
                "messages": messages,
                "us_per_message": best * 1e6 / messages.max(1) as f64,
                "messages_per_s": messages as f64 / best,
            })
        );
    }
    Ok(())
}
