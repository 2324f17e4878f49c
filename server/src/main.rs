//! `evermap-server`: the fleet map server and its back-end tools.

mod command_runtime;
mod demo_command;
mod load_command;
mod optimize_command;
mod serve_command;

use clap::{Parser, Subcommand};

/// evermap map server.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// The fleet in one process: a map server on embedded sled and simulated robots mapping and cleaning a
    /// changing store over loopback gRPC; prints map versions, writes map pictures and a report.
    Demo(demo_command::DemoArgs),
    /// Fleet load benchmark: N simulated robots on several sites stream at real time into one server;
    /// reports server CPU and memory, uplink bytes per robot-second and submap-to-fleet latency.
    Load(load_command::LoadArgs),
    /// Optimize a g2o/TORO pose graph file and print one JSON line of results.
    Optimize(optimize_command::OptimizeArgs),
    /// Serves site maps to robots over gRPC (with health, reflection and Prometheus metrics).
    Serve(serve_command::ServeArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Some(Command::Demo(args)) => demo_command::run(&args),
        Some(Command::Load(args)) => load_command::run(&args),
        Some(Command::Optimize(args)) => optimize_command::run(&args),
        Some(Command::Serve(args)) => serve_command::run(&args),
        None => Ok(()),
    }
}
