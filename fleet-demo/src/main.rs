//! `evermap-demo`: the simulations — the fleet simulated in one process (a real map server, the `server`
//! crate, and simulated robots running the real agent code, the `robot-agent` crate, on loopback), the
//! load benchmark, and the experiments on the simulated store (`lifelong`, `simulate`). Kept out of
//! `evermap-server` and `evermap-agent`, so the server that runs in a data centre links no robot code
//! and neither binary links the simulator.

mod catch_up;
mod command_runtime;
mod demo_command;
mod idle_sites;
mod lifelong_command;
mod lifelong_resume;
mod load_command;
mod load_fleet;
mod memory_attribution;
mod minute_figures;
mod prepared_session;
mod prepared_stream;
mod simulate_command;
mod site_growth;
mod submap_latency;

use clap::{Parser, Subcommand};
use peak_alloc::PeakAlloc;
use tracing_subscriber::filter::LevelFilter;

/// Counts live heap bytes (the load benchmark's per-minute memory attribution), then allocates with
/// the system allocator.
#[global_allocator]
static HEAP: PeakAlloc = PeakAlloc;

/// evermap simulations: the fleet demo (the default), the load benchmark, and the lifelong experiment
/// on the simulated store.
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
    /// The lifelong experiment on the simulated changing store: session 0 maps it, sessions 1..N relocalize,
    /// localize and update the map per the trimming policy; scored against ground truth (CRI, MRCL, AMS,
    /// ATE, MCR, graph size).
    Lifelong(lifelong_command::LifelongArgs),
    /// Writes one session of the simulated changing store as a ROS1 bag plus its ground truth (TUM).
    Simulate(simulate_command::SimulateArgs),
}

/// Runs the command; an error is reported with its causes, each once (`proto::error_report`).
fn main() -> std::process::ExitCode {
    proto::exit_code(run())
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    // Every command prints its own progress and figures; the server's and the robots' log lines are off
    // unless RUST_LOG asks for them (then on standard error).
    server::init_logging(LevelFilter::OFF, server::LogOutput::Stderr);
    match cli.command {
        Some(Command::Demo(args)) => demo_command::run(&args),
        Some(Command::Load(args)) => load_command::run(&args),
        Some(Command::Lifelong(args)) => lifelong_command::run(&args),
        Some(Command::Simulate(args)) => simulate_command::run(&args),
        None => demo_command::run(&cli.demo),
    }
}
