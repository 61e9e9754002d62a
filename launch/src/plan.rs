//! A launch's plan: its ports, who dials whom, and each node's command
//! line, computed before anything starts ([`monitor_and_leader`],
//! [`agents`]). Nothing here starts a process; [`crate::supervisor`] does.

use std::path::Path;
use std::process::{Command, Stdio};

use formation_net::session;
use formation_scenario::Scenario;

use crate::options::{LaunchArgs, LaunchMode, Links, Robots, RunOptions};
use crate::ports::Lease;
use formation_exit::Error;

/// The endpoints of the nodes of one launch, named by their loopback port:
/// what a node listens on and what others dial to reach it. With unix
/// links, the sockets' folder lives (and is removed) with this value.
pub struct Endpoints {
    pub(crate) unix: Option<tempfile::TempDir>,
}

impl Endpoints {
    pub fn new(links: Links) -> Result<Self, Error> {
        let unix = match links {
            Links::Tcp => None,
            Links::Unix => Some({
                sweep_orphaned_sockets(&std::env::temp_dir());
                tempfile::Builder::new()
                    .prefix(&format!("{LINKS_PREFIX}{}-", std::process::id()))
                    .permissions(std::os::unix::fs::PermissionsExt::from_mode(0o700))
                    .tempdir()
                    .map_err(|e| Error::Run(format!("making a folder for the nodes' unix sockets: {e}")))?
            }),
        };
        Ok(Self { unix })
    }

    /// What a node dials to reach the node that listens at `port`.
    pub fn dial(&self, port: u16) -> String {
        match &self.unix {
            Some(dir) => format!("unixsock-stream/{}", dir.path().join(port.to_string()).display()),
            None => ep(port),
        }
    }

    /// What the node at `port` listens on: its TCP port, and its socket.
    pub fn listen(&self, port: u16) -> Vec<String> {
        let mut l = vec![ep(port)];
        if self.unix.is_some() {
            l.push(self.dial(port));
        }
        l
    }
}

/// The start of the name of a launch's sockets folder, followed by the
/// launch's process id.
pub(crate) const LINKS_PREFIX: &str = "formation-links-";

/// Removes the sockets folders in `tmp` of launches that are gone (killed
/// with SIGKILL, which leaves no chance to remove them): ours, named for a
/// process that no longer runs, holding nothing but sockets. Anything else
/// is left alone.
pub(crate) fn sweep_orphaned_sockets(tmp: &Path) {
    use std::os::unix::fs::{FileTypeExt, MetadataExt};
    let Ok(entries) = std::fs::read_dir(tmp) else { return };
    // SAFETY: geteuid has no preconditions and cannot fail.
    let me = unsafe { libc::geteuid() };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(pid) = name.to_str().and_then(|n| n.strip_prefix(LINKS_PREFIX)).and_then(|r| r.split_once('-')) else {
            continue;
        };
        let Ok(pid) = pid.0.parse::<u32>() else { continue };
        let dir = e.path();
        let ours = std::fs::symlink_metadata(&dir).is_ok_and(|m| m.is_dir() && m.uid() == me);
        if !ours || pid == std::process::id() || Path::new(&format!("/proc/{pid}")).exists() {
            continue;
        }
        let Ok(inside) = std::fs::read_dir(&dir) else { continue };
        let inside: Vec<_> = inside.flatten().collect();
        let only_sockets = inside.iter().all(|s| s.file_type().is_ok_and(|t| t.is_socket()));
        // A launch in another pid namespace (a container sharing /tmp)
        // looks gone by its pid; its nodes still listen on their sockets.
        let listened = || inside.iter().any(|s| std::os::unix::net::UnixStream::connect(s.path()).is_ok());
        if only_sockets && !listened() {
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
}

pub(crate) fn ep(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

/// `count` loopback ports: consecutive from `base`, or free ones
/// ([`crate::ports::free`]), claimed while the lease lives.
pub(crate) fn ports(base: Option<u16>, count: usize) -> Result<Lease, Error> {
    let Some(b) = base else { return crate::ports::free(count) };
    if b == 0 {
        return Err(Error::Input(
            "--base-port 0: give a port of 1 or more (or leave --base-port out for free ports)".into(),
        ));
    }
    // The ports are b, b + 1, …, b + count − 1.
    let last = u32::from(b) + count.saturating_sub(1) as u32;
    if last > u32::from(u16::MAX) {
        return Err(Error::Input(format!("--base-port {b}: not enough ports above it for {count} nodes")));
    }
    Ok(Lease::given((0..count as u16).map(|i| b + i).collect()))
}

/// The links' lease of a launch whose nodes all run on this host (none
/// with `--router`, which may be elsewhere: its links keep the 1 s that
/// notices a cut link), nor when `--zenoh-config` set one (the file's is
/// kept). See [`session::LAUNCH_LEASE_MS`].
pub(crate) fn one_host_lease(a: &LaunchArgs, zfile: Option<&session::SharedFile>) -> Option<u64> {
    let own = zfile.and_then(|f| f.lease_ms).is_some();
    (a.router.is_none() && !own).then_some(session::LAUNCH_LEASE_MS)
}

/// `--config FILE` of `--zenoh-config`, for every node and the router.
pub(crate) fn zenoh_file_arg(c: &mut Command, zfile: Option<&session::SharedFile>) {
    if let Some(f) = zfile {
        c.arg("--config").arg(&f.path);
    }
}

pub(crate) fn node_command(exe: &Path, node: &str, a: &LaunchArgs, run: &str) -> Command {
    let mut c = Command::new(exe);
    node_args(&mut c, node, &a.opts, run);
    c
}

/// `node <node> --scenario … --run … --set …` of a run, stdin closed.
pub(crate) fn node_args(c: &mut Command, node: &str, opts: &RunOptions, run: &str) {
    c.args(["node", node]).arg("--run").arg(run);
    scenario_args(c, opts);
    tls_arg(c, opts);
    quorum_args(c, node, opts);
    c.stdin(Stdio::null());
}

/// A quorum start: every node waits as long, and the leader decides.
fn quorum_args(c: &mut Command, node: &str, opts: &RunOptions) {
    let Some(n) = opts.quorum else { return };
    if matches!(node, "leader" | "agent" | "monitor") {
        c.arg("--quorum-wait").arg(opts.quorum_wait().to_string());
    }
    if node == "leader" {
        c.arg("--quorum").arg(n.to_string());
        if opts.even_if_cut_off {
            c.arg("--even-if-cut-off");
        }
    }
}

/// `--scenario FILE --set …` of a run.
pub(crate) fn scenario_args(c: &mut Command, opts: &RunOptions) {
    c.arg("--scenario").arg(&opts.scenario.scenario);
    for o in &opts.overrides() {
        c.arg("--set").arg(o);
    }
    // Every node (and the router) knows the run's rate: the limits on what
    // it receives are set from it (formation_net::limits).
    if let Some(x) = opts.time_scale {
        c.arg("--set").arg(format!("network.time_scale={x:?}"));
    }
}

/// `--tls DIR` (absolute) when the run has it.
pub(crate) fn tls_arg(c: &mut Command, opts: &RunOptions) {
    // The run said once whether its traffic is authenticated.
    c.env(formation_net::node::LAUNCHED_ENV, "1");
    if let Some(dir) = &opts.tls {
        c.arg("--tls").arg(std::path::absolute(dir).unwrap_or_else(|_| dir.clone()));
    }
}

/// How every node of a launch reaches the others: its mode, its links'
/// endpoints and the zenoh settings it shares.
pub(crate) struct Wiring<'a> {
    pub(crate) mode: LaunchMode,
    pub(crate) links: Links,
    pub(crate) eps: Endpoints,
    pub(crate) router_ep: String,
    pub(crate) lease: Option<u64>,
    pub(crate) zfile: Option<&'a session::SharedFile>,
}

impl Wiring<'_> {
    /// A node's zenoh arguments: a client of the router, or a peer that
    /// listens on `listen` and dials `connect`.
    pub(crate) fn apply(&self, c: &mut Command, listen: Option<u16>, connect: &[u16]) {
        if let Some(ms) = self.lease {
            c.arg("--lease-ms").arg(ms.to_string());
        }
        zenoh_file_arg(c, self.zfile);
        if self.mode == LaunchMode::Client {
            c.args(["--mode", "client", "--connect", &self.router_ep]);
            return;
        }
        c.args(["--mode", "peer"]);
        for l in listen.map(|l| self.eps.listen(l)).unwrap_or_default() {
            c.arg("--listen").arg(l);
        }
        // The links below are every pair that talks (agent–neighbour,
        // agent–leader, node–monitor): no full mesh by gossip.
        c.arg("--no-gossip");
        for &q in connect {
            c.arg("--connect").arg(self.eps.dial(q));
        }
    }
}

/// The router child's command line (client mode).
pub(crate) fn router(
    exe: &Path,
    listen: &[String],
    opts: &RunOptions,
    timing: formation_scenario::Timing,
    lease: Option<u64>,
    zfile: Option<&session::SharedFile>,
) -> Command {
    let mut c = Command::new(exe);
    c.args(["node", "router"]);
    zenoh_file_arg(&mut c, zfile);
    for l in listen {
        c.arg("--listen").arg(l);
    }
    if let Some(ms) = lease {
        c.arg("--lease-ms").arg(ms.to_string());
    }
    scenario_args(&mut c, opts);
    tls_arg(&mut c, opts);
    session::router_runtime(&mut c, timing);
    c
}

/// One process of a launch, planned and not yet started: its name (as the
/// supervisor and the logs call it) and its command line.
pub struct Planned {
    pub name: String,
    pub command: Command,
}

/// The monitor and the leader, listening on their ports (peer mode).
pub(crate) fn monitor_and_leader(
    a: &LaunchArgs,
    run: &str,
    out: &Path,
    exe: &Path,
    wiring: &Wiring,
    (mon_port, lead_port): (u16, u16),
) -> [Planned; 2] {
    let mut monitor = node_command(exe, "monitor", a, run);
    monitor.arg("--out").arg(out).stdout(Stdio::null());
    for (on, flag) in [(a.opts.quiet, "--quiet"), (a.opts.mcap, "--mcap"), (a.opts.rosbag2, "--rosbag2")] {
        if on {
            monitor.arg(flag);
        }
    }
    monitor.args(a.opts.web.to_args());
    wiring.apply(&mut monitor, Some(mon_port), &[]);
    let mut leader = leader_command(exe, a, run);
    wiring.apply(&mut leader, Some(lead_port), &[mon_port]);
    [Planned { name: "monitor".into(), command: monitor }, Planned { name: "leader".into(), command: leader }]
}

/// `node leader` of a run, with the launch's time scale (the leader's, and its standby's).
fn leader_command(exe: &Path, a: &LaunchArgs, run: &str) -> Command {
    let mut c = node_command(exe, "leader", a, run);
    if let Some(x) = a.opts.time_scale {
        c.arg("--time-scale").arg(x.to_string());
    }
    c
}

/// `--standby`: a second leader process, a client of the router, that
/// takes the run over when the leader is gone.
pub(crate) fn standby(a: &LaunchArgs, run: &str, exe: &Path, wiring: &Wiring) -> Planned {
    let mut c = leader_command(exe, a, run);
    c.arg("--standby").arg("--take-over-after").arg(a.take_over_after.to_string());
    wiring.apply(&mut c, None, &[]);
    Planned { name: crate::supervisor::STANDBY.into(), command: c }
}

/// The port agent process `g` listens on (peer mode; None as a client).
fn agent_listen(wiring: &Wiring, p: &[u16], g: usize) -> Option<u16> {
    (wiring.mode == LaunchMode::Peer).then(|| p.get(2 + g).copied().unwrap_or(0))
}

/// The followers' ids of each agent process, as their command lines give them.
fn group_ids(scenario: &Scenario, members: &std::ops::Range<usize>) -> Vec<String> {
    members.clone().map(|i| scenario.graph.id(i).to_string()).collect()
}

/// One agent process per group of followers (peer mode: each dials every
/// earlier process that holds a neighbour, or with the safety filter any
/// follower), and a stand-in robot per follower where the scenario has them.
#[allow(clippy::too_many_arguments)]
pub(crate) fn agents(
    a: &LaunchArgs,
    scenario: &Scenario,
    run: &str,
    exe: &Path,
    wiring: &Wiring,
    groups: &[std::ops::Range<usize>],
    p: &[u16],
    robots: Robots,
) -> Vec<Planned> {
    let peer = wiring.mode == LaunchMode::Peer;
    let (mon_port, lead_port) = if peer { (p[0], p[1]) } else { (0, 0) };
    let mut planned = Vec::new();
    // Agents left out (--absent): nobody dials them.
    let absent = |h: usize| groups[h].clone().all(|i| a.opts.absent.contains(&scenario.graph.id(i)));
    for (g, members) in groups.iter().enumerate() {
        if absent(g) {
            continue;
        }
        let ids = group_ids(scenario, members);
        let mut c = node_command(exe, "agent", a, run);
        c.arg("--id").arg(ids.join(","));
        if a.opts.quiet {
            c.arg("--quiet");
        }
        for l in members.clone().flat_map(|i| a.opts.leaves_of(scenario.graph.id(i))) {
            c.arg("--leave").arg(l);
        }
        if a.opts.even_if_cut_off {
            c.arg("--even-if-cut-off");
        }
        let mut connect = vec![mon_port, lead_port];
        if peer {
            let mut dial: Vec<usize> = members
                .clone()
                .flat_map(|i| scenario.peers_of(i))
                .map(|j| j / a.group)
                .filter(|&h| h < g && !absent(h))
                .collect();
            dial.sort_unstable();
            dial.dedup();
            connect.extend(dial.into_iter().map(|h| p[2 + h]));
        }
        let listen = agent_listen(wiring, p, g);
        wiring.apply(&mut c, listen, &connect);
        let name = if ids.len() == 1 { format!("agent {}", ids[0]) } else { format!("agents {}", ids.join(",")) };
        planned.push(Planned { name, command: c });
        // A robot talks to its own agent only (peer), or through the router.
        if robots == Robots::StandIn {
            for id in &ids {
                let mut c = node_command(exe, "robot", a, run);
                c.arg("--id").arg(id);
                wiring.apply(&mut c, None, &listen.into_iter().collect::<Vec<_>>());
                planned.push(Planned { name: format!("robot {id}"), command: c });
            }
        }
    }
    planned
}

/// With robots of the user's own (`ros2.robots = "external"`): what each
/// follower's robot must publish and take, and where.
pub(crate) fn external_robot_lines(
    a: &LaunchArgs,
    scenario: &Scenario,
    wiring: &Wiring,
    groups: &[std::ops::Range<usize>],
    p: &[u16],
) -> Vec<String> {
    let mut lines = Vec::new();
    for (g, members) in groups.iter().enumerate() {
        // A TCP endpoint: the unix sockets' folder is the launch's own.
        let at = match agent_listen(wiring, p, g) {
            Some(port) => ep(port),
            None => a.router.clone().unwrap_or_else(|| ep(p[0])),
        };
        let domain = scenario.ros2.map_or(0, |r| r.domain_id);
        for id in group_ids(scenario, members) {
            lines.push(format!(
                "waiting for robot {id}: publish /follower_{id}/odom (nav_msgs/msg/Odometry), take \
                 /follower_{id}/cmd_vel (geometry_msgs/msg/Twist), ROS domain {domain}, zenoh at {at}"
            ));
        }
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        l: LaunchArgs,
    }

    /// The words after each `--connect` of a command line.
    fn dials(c: &Command) -> Vec<String> {
        let args: Vec<String> = c.get_args().map(|a| a.to_string_lossy().into_owned()).collect();
        args.windows(2).filter(|w| w[0] == "--connect").map(|w| w[1].clone()).collect()
    }

    /// The plan of a peer-mode launch of the paper's formation, read from
    /// its command lines without starting anything: the monitor dials no
    /// one, the leader the monitor, and each agent the monitor, the leader
    /// and the earlier agents that hold a neighbour of its follower, each
    /// pair of neighbours linked once.
    #[test]
    fn who_dials_whom_is_the_graph_once() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/paper.toml");
        let a = Cli::try_parse_from(["launch", path, "--links", "tcp", "--base-port", "41000"]).expect("parses").l;
        let s = a.opts.scenario.load().expect("scenario");
        let n = s.followers.len();
        let p = ports(a.base_port, n + 2).expect("ports").ports;
        let wiring = Wiring {
            mode: LaunchMode::Peer,
            links: Links::Tcp,
            eps: Endpoints::new(Links::Tcp).expect("endpoints"),
            router_ep: String::new(),
            lease: None,
            zfile: None,
        };
        let exe = Path::new("/bin/formation");
        let [monitor, leader] = monitor_and_leader(&a, "r", Path::new("/tmp/out"), exe, &wiring, (p[0], p[1]));
        assert_eq!((monitor.name.as_str(), dials(&monitor.command)), ("monitor", vec![]));
        assert_eq!((leader.name.as_str(), dials(&leader.command)), ("leader", vec![ep(p[0])]));
        let groups: Vec<std::ops::Range<usize>> = (0..n).map(|i| i..i + 1).collect();
        let agents = agents(&a, &s, "r", exe, &wiring, &groups, &p, Robots::Simulated);
        assert_eq!(agents.len(), n, "one process per follower");
        let mut links = 0;
        for (i, agent) in agents.iter().enumerate() {
            let mut want = vec![ep(p[0]), ep(p[1])];
            want.extend(s.graph.neighbours(i).iter().filter(|&&j| j < i).map(|&j| ep(p[2 + j])));
            assert_eq!(dials(&agent.command), want, "{}", agent.name);
            links += want.len() - 2;
        }
        assert_eq!(links, s.graph.edge_count(), "agent-to-agent links against the graph's edges");
        // A quorum start without follower 3 (index 2): no agent 3, nobody
        // dials its port, every node waits as long, the leader decides.
        let q = Cli::try_parse_from([
            "launch",
            path,
            "--links",
            "tcp",
            "--base-port",
            "41000",
            "--quorum",
            "3",
            "--absent",
            "3",
        ])
        .expect("parses")
        .l;
        let without_3 = super::agents(&q, &s, "r", exe, &wiring, &groups, &p, Robots::Simulated);
        let names: Vec<&str> = without_3.iter().map(|a| a.name.as_str()).collect();
        assert_eq!(names, ["agent 1", "agent 2", "agent 4"]);
        assert!(without_3.iter().all(|a| !dials(&a.command).contains(&ep(p[2 + 2]))), "agent 3's port dialled");
        let args = |c: &Command| c.get_args().map(|a| a.to_string_lossy().into_owned()).collect::<Vec<_>>();
        let [monitor, leader] = monitor_and_leader(&q, "r", Path::new("/tmp/out"), exe, &wiring, (p[0], p[1]));
        for c in [&monitor.command, &leader.command, &without_3[0].command] {
            assert!(args(c).windows(2).any(|w| w == ["--quorum-wait", "10"]), "{:?}", args(c));
        }
        assert!(args(&leader.command).windows(2).any(|w| w == ["--quorum", "3"]), "{:?}", args(&leader.command));
        assert!(!args(&monitor.command).contains(&"--quorum".to_string()), "only the leader decides");
    }
}
