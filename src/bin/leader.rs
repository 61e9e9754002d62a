//! `leader --scenario FILE [--set KEY=VALUE]… [--run NAME] [zenoh options]`:
//! the virtual leader as its own process; it also starts the run
//! (`formation_net::leader`).

use clap::Parser;
use formation::node;

#[derive(Parser, Debug)]
#[command(about = "The formation's virtual leader as a zenoh node (multicast scouting off)")]
struct Cli {
    #[command(flatten)]
    args: formation_net::leader::LeaderArgs,
}

fn main() -> std::process::ExitCode {
    node::run_leader(formation::args::parse_or_exit::<Cli>().args)
}
