//! `agent --scenario FILE --id N [--set KEY=VALUE]… [--run NAME] [zenoh options]`:
//! one follower of the formation as its own process (`formation_net::agent`).

use clap::Parser;
use formation::node;

#[derive(Parser, Debug)]
#[command(about = "One follower of the formation as a zenoh node (multicast scouting off)")]
struct Cli {
    #[command(flatten)]
    args: formation_net::agent::AgentArgs,
}

fn main() -> std::process::ExitCode {
    node::run_agent(formation::args::parse_or_exit::<Cli>().args)
}
