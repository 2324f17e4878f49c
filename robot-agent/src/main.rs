//! `evermap-agent`: runs on each robot; also offers offline tools on recordings. What a robot does not
//! run — the simulated store and the experiments on it — is `evermap-demo`'s (the `fleet-demo` crate),
//! so this binary links no simulator.

mod commands;

use clap::{Parser, Subcommand};
use proto::logging::{LogOutput, init_logging};
use tracing_subscriber::filter::LevelFilter;

/// evermap robot agent: local LiDAR odometry and global matching, and offline tools on recordings.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Maps a whole recording (LLO + GLM + PGR in one process) and writes the trajectory, the map and a report.
    Offline(commands::offline::OfflineArgs),
    /// Builds a map from the first 60 % of a recording and relocalizes scans of the rest with no prior.
    Relocalize(commands::relocalize::RelocalizeArgs),
    /// Runs a recording as several time sessions through the lifelong map (relocalization, GLM across
    /// sessions, trimming) and scores it over cross-session relations.
    Sessions(commands::sessions::SessionsArgs),
    /// Runs LLO on a recording and streams it to the fleet map server (durable outbox, resumes after a
    /// reconnect).
    Run(commands::run::RunArgs),
}

/// Runs the command; an error is reported with its causes, each once (`proto::error_report`).
fn main() -> std::process::ExitCode {
    proto::exit_code(run())
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    // `run` logs to standard output at INFO as a service does; the offline tools print their results
    // there and log nothing unless RUST_LOG asks (then to standard error).
    let (level, output) = match &cli.command {
        Command::Run(_) => (LevelFilter::INFO, LogOutput::Stdout),
        _ => (LevelFilter::OFF, LogOutput::Stderr),
    };
    init_logging(level, output);
    match cli.command {
        Command::Offline(args) => commands::offline::run(&args),
        Command::Relocalize(args) => commands::relocalize::run(&args),
        Command::Sessions(args) => commands::sessions::run(&args),
        Command::Run(args) => commands::run::run(&args),
    }
}
