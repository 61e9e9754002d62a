//! `formation launch`: the whole formation as separate OS processes on
//! this machine — the leader, one agent per follower and the monitor (and a
//! zenoh router in client mode) — talking over zenoh on this machine.
//!
//! Links ([`Links`]): by default the nodes dial each other over unix
//! sockets in a private folder; each also listens on its loopback TCP port,
//! for anything else that joins (a ROS 2 tool, a node started by hand).
//! `--links tcp` (and always with --tls or --router): loopback TCP only.
//!
//! Peer mode (default): every node listens on its own loopback port; the
//! leader connects to the monitor, each agent to the monitor, the leader and
//! the earlier processes that hold its neighbours (gossip off: these links
//! are every pair that talks). Client mode: every node connects to a
//! `router` child.
//!
//! Lease: every node of one host tells the others to wait 10 s for it
//! before they call a link dead (`--lease-ms`, zenoh's own default; a node
//! run by hand waits 1 s). A dead process's links close at once anyway;
//! the 1 s lease only cost a loaded host its links.
//!
//! `--zenoh-config FILE`: every node and the router get `--config FILE`
//! (checked once first, [`session::SharedFile`]); the launch still gives
//! each its mode and links, and its lease unless the file set one.
//!
//! No process is left behind: on success, when any child fails (the monitor
//! is told to write what it has, the rest are killed), on Ctrl-C or SIGTERM
//! (forwarded; the monitor flushes its run folder), and when this process
//! unwinds (a guard kills every child still running).
//!
//! The nodes are this executable's hidden `formation node agent|leader|
//! monitor|router` commands (the same code as the `agent`, `leader`,
//! `monitor` and `router` binaries), so they always match the launcher.

use std::path::Path;
use std::time::Duration;

use formation_scenario::Scenario;

use formation_net::session;
use formation_record::Summary;

use crate::options::{LaunchArgs, LaunchMode, Robots};
use crate::plan::{self, ep, one_host_lease, ports, Endpoints, Wiring};
use crate::supervisor::{spawn, start_router_with, supervise, Children};
use crate::zenoh_log;
use formation_exit::Error;

/// Where a ROS 2 node (rmw_zenoh's nodes are clients of a router) sees
/// the run's topics: the launch's own router, or the monitor (router-less
/// peers: every node links to the monitor, which passes what they publish
/// on to a client that asks). With `--router`, that router (the user's,
/// named in the launch line): nothing to add.
fn ros2_endpoint_line(scenario: &Scenario, mode: LaunchMode, own_router: bool, port: u16) -> Option<String> {
    let r = scenario.ros2?;
    let at = match (mode, own_router) {
        (LaunchMode::Client, true) => "this launch's router",
        (LaunchMode::Client, false) => return None,
        (LaunchMode::Peer, _) => "the monitor, which every node links to",
    };
    Some(format!(
        "ROS 2 (domain {}): connect ROS 2 nodes to {} ({at}), e.g. \
         ZENOH_CONFIG_OVERRIDE='mode=\"client\";connect/endpoints=[\"{}\"]'",
        r.domain_id,
        ep(port),
        ep(port)
    ))
}

/// `formation launch`.
pub fn run(a: &LaunchArgs) -> Result<(), Error> {
    if a.group == 0 {
        return Err(Error::Input("--group 0: give 1 or more followers per agent process".into()));
    }
    if a.group > 1 && a.opts.tls.is_some() {
        return Err(Error::Input(
            "--group with --tls: each follower has its own certificate and access rights, so each needs a process \
             of its own (leave --group out)"
                .into(),
        ));
    }
    a.links()?;
    a.check_standby()?;
    let zfile = match &a.zenoh_config {
        Some(path) => Some(session::SharedFile::check(path).map_err(|e| Error::Input(format!("--zenoh-config: {e}")))?),
        None => None,
    };
    if let Some(r) = &a.router {
        let z = session::ZenohArgs {
            mode: Some(session::ZenohMode::Client),
            connect: vec![r.clone()],
            ..Default::default()
        };
        z.to_config().map_err(|e| Error::Input(format!("--router {r}: {e}")))?;
        if a.opts.tls.is_some() {
            return Err(Error::Input(
                "--router with --tls: a router this launch does not start does not hold the run's certificates".into(),
            ));
        }
    }
    let (scenario, run, out) = a.opts.resolve()?;
    a.opts.warnings(&scenario, &out, &[], &[])?;
    if !a.opts.absent.is_empty() && a.group > 1 {
        return Err(Error::Input("--absent leaves out one follower's agent: it needs --group 1".into()));
    }
    let exe = std::env::current_exe().map_err(|e| Error::Run(format!("locating this executable: {e}")))?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(|e| Error::Run(format!("starting the async runtime: {e}")))?;
    let mut children = Children::new();
    let realtime = scenario.timing == formation_scenario::Timing::Realtime;
    children.let_agents_die(match (realtime, scenario.network.gone_after_s) {
        (true, Some(_)) => Some("the monitor takes it for gone after network.gone_after"),
        (true, None) => None,
        (false, _) => Some("the others agree on its last step, and the monitor names it"),
    });
    let logs = zenoh_log::start(&out)?;
    let result = runtime.block_on(launch(a, zfile.as_ref(), &scenario, &run, &out, &exe, &mut children));
    drop(children);
    zenoh_log::finish_and_say(logs, &out, a.opts.quiet);
    let summary = result?;
    let health = read_health(&out);
    if !a.opts.quiet {
        print!("{}", summary.table());
        if let Some((line, _)) = &health {
            println!("{line}");
        }
        if let Some(why) = a.opts.rt_priority.and_then(|_| rt_throttling_note(&out, &read_rt_limit())) {
            println!("{why}");
        }
        println!("wrote {}", out.display());
    }
    degraded_error(health, &out)
}

/// The kernel's limit on real-time processes: (runtime, period) in µs from
/// /proc/sys/kernel/sched_rt_{runtime,period}_us; None where unlimited
/// (runtime −1) or unreadable.
pub(crate) fn read_rt_limit() -> Option<(i64, i64)> {
    let read = |f: &str| std::fs::read_to_string(format!("/proc/sys/kernel/{f}")).ok()?.trim().parse::<i64>().ok();
    let (runtime, period) = (read("sched_rt_runtime_us")?, read("sched_rt_period_us")?);
    (runtime >= 0 && runtime < period).then_some((runtime, period))
}

/// Under `--rt-priority`, a run whose health names stalls of every node at
/// once, with the kernel throttling real-time processes: what that is and
/// what helps (issue 47: the 50-agent ring stalled 60 ms at t = 6.47 s on a
/// quiet CI machine; 100 agents here stalled at t = 5.58 and 6.58 s, the
/// second both CPUs were throttled, one second apart).
pub(crate) fn rt_throttling_note(out: &Path, limit: &Option<(i64, i64)>) -> Option<String> {
    let (runtime, period) = (*limit)?;
    let text = std::fs::read_to_string(out.join("network.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    let stalls = v["health"]["stalls"].as_array()?;
    if stalls.is_empty() {
        return None;
    }
    Some(format!(
        "why the run stalled: every node ran under real-time scheduling (--rt-priority), and this kernel stops every \
         real-time process on a CPU for the rest of a {:.0} ms period once they used {:.0} ms of it \
         (kernel.sched_rt_runtime_us = {runtime}, sched_rt_period_us = {period}; dmesg says 'RT throttling \
         activated' once a boot): the nodes needed more than {:.0} % of a CPU. Fewer processes (--group N), or no \
         --rt-priority, avoid it; `sysctl -w kernel.sched_rt_runtime_us=-1` lifts the limit (then a runaway node \
         can hold a CPU). docs/why-did-my-run-differ.md, \"Every node at once: a stall\"",
        period as f64 / 1e3,
        runtime as f64 / 1e3,
        100.0 * runtime as f64 / period as f64
    ))
}

/// network.json's health: its line for the terminal, and whether degraded.
pub(crate) fn read_health(out: &Path) -> Option<(String, bool)> {
    let text = std::fs::read_to_string(out.join("network.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    let h = &v["health"];
    let verdict = h["verdict"].as_str()?;
    let reasons: Vec<String> = h["degraded"]
        .as_array()
        .into_iter()
        .flatten()
        .chain(h["disturbed"].as_array().into_iter().flatten())
        .filter_map(|r| r.as_str().map(str::to_string))
        .collect();
    let line = match (verdict, reasons.is_empty()) {
        (_, true) => format!("health: {verdict}"),
        _ => format!("health: {verdict}: {}", reasons.join("; ")),
    };
    Some((line, verdict == "degraded"))
}

/// A degraded run's error (exit status 3), naming why; Ok otherwise.
pub(crate) fn degraded_error(health: Option<(String, bool)>, out: &Path) -> Result<(), Error> {
    match health {
        Some((line, true)) => Err(Error::Degraded(format!(
            "the run was recorded to its end but is degraded ({}; {}/network.json has the evidence)",
            line.trim_start_matches("health: degraded: "),
            out.display()
        ))),
        _ => Ok(()),
    }
}

/// What a launch starts, said before it starts it.
#[allow(clippy::too_many_arguments)]
fn announce(
    a: &LaunchArgs,
    scenario: &Scenario,
    run: &str,
    groups: usize,
    own_router: bool,
    robots: Robots,
    wiring: &Wiring,
    router_port: u16,
) {
    let (n, mode) = (scenario.followers.len() - a.opts.absent.len(), wiring.mode);
    let groups = groups - a.opts.absent.len();
    eprintln!(
        "launching {} processes ({} mode, {} links, run {run}): leader, {n} agents{}, monitor{}",
        groups + 2 + usize::from(own_router) + if robots == Robots::StandIn { n } else { 0 },
        if mode == LaunchMode::Peer { "peer" } else { "client" },
        wiring.links.label(),
        if groups < n { format!(" in {groups} processes of up to {}", a.group) } else { String::new() },
        match (own_router, &a.router) {
            (true, _) => ", router".to_string(),
            (false, Some(r)) => format!(", all clients of the router at {r}"),
            (false, None) => String::new(),
        } + if robots == Robots::StandIn { " and a stand-in robot per follower" } else { "" }
            + &absent_words(&a.opts.absent),
    );
    if let Some(line) = ros2_endpoint_line(scenario, mode, own_router, router_port) {
        eprintln!("{line}");
    }
    if let Some(hint) = formation_net::node::realtime_hint(scenario) {
        eprintln!("{hint}");
    }
    if let Some(w) = scenario.estimator_stability_warning() {
        eprintln!("{w}");
    }
}

async fn launch(
    a: &LaunchArgs,
    zfile: Option<&session::SharedFile>,
    scenario: &Scenario,
    run: &str,
    out: &Path,
    exe: &Path,
    children: &mut Children,
) -> Result<Summary, Error> {
    // Signals first: from here on Ctrl-C must reach the children's cleanup.
    let shutdown = formation_exit::shutdown::from_now();
    let n = scenario.followers.len();
    let robots = match scenario.ros2.map(|r| r.robots) {
        Some(formation_scenario::RobotSource::StandIn) => Robots::StandIn,
        Some(formation_scenario::RobotSource::External) => Robots::External,
        _ => Robots::Simulated,
    };
    // Agent processes: followers by index, `group` consecutive ones each.
    let groups: Vec<std::ops::Range<usize>> = (0..n).step_by(a.group).map(|i| i..(i + a.group).min(n)).collect();
    // Ports: monitor, leader, agent processes (peer); or the router (client).
    // --router: every node a client of a router this launch does not own.
    let mode = if a.router.is_some() { LaunchMode::Client } else { a.mode };
    let own_router = mode == LaunchMode::Client && a.router.is_none();
    let count = if mode == LaunchMode::Peer { groups.len() + 2 } else { 1 };
    // Claimed until the run ends: no other launch takes them meanwhile.
    let lease = ports(a.base_port, count)?;
    let p = &lease.ports;
    let links = a.links()?;
    let eps = Endpoints::new(links)?;
    let router_ep = a.router.clone().unwrap_or_else(|| eps.dial(p[0]));
    let wiring = Wiring { mode, links, eps, router_ep, lease: one_host_lease(a, zfile), zfile };
    if !a.opts.quiet {
        announce(a, scenario, run, groups.len(), own_router, robots, &wiring, p[0]);
    }
    if !a.opts.quiet && robots == Robots::External {
        for line in plan::external_robot_lines(a, scenario, &wiring, &groups, p) {
            eprintln!("{line}");
        }
    }
    if own_router {
        let router = plan::router(exe, &wiring.eps.listen(p[0]), &a.opts, scenario.timing, wiring.lease, zfile);
        start_router_with(children, router)?;
    }
    let node_ports = if mode == LaunchMode::Peer { (p[0], p[1]) } else { (0, 0) };
    let monitor_and_leader = plan::monitor_and_leader(a, run, out, exe, &wiring, node_ports);
    let standby = a.standby.then(|| plan::standby(a, run, exe, &wiring));
    let agents = plan::agents(a, scenario, run, exe, &wiring, &groups, p, robots);
    for node in monitor_and_leader.into_iter().chain(standby).chain(agents) {
        spawn(children, &node.name, node.command)?;
    }
    let ended = supervise(children, out, Duration::from_millis(50), shutdown, |_| Ok(())).await;
    drop(lease);
    ended
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::options::Links;
    use crate::plan::{sweep_orphaned_sockets, LINKS_PREFIX};

    /// `launch scenarios/paper.toml` with `extra`, parsed.
    fn launch_args(extra: &[&str]) -> LaunchArgs {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            l: LaunchArgs,
        }
        let mut args = vec!["launch", concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/paper.toml")];
        args.extend_from_slice(extra);
        Cli::try_parse_from(args).expect("parses").l
    }

    /// A run whose health names a stall, under the kernel's real-time
    /// throttle, says why; without a stall, or without the throttle, nothing.
    #[test]
    fn a_stall_under_the_real_time_throttle_is_explained() {
        let tmp = tempfile::tempdir().expect("tmp");
        let write = |stalls: &str| {
            std::fs::write(tmp.path().join("network.json"), format!("{{\"health\": {{\"stalls\": {stalls}}}}}"))
                .expect("write")
        };
        write(r#"[{"from_k": 647, "to_k": 653}]"#);
        let limit = Some((950_000, 1_000_000));
        let said = rt_throttling_note(tmp.path(), &limit).expect("a note");
        for words in ["kernel.sched_rt_runtime_us = 950000", "950 ms", "1000 ms", "95 % of a CPU", "--group N"] {
            assert!(said.contains(words), "'{words}' not in: {said}");
        }
        assert_eq!(rt_throttling_note(tmp.path(), &None), None, "no throttle (runtime -1): nothing to explain");
        write("[]");
        assert_eq!(rt_throttling_note(tmp.path(), &limit), None, "no stall: nothing said");
    }

    /// A killed launch's sockets folder goes at the next launch; a live
    /// launch's, a folder holding more than sockets, and any other name stay.
    #[test]
    fn only_the_sockets_folders_of_gone_launches_are_swept() {
        let tmp = tempfile::tempdir().expect("tmp");
        let gone = 3_999_999_999u32; // above any pid_max
        let make = |name: &str, socket: bool, file: bool| {
            let d = tmp.path().join(name);
            std::fs::create_dir(&d).expect("dir");
            if socket {
                std::os::unix::net::UnixListener::bind(d.join("24001")).expect("socket");
            }
            if file {
                std::fs::write(d.join("notes.txt"), "mine").expect("file");
            }
            d
        };
        let swept = make(&format!("{LINKS_PREFIX}{gone}-aB3x"), true, false);
        // Named for a pid that is gone here, but listened on (another pid namespace).
        let listening = tmp.path().join(format!("{LINKS_PREFIX}{gone}-Lstn"));
        std::fs::create_dir(&listening).expect("dir");
        let _held = std::os::unix::net::UnixListener::bind(listening.join("24002")).expect("socket");
        let empty = make(&format!("{LINKS_PREFIX}{gone}-Qz9k"), false, false);
        let live = make(&format!("{LINKS_PREFIX}{}-Zz1q", std::process::id()), true, false);
        let mixed = make(&format!("{LINKS_PREFIX}{gone}-c4Dd"), true, true);
        let unnamed = make(&format!("{LINKS_PREFIX}aB3xyz"), true, false);
        let other = make("formation-linksX-1-a", true, false);
        sweep_orphaned_sockets(tmp.path());
        for (d, kept) in [
            (&swept, false),
            (&empty, false),
            (&live, true),
            (&mixed, true),
            (&unnamed, true),
            (&other, true),
            (&listening, true),
        ] {
            assert_eq!(d.exists(), kept, "{}: expected {}", d.display(), if kept { "kept" } else { "swept" });
        }
    }

    #[test]
    fn links_are_unix_unless_tls_or_a_foreign_router() {
        let links = |extra: &[&str]| launch_args(extra).links();
        assert_eq!(links(&[]).ok(), Some(Links::Unix));
        assert_eq!(links(&["--mode", "client"]).ok(), Some(Links::Unix));
        assert_eq!(links(&["--links", "tcp"]).ok(), Some(Links::Tcp));
        assert_eq!(links(&["--tls", "certs"]).ok(), Some(Links::Tcp));
        assert_eq!(links(&["--router", "tcp/127.0.0.1:7447"]).ok(), Some(Links::Tcp));
        for (extra, why) in [
            (["--tls", "certs"], "--links unix cannot go with --tls"),
            (["--router", "tcp/127.0.0.1:7447"], "--links unix cannot go with --router"),
        ] {
            let mut args = vec!["--links", "unix"];
            args.extend_from_slice(&extra);
            match links(&args) {
                Err(Error::Input(m)) => assert!(m.starts_with(why), "{extra:?}: {m}"),
                other => panic!("{extra:?}: {other:?}"),
            }
        }
    }

    /// The nodes of one host get zenoh's 10 s lease; a foreign router's
    /// clients keep the 1 s that notices a cut link.
    #[test]
    fn the_nodes_of_one_host_keep_their_links_ten_seconds() {
        let lease = |extra: &[&str]| one_host_lease(&launch_args(extra), None);
        assert_eq!(lease(&[]), Some(10_000));
        assert_eq!(lease(&["--mode", "client"]), Some(10_000));
        assert_eq!(lease(&["--tls", "certs"]), Some(10_000));
        assert_eq!(lease(&["--router", "tcp/127.0.0.1:7447"]), None);
        // A --zenoh-config file that sets a lease keeps it; one that does not gets 10 s.
        let file = |lease_ms| session::SharedFile { path: "/z.json5".into(), lease_ms };
        assert_eq!(one_host_lease(&launch_args(&[]), Some(&file(Some(3000)))), None);
        assert_eq!(one_host_lease(&launch_args(&[]), Some(&file(None))), Some(10_000));
    }

    /// Unix links: each node listens on its TCP port and on a socket in a
    /// folder only this user can enter, which goes with the value.
    #[test]
    fn unix_endpoints_live_in_a_private_folder_removed_at_the_end() {
        use std::os::unix::fs::PermissionsExt;
        let eps = Endpoints::new(Links::Unix).expect("folder");
        let dir = eps.unix.as_ref().expect("unix").path().to_path_buf();
        assert_eq!(std::fs::metadata(&dir).expect("folder").permissions().mode() & 0o777, 0o700);
        let dial = eps.dial(24001);
        assert_eq!(dial, format!("unixsock-stream/{}/24001", dir.display()));
        assert_eq!(eps.listen(24001), vec!["tcp/127.0.0.1:24001".to_string(), dial.clone()]);
        // Unix sockets' paths are limited to 107 bytes.
        assert!(dial.len() - "unixsock-stream/".len() < 100, "{dial}");
        drop(eps);
        assert!(!dir.exists(), "{} is left behind", dir.display());
        let tcp = Endpoints::new(Links::Tcp).expect("tcp");
        assert_eq!((tcp.dial(7), tcp.listen(7)), ("tcp/127.0.0.1:7".to_string(), vec!["tcp/127.0.0.1:7".to_string()]));
    }

    #[test]
    fn base_port_range_is_checked_up_front() {
        assert!(matches!(ports(Some(0), 3), Err(Error::Input(_))));
        assert_eq!(ports(Some(65533), 3).ok().map(|l| l.ports), Some(vec![65533, 65534, 65535]));
        assert!(matches!(ports(Some(65534), 3), Err(Error::Input(_))));
    }
}

/// "; follower 3 absent (--absent)", or nothing.
fn absent_words(absent: &[u32]) -> String {
    let list = formation_scenario::graph::id_list(absent);
    match absent.len() {
        0 => String::new(),
        1 => format!("; follower {list} absent (--absent)"),
        _ => format!("; followers {list} absent (--absent)"),
    }
}
