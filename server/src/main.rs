//! `evermap-server`: the fleet map server and its back-end tools. The fleet simulations (demo, load
//! benchmark) are `evermap-demo`, in the `fleet-demo` crate: this binary links no robot code.

mod optimize_command;
mod serve_command;
mod site_command;

use clap::{Parser, Subcommand};
use tracing_subscriber::filter::LevelFilter;

/// evermap map server.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Optimize a g2o/TORO pose graph file and print one JSON line of results.
    Optimize(optimize_command::OptimizeArgs),
    /// Serves site maps to robots over gRPC (with health, reflection and Prometheus metrics).
    Serve(serve_command::ServeArgs),
    /// A stopped instance's sites: list, export to an archive, import one, delete (moving a site
    /// between instances).
    Site(site_command::SiteArgs),
}

/// Runs the command; an error is reported with its causes, each once (`proto::error_report`).
fn main() -> std::process::ExitCode {
    proto::exit_code(run())
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    // `serve` logs to standard output at INFO (DEBUG with `--verbose`) as a service does; the tools
    // print their results there and log nothing unless RUST_LOG asks (then to standard error).
    let (level, output) = match &cli.command {
        Some(Command::Serve(args)) => (args.log_level(), server::LogOutput::Stdout),
        _ => (LevelFilter::OFF, server::LogOutput::Stderr),
    };
    server::init_logging(level, output);
    match cli.command {
        Some(Command::Optimize(args)) => optimize_command::run(&args),
        Some(Command::Serve(args)) => serve_command::run(&args),
        Some(Command::Site(args)) => site_command::run(&args),
        None => Ok(()),
    }
}
