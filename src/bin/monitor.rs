//! `monitor --scenario FILE [--out DIR] [--set KEY=VALUE]… [--run NAME] [zenoh options]`:
//! records a networked run into a run folder (see `formation::net::monitor`).
//! Exit status 130 after Ctrl-C, 143 after SIGTERM (the folder holds what was received).

use std::process::ExitCode;

use clap::Parser;
use formation::net::monitor::{self, Ending};
use formation::net::node;

#[derive(Parser, Debug)]
#[command(about = "Records a networked formation run: live formation error, run folder, message counts")]
struct Cli {
    #[command(flatten)]
    args: monitor::MonitorArgs,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    node::main_with(|| async move {
        monitor::run(&cli.args).await.map(|ending| match ending {
            Ending::Interrupted => ExitCode::from(130),
            Ending::Terminated => ExitCode::from(143),
            _ => ExitCode::SUCCESS,
        })
    })
}
