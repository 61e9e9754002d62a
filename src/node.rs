//! The one shell every node runs in, whether started by hand (the `agent`,
//! `leader`, `monitor` and `router` binaries) or by `formation launch` and
//! the lab (`formation node …`): logging, zenoh's threads, the async
//! runtime, and the exit status (0 done, 1 the run failed, 2 bad input,
//! 130 and 143 for a monitor stopped by SIGINT and SIGTERM, its folder
//! holding what it received).

use std::process::ExitCode;
use std::time::Duration;

use clap::Args;
use formation_net::monitor::Ending;
use formation_net::session;
use formation_net::{agent, leader, monitor, router};

use crate::error::Error;

/// `formation node …`: the node binaries' work inside the `formation`
/// executable, so that `formation launch` always starts nodes built from the
/// same code as itself (`cargo run -- launch` builds only this binary).
#[derive(Args, Debug, Clone)]
pub struct NodeCommand {
    #[command(subcommand)]
    pub node: Node,
}

#[derive(clap::Subcommand, Debug, Clone)]
pub enum Node {
    /// One follower (as the `agent` binary).
    Agent(agent::AgentArgs),
    /// The virtual leader (as the `leader` binary).
    Leader(leader::LeaderArgs),
    /// The monitor (as the `monitor` binary).
    Monitor(monitor::MonitorArgs),
    /// A zenoh router for client mode (as the `router` binary).
    Router(router::RouterArgs),
}

/// Runs a node to its end and says how it ended: errors as one line on
/// stderr, and the exit status.
pub fn run(node: Node) -> ExitCode {
    // Before the runtime's threads start. A router keeps zenoh's own
    // threads: it forwards, and a forwarding task may wait for room in a
    // full queue (lock-step traffic is not dropped), which on one thread
    // would hold the thread that empties it.
    if !matches!(node, Node::Router(_)) {
        session::default_runtime();
    }
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .try_init();
    let (zenoh, name) = match &node {
        Node::Agent(a) => (&a.node.zenoh, formation_net::names::agent_name(a.id.first().copied().unwrap_or(0))),
        Node::Leader(a) => (&a.node.zenoh, formation_net::names::LEADER.to_string()),
        Node::Monitor(a) => (&a.node.zenoh, formation_net::names::MONITOR.to_string()),
        Node::Router(r) => (&r.zenoh, formation_net::names::ROUTER.to_string()),
    };
    formation_net::node::warn_if_unauthenticated(zenoh);
    // The authority's revocation list, for the TLS link (before any thread starts).
    if let Some(dir) = &zenoh.tls {
        formation_net::identity::export_crl(dir, &name);
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            return ExitCode::from(1);
        }
    };
    let result: Result<ExitCode, Error> = runtime.block_on(async {
        match &node {
            Node::Agent(a) => agent::run(a).await.map(|()| ExitCode::SUCCESS).map_err(Error::from),
            Node::Leader(a) => leader::run(a).await.map(|()| ExitCode::SUCCESS).map_err(Error::from),
            Node::Monitor(a) => monitor::run(a).await.map(monitor_status).map_err(Error::from),
            Node::Router(z) => router::run(z).await.map(|()| ExitCode::SUCCESS).map_err(Error::from),
        }
    });
    // Zenoh's background tasks must not keep the process alive.
    runtime.shutdown_timeout(Duration::from_secs(1));
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            e.exit_code()
        }
    }
}

/// A monitor's exit status: 0 for a run recorded to its end, 130 after
/// SIGINT and 143 after SIGTERM (the shell's convention).
fn monitor_status(ending: Ending) -> ExitCode {
    match ending {
        Ending::Interrupted => ExitCode::from(130),
        Ending::Terminated => ExitCode::from(143),
        _ => ExitCode::SUCCESS,
    }
}
