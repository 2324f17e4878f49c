//! `evermap-fuzz`: runs the decoder fuzz targets for N inputs each (at most S seconds each) and reports
//! inputs/s, accepted/rejected inputs, the largest heap one input used and every distinct finding.
//!
//! ```text
//! cargo run --release -p tests --bin evermap-fuzz -- --inputs 20000 --seconds 120 [--target g2o] \
//!     [--seed 1] [--slow-input-s 2] [--findings-dir out/fuzz] [--json out/fuzz/report.json]
//! ```
//! Exit status 1 when anything was found.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Parser;
use peak_alloc::PeakAlloc;
use tests::fuzz::{FuzzOptions, TARGET_NAMES, fuzz, target};

#[global_allocator]
static HEAP: PeakAlloc = PeakAlloc;

#[derive(Parser, Debug)]
#[command(about = "Fuzz every evermap decoder with mutated real inputs")]
struct Args {
    /// Mutated inputs per target (after its seeds).
    #[arg(long, default_value_t = 2000)]
    inputs: u64,
    /// Wall-time limit per target, seconds.
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Only this target (repeatable); all by default.
    #[arg(long)]
    target: Vec<String>,
    /// Seed of the mutation generator.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Report inputs slower than this, seconds.
    #[arg(long, default_value_t = 2.0)]
    slow_input_s: f64,
    /// Write each finding's smallest input here (`<target>-<n>.bin`).
    #[arg(long)]
    findings_dir: Option<PathBuf>,
    /// Write the reports as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let options = FuzzOptions {
        inputs: args.inputs,
        max_seconds: args.seconds,
        rng_seed: args.seed,
        slow_input_s: Some(args.slow_input_s),
        ..FuzzOptions::default()
    };
    options.validate()?;
    let names: Vec<String> = if args.target.is_empty() {
        TARGET_NAMES.iter().map(|s| (*s).to_owned()).collect()
    } else {
        args.target.clone()
    };
    let datasets = tests::datasets_dir();
    let mut reports = Vec::new();
    println!(
        "{:<16} {:>8} {:>9} {:>9} {:>9} {:>10} {:>9} {:>8}",
        "target", "inputs", "inputs/s", "accepted", "rejected", "max heap", "slowest", "findings"
    );
    for name in &names {
        let mut target = target(name, &datasets).with_context(|| format!("target {name}"))?;
        let report = fuzz(&mut target, &options);
        println!(
            "{:<16} {:>8} {:>9.1} {:>9} {:>9} {:>8.1}MB {:>8.3}s {:>8}",
            report.target,
            report.inputs,
            report.inputs_per_s(),
            report.accepted,
            report.rejected,
            report.max_heap_bytes as f64 / f64::from(1_u32 << 20),
            report.slowest_input_s,
            report.findings.len()
        );
        for (n, finding) in report.findings.iter().enumerate() {
            println!(
                "    {:?} at {} ({} hits, {}-byte reproducer): {}",
                finding.kind,
                finding.key,
                finding.hits,
                finding.input.len(),
                finding.message
            );
            if let Some(dir) = &args.findings_dir {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("cannot create {}", dir.display()))?;
                let path = dir.join(format!("{}-{n}.bin", report.target));
                std::fs::write(&path, &finding.input)
                    .with_context(|| format!("cannot write {}", path.display()))?;
            }
        }
        reports.push(report);
    }
    if let Some(path) = &args.json {
        let json = serde_json::Value::Array(
            reports
                .iter()
                .map(tests::fuzz::FuzzReport::to_json)
                .collect(),
        );
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    let findings: usize = reports.iter().map(|r| r.findings.len()).sum();
    println!("heap per input measured: {}", HEAP.current_usage() > 0);
    if findings > 0 {
        println!("{findings} distinct findings");
        std::process::exit(1);
    }
    Ok(())
}
