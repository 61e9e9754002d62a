//! `leader --scenario FILE [--set KEY=VALUE]… [--run NAME] [zenoh options]`:
//! the virtual leader as its own process; it also starts the run (see
//! `formation::net::leader`).

use std::process::ExitCode;

use clap::Parser;
use formation::net::{leader, node};

#[derive(Parser, Debug)]
#[command(about = "The formation's virtual leader as a zenoh node (multicast scouting off)")]
struct Cli {
    #[command(flatten)]
    args: leader::LeaderArgs,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    node::main_with(|| async move { leader::run(&cli.args).await.map(|()| ExitCode::SUCCESS) })
}
