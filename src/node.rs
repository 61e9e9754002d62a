//! The one shell every node runs in, whether started by hand (the `agent`,
//! `leader`, `monitor` and `router` binaries) or by `formation launch` and
//! the lab (`formation node …`): logging, zenoh's threads, the async
//! runtime, and the exit status (0 done, 1 the run failed, 2 bad input,
//! 130 and 143 for a monitor stopped by SIGINT and SIGTERM, its folder
//! holding what it received).

use std::process::ExitCode;
use std::time::Duration;

use clap::Args;
use formation_exit::shutdown::Signal;
use formation_net::session;
use formation_net::{agent, leader, monitor, router};
use formation_recorder::watch::Ending;

use formation_exit::Error;

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
    /// A stand-in robot speaking ROS 2 (as `formation robot`).
    Robot(formation_net::ros2::robot::RobotArgs),
}

/// A log line of zenoh's own (its crates' targets), not the formation's.
fn is_zenoh(target: &str) -> bool {
    target == "zenoh" || target.starts_with("zenoh::") || target.starts_with("zenoh_")
}

/// Hands zenoh's access-control denials to [`formation_net::denials::note`].
struct Denials;

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for Denials {
    fn on_event(&self, event: &tracing::Event<'_>, _: tracing_subscriber::layer::Context<'_, S>) {
        if event.metadata().line().is_some_and(|l| formation_net::denials::ALLOWED_LINES.contains(&l)) {
            return;
        }
        struct Message(String);
        impl tracing::field::Visit for Message {
            fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
                if field.name() == "message" {
                    self.0 = format!("{value:?}");
                }
            }
        }
        let mut m = Message(String::new());
        event.record(&mut m);
        formation_net::denials::note(&m.0);
    }
}

/// Runs a node to its end and says how it ended: errors as one line on
/// stderr, and the exit status.
pub fn run(node: Node) -> ExitCode {
    match node {
        Node::Agent(a) => run_agent(a),
        Node::Leader(a) => run_leader(a),
        Node::Monitor(a) => run_monitor(a),
        Node::Router(r) => run_router(r),
        Node::Robot(r) => run_robot(r),
    }
}

/// `formation bench-floor` (hidden): one of `bench-net --floor`'s
/// plain-zenoh processes with an agent's message pattern, in the node shell.
pub fn run_floor(f: formation_bench::floor::FloorArgs) -> ExitCode {
    let name = format!("floor-{}", f.id);
    shell(&f.node.zenoh.clone(), &name, true, async move {
        formation_bench::floor::node(&f).await.map(|()| ExitCode::SUCCESS)
    })
}

/// `formation robot`: a stand-in robot on ROS 2's wire until the run ends or a signal.
pub fn run_robot(r: formation_net::ros2::robot::RobotArgs) -> ExitCode {
    let name = format!("robot-{}", r.id);
    shell(&r.node.zenoh.clone(), &name, true, async move {
        let stop = formation_exit::shutdown::from_now();
        formation_net::ros2::robot::run(&r, async move {
            stop.await;
        })
        .await
        .map(|()| ExitCode::SUCCESS)
    })
}

/// The `agent` binary. Each node has its own entry, so that a binary links
/// only its node: a headless agent carries no live page, Foxglove server,
/// replay or certificate generator.
pub fn run_agent(a: agent::AgentArgs) -> ExitCode {
    let name = formation_protocol::names::agent_name(a.id.first().copied().unwrap_or(0));
    shell(&a.node.zenoh.clone(), &name, true, async move {
        // The handlers from the process's first moment (a signal before its
        // loop began is a stop, not the default death).
        agent::run(&a, formation_exit::shutdown::from_now()).await.map(stopped_by)
    })
}

/// A node's exit status: 0 for its run done, 128 + the signal's number
/// (130, 143) for one stopped by a signal, as a shell says it.
fn stopped_by(signal: Option<Signal>) -> ExitCode {
    match signal {
        None => ExitCode::SUCCESS,
        Some(s) => ExitCode::from(s.status()),
    }
}

/// `formation leave`: the line that says when the follower left, on stdout.
pub fn run_leave(a: formation_net::leave::LeaveArgs) -> ExitCode {
    shell(&a.node.zenoh.clone(), "leave", true, async move {
        let line = formation_net::leave::run(&a).await?;
        println!("{line}");
        Ok(ExitCode::SUCCESS)
    })
}

/// The `leader` binary.
pub fn run_leader(a: leader::LeaderArgs) -> ExitCode {
    shell(&a.node.zenoh.clone(), formation_protocol::names::LEADER, true, async move {
        leader::run(&a, formation_exit::shutdown::from_now()).await.map(stopped_by)
    })
}

/// The `monitor` binary.
pub fn run_monitor(a: monitor::MonitorArgs) -> ExitCode {
    shell(&a.node.zenoh.clone(), formation_protocol::names::MONITOR, true, async move {
        monitor::run(&a, formation_exit::shutdown::from_now()).await.map(monitor_status)
    })
}

/// The `router` binary. A router keeps zenoh's own threads: it forwards,
/// and a forwarding task may wait for room in a full queue (lock-step
/// traffic is not dropped), which on one thread would hold the thread that
/// empties it.
pub fn run_router(r: router::RouterArgs) -> ExitCode {
    shell(&r.zenoh.clone(), formation_protocol::names::ROUTER, false, async move {
        router::run(&r, formation_exit::shutdown::from_now()).await.map(|()| ExitCode::SUCCESS)
    })
}

/// The shell of every node: zenoh's runtime (`shared_runtime`: on this
/// process's threads), logging, the TLS revocation list, the async
/// runtime, and the end as one line and an exit status.
fn shell<F>(zenoh: &formation_net::session::ZenohArgs, name: &str, shared_runtime: bool, work: F) -> ExitCode
where
    F: std::future::Future<Output = Result<ExitCode, formation_exit::Error>>,
{
    // Before the runtime's threads start.
    if shared_runtime {
        session::default_runtime();
    }
    {
        use tracing_subscriber::layer::SubscriberExt;
        use tracing_subscriber::util::SubscriberInitExt;
        use tracing_subscriber::Layer;
        // Zenoh's own log lines go to the file `formation launch` names
        // (`formation_net::node::ZENOH_LOG_ENV`), not onto the user's terminal; the launch sums
        // them up in one line. A node started by hand keeps them on stderr.
        let zenoh_file = std::env::var_os(formation_net::node::ZENOH_LOG_ENV)
            .and_then(|p| std::fs::OpenOptions::new().create(true).append(true).open(p).ok());
        let to_file = zenoh_file.is_some();
        // One filter per layer (two filters' `and`), not a filter on a
        // filtered layer: with the nested filters the registry built and
        // dropped one of zenoh's trace spans for every message (perf of a
        // lock-step agent: span_data, new_span, try_close, the EnvFilter's
        // `enabled` per event), and the paper's lock-step run went 20-25 %
        // slower (docs/performance.md).
        use tracing_subscriber::filter::FilterExt;
        let not_zenoh = tracing_subscriber::filter::filter_fn(move |m| !(to_file && is_zenoh(m.target())));
        let log = tracing_subscriber::fmt::layer()
            .with_writer(std::io::stderr)
            .with_filter(not_zenoh.and(tracing_subscriber::EnvFilter::from_default_env()));
        let file = zenoh_file.map(|f| {
            tracing_subscriber::fmt::layer().with_ansi(false).with_writer(std::sync::Mutex::new(f)).with_filter(
                tracing_subscriber::filter::filter_fn(|m| is_zenoh(m.target()))
                    .and(tracing_subscriber::EnvFilter::from_default_env()),
            )
        });
        // zenoh's access-control decisions, for the denials it counts.
        let acl = Denials.with_filter(
            tracing_subscriber::filter::Targets::new()
                .with_target(formation_net::denials::ACL_TARGET, tracing::Level::TRACE),
        );
        let _ = tracing_subscriber::registry().with(log).with(file).with(acl).try_init();
    }
    // The authority's revocation list, for the TLS link (before any thread starts).
    if let Some(dir) = &zenoh.tls {
        formation_net::identity::export_crl(dir, name);
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build() {
        Ok(r) => r,
        Err(e) => {
            formation_net::node::say(&format!("error: cannot start the async runtime: {e}"));
            return ExitCode::from(1);
        }
    };
    let result: Result<ExitCode, Error> = runtime.block_on(work).map_err(Error::from);
    // Zenoh's background tasks must not keep the process alive.
    runtime.shutdown_timeout(Duration::from_secs(1));
    match result {
        Ok(code) => code,
        Err(e) => {
            formation_net::node::say(&format!("error: {e}"));
            ExitCode::from(e.status())
        }
    }
}

/// A monitor's exit status: 0 for a run recorded to its end, 3 for one
/// recorded to its end but degraded (network.json's `health`), 130 after
/// SIGINT and 143 after SIGTERM (the shell's convention).
fn monitor_status((ending, verdict): (Ending, Option<formation_recorder::health::Verdict>)) -> ExitCode {
    match ending {
        Ending::Interrupted => stopped_by(Some(Signal::Interrupt)),
        Ending::Terminated => stopped_by(Some(Signal::Terminate)),
        _ if verdict == Some(formation_recorder::health::Verdict::Degraded) => ExitCode::from(formation_exit::DEGRADED),
        _ => ExitCode::SUCCESS,
    }
}
