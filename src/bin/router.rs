//! A zenoh router for `formation` nodes in client mode.
//!
//! `router [--listen tcp/127.0.0.1:7447] [--config FILE.json5]`: prints one
//! line `router listening on <endpoints>` to stdout once open, then runs
//! until SIGINT/SIGTERM and closes the session. Multicast scouting is off.

use clap::Parser;
use formation::node;

#[derive(Parser, Debug)]
#[command(about = "Zenoh router for formation nodes (loopback by default, no multicast)")]
struct Cli {
    #[command(flatten)]
    router: formation_net::router::RouterArgs,
}

fn main() -> std::process::ExitCode {
    node::run_router(formation::args::parse_or_exit::<Cli>().router)
}
