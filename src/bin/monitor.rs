//! `monitor --scenario FILE [--out DIR] [--set KEY=VALUE]… [--run NAME] [zenoh options]`:
//! records a networked run into a run folder (`formation_net::monitor`).
//! Exit status 130 after Ctrl-C, 143 after SIGTERM (the folder holds what was received).

use clap::Parser;
use formation::node;

#[derive(Parser, Debug)]
#[command(about = "Records a networked formation run: live formation error, run folder, message counts")]
struct Cli {
    #[command(flatten)]
    args: formation_net::monitor::MonitorArgs,
}

fn main() -> std::process::ExitCode {
    node::run_monitor(formation::args::parse_or_exit::<Cli>().args)
}
