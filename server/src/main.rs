//! `evermap-server`: the fleet map server and its back-end tools.

use clap::Parser;

/// evermap map server.
#[derive(Parser)]
#[command(version, about)]
struct Cli {}

fn main() {
    Cli::parse();
}
