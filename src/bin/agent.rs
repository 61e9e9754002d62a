//! `agent --scenario FILE --id N [--set KEY=VALUE]… [--run NAME] [zenoh options]`:
//! one follower of the formation as its own process (see `formation::net::agent`).

use std::process::ExitCode;

use clap::Parser;
use formation::net::{agent, node};

#[derive(Parser, Debug)]
#[command(about = "One follower of the formation as a zenoh node (multicast scouting off)")]
struct Cli {
    #[command(flatten)]
    args: agent::AgentArgs,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    node::main_with(|| async move { agent::run(&cli.args).await.map(|()| ExitCode::SUCCESS) })
}
