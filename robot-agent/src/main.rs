//! `evermap-agent`: runs on each robot; also offers offline tools on recordings.

use clap::Parser;

/// evermap robot agent.
#[derive(Parser)]
#[command(version, about)]
struct Cli {}

fn main() {
    Cli::parse();
}
