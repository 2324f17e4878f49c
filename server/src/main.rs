//! `evermap-server`: the fleet map server and its back-end tools. The fleet simulations (demo, load
//! benchmark) are `evermap-demo`, in the `fleet-demo` crate: this binary links no robot code.

mod optimize_command;
mod serve_command;
mod site_command;

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
    /// Optimize a g2o/TORO pose graph file and print one JSON line of results.
    Optimize(optimize_command::OptimizeArgs),
    /// Serves site maps to robots over gRPC (with health, reflection and Prometheus metrics).
    Serve(serve_command::ServeArgs),
    /// A stopped instance's sites: list, export to an archive, import one, delete (moving a site
    /// between instances).
    Site(site_command::SiteArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Some(Command::Optimize(args)) => optimize_command::run(&args),
        Some(Command::Serve(args)) => serve_command::run(&args),
        Some(Command::Site(args)) => site_command::run(&args),
        None => Ok(()),
    }
}
