//! `evermap-demo`: the fleet simulated in one process — a real map server (the `server` crate) and
//! simulated robots running the real agent code (the `robot-agent` crate) on loopback. Kept out of
//! `evermap-server`, so the server that runs in a data centre links no robot code.

mod command_runtime;
mod demo_command;
mod load_command;
mod memory_attribution;
mod minute_figures;

use clap::{Parser, Subcommand};
use peak_alloc::PeakAlloc;
use tracing_subscriber::filter::LevelFilter;

/// Counts live heap bytes (the load benchmark's per-minute memory attribution), then allocates with
/// the system allocator.
#[global_allocator]
static HEAP: PeakAlloc = PeakAlloc;

/// evermap fleet simulations: the demo (the default) and the load benchmark.
#[derive(Parser)]
#[command(version, about, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    /// The demo's options, when no subcommand is given.
    #[command(flatten)]
    demo: demo_command::DemoArgs,
}

#[derive(Subcommand)]
enum Command {
    /// The fleet in one process (the default): a map server on embedded sled and simulated robots
    /// mapping and cleaning a changing store over loopback zenoh or gRPC; prints map versions, writes
    /// map pictures and a report.
    Demo(demo_command::DemoArgs),
    /// Fleet load benchmark: N simulated robots on several sites stream at real time (or `--speed` times
    /// faster) into one server; reports server CPU and memory, uplink bytes per robot-second and
    /// submap-to-fleet latency, and per minute of robot time memory, latency and throughput (a soak:
    /// `--duration-s 1800 --session-s 300`) with a chart, `minutes.png`.
    Load(load_command::LoadArgs),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    // The demo and the benchmark print their own progress and figures; the server's and the robots'
    // log lines are off unless RUST_LOG asks for them (then on standard error).
    server::init_logging(LevelFilter::OFF, server::LogOutput::Stderr);
    match cli.command {
        Some(Command::Demo(args)) => demo_command::run(&args),
        Some(Command::Load(args)) => load_command::run(&args),
        None => demo_command::run(&cli.demo),
    }
}
