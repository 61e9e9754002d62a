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

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use clap::Args;
use formation_topology::Scenario;

use formation_net::session;
use formation_record::Summary;

use crate::args::ScenarioArgs;
use crate::error::CliError;

/// How the launched nodes reach each other.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum LaunchMode {
    /// Router-less peers, each listening on its own loopback port.
    Peer,
    /// Clients of a `router` child.
    Client,
}

/// What the launched nodes' links to each other run over.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Links {
    /// Unix-domain sockets in a private folder (mode 0700, removed at the
    /// end): the same bytes as TCP without the kernel's TCP path, so fewer
    /// late messages when the host is busy. Every node still listens on
    /// its loopback TCP port as well, for anything else that joins.
    #[default]
    Unix,
    /// Loopback TCP, as between hosts (the only choice with --tls or --router).
    Tcp,
}

impl Links {
    /// Its `--links` value.
    pub fn arg(self) -> &'static str {
        match self {
            Links::Unix => "unix",
            Links::Tcp => "tcp",
        }
    }

    /// How a line for people names it.
    pub fn label(self) -> &'static str {
        match self {
            Links::Unix => "unix-socket",
            Links::Tcp => "TCP",
        }
    }
}

/// The endpoints of the nodes of one launch, named by their loopback port:
/// what a node listens on and what others dial to reach it. With unix
/// links, the sockets' folder lives (and is removed) with this value.
pub struct Endpoints {
    unix: Option<tempfile::TempDir>,
}

impl Endpoints {
    pub fn new(links: Links) -> Result<Self, CliError> {
        let unix = match links {
            Links::Tcp => None,
            Links::Unix => Some({
                sweep_orphaned_sockets(&std::env::temp_dir());
                tempfile::Builder::new()
                    .prefix(&format!("{LINKS_PREFIX}{}-", std::process::id()))
                    .permissions(std::os::unix::fs::PermissionsExt::from_mode(0o700))
                    .tempdir()
                    .map_err(|e| CliError::Run(format!("making a folder for the nodes' unix sockets: {e}")))?
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

/// The start of the name of a launch's sockets folder, followed by the
/// launch's process id.
const LINKS_PREFIX: &str = "formation-links-";

/// Removes the sockets folders in `tmp` of launches that are gone (killed
/// with SIGKILL, which leaves no chance to remove them): ours, named for a
/// process that no longer runs, holding nothing but sockets. Anything else
/// is left alone.
fn sweep_orphaned_sockets(tmp: &Path) {
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

/// What every command that runs the whole networked formation takes
/// (`launch`, `lab`).
#[derive(Args, Debug, Clone)]
pub struct RunOptions {
    #[command(flatten)]
    pub scenario: ScenarioArgs,
    /// Run folder the monitor writes [default: runs/<run name>]. Replaced if it is a run folder; any other existing folder is refused.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Run name (key namespace formation/<run>/…) [default: scenario name].
    #[arg(long, value_name = "NAME")]
    pub run: Option<String>,
    /// Real-time mode: run seconds per wall-clock second [default: network.time_scale].
    #[arg(long, value_name = "X")]
    pub time_scale: Option<f64>,
    /// Print nothing but errors (and no live line).
    #[arg(long, short)]
    pub quiet: bool,
    /// Mutual TLS on every link and access control from the topology, with
    /// the certificates in DIR (made by `formation certs SCENARIO --out DIR`).
    #[arg(long, value_name = "DIR")]
    pub tls: Option<PathBuf>,
    /// Also write run.mcap: the CSVs' rows as an MCAP recording that
    /// Foxglove and the mcap tools open (poses as foxglove.PoseInFrame, every
    /// column as numbers, network events). About 1.6 KB per follower row:
    /// combine with --every for long runs.
    #[arg(long)]
    pub mcap: bool,
    /// Also write rosbag2/: the CSVs' rows as a ROS 2 bag (metadata.yaml and
    /// an MCAP file of CDR messages: odom, cmd_vel, leader_estimate, /tf,
    /// /clock) that `ros2 bag` and Foxglove open (docs/ros2.md).
    #[arg(long)]
    pub rosbag2: bool,
    #[command(flatten)]
    pub web: formation_net::monitor::WebArgs,
    /// Real time: run every node under the OS's real-time scheduling
    /// (SCHED_FIFO) at this priority, 1–99, so that other work on the
    /// machine cannot hold a step or a message up (needs root or
    /// CAP_SYS_NICE). On a 2-core machine with 52 processes it took the
    /// 50-agent ring from 2–50 late link-steps in 10 s to 0–4.
    #[arg(long, value_name = "N")]
    pub rt_priority: Option<u8>,
    /// Publish the formation on ROS 2's wire (rmw_zenoh): each follower's
    /// odom, cmd_vel and leader_estimate in /follower_<i>, /leader/odom,
    /// /tf, and /clock in lock-step (the scenario's [ros2] table; docs/ros2.md).
    #[arg(long)]
    pub ros2: bool,
    /// Who moves the robots: simulated (in each agent), stand-in (a
    /// `formation robot` process per follower, driven through ROS 2's
    /// cmd_vel and odom) or external (real robots or Gazebo; the run waits
    /// for their odometry). stand-in and external need robot.model =
    /// "velocity" and turn --ros2 on.
    #[arg(long, value_enum, value_name = "WHO")]
    pub robots: Option<Robots>,
}

/// `--robots`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Robots {
    Simulated,
    StandIn,
    External,
}

impl Robots {
    fn name(self) -> &'static str {
        match self {
            Robots::Simulated => "simulated",
            Robots::StandIn => "stand-in",
            Robots::External => "external",
        }
    }
}

/// Puts this process (and every process it starts from now on) under
/// SCHED_FIFO at `priority`.
fn real_time_scheduling(priority: u8) -> Result<(), CliError> {
    if !(1..=99).contains(&priority) {
        return Err(CliError::Input(format!("--rt-priority must be 1 to 99, not {priority}")));
    }
    let param = libc::sched_param { sched_priority: i32::from(priority) };
    // SAFETY: a plain system call on this process with a valid parameter.
    if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } != 0 {
        let e = std::io::Error::last_os_error();
        return Err(CliError::Input(format!(
            "--rt-priority {priority}: the OS refused real-time scheduling ({e}); run as root, with CAP_SYS_NICE, or \
             with a real-time priority limit (ulimit -r)"
        )));
    }
    Ok(())
}

impl RunOptions {
    /// The scenario, the run name and the run folder, checked (bad input: exit 2).
    pub fn resolve(&self) -> Result<(Scenario, String, PathBuf), CliError> {
        let scenario = Scenario::load(&self.scenario.scenario, &self.overrides())
            .map_err(|e| CliError::Input(self.as_typed(e)))?;

        formation_net::node::networked(&scenario)?;
        let run = self.run.clone().unwrap_or_else(|| scenario.name.clone());
        formation_protocol::names::validate_run_name(&run).map_err(|e| CliError::Input(e.to_string()))?;
        if let Some(x) = self.time_scale {
            if !(x.is_finite() && x > 0.0) {
                return Err(CliError::Input(format!("--time-scale must be a positive number, not {x}")));
            }
        }
        let out = self.out.clone().unwrap_or_else(|| Path::new("runs").join(&run));
        crate::args::check_out_path("--out", &out, crate::args::MAX_OUT_NAME_BYTES)?;
        // The monitor would refuse it too, but only once every node runs.
        formation_record::refuse_replacing_foreign(&out).map_err(|e| CliError::Input(format!("--out: {e}")))?;
        if let Some(p) = self.rt_priority {
            if scenario.timing != formation_topology::Timing::Realtime {
                return Err(CliError::Input(format!(
                    "--rt-priority {p}: a lock-step run waits for its inputs and has no period to meet (set timing = \
                     \"realtime\")"
                )));
            }
            real_time_scheduling(p)?;
        }
        if let Some(dir) = &self.tls {
            // Every node's files, checked before any process starts.
            formation_net::identity::check_all(dir, &scenario).map_err(|e| CliError::Input(e.0))?;
        }
        Ok((scenario, run, out))
    }

    /// The scenario's overrides, with what --ros2 and --robots set.
    pub fn overrides(&self) -> Vec<String> {
        let mut o = self.scenario.overrides.clone();
        if self.ros2 {
            o.push("ros2.enabled=true".into());
        }
        if let Some(r) = self.robots {
            o.push(format!("ros2.robots=\"{}\"", r.name()));
        }
        o
    }

    /// A scenario error in the user's words: the `--set` that --ros2 and
    /// --robots stand for named as the flag typed (it quoted
    /// `--set ros2.robots="stand-in"` to a user who typed `--robots stand-in`).
    fn as_typed(&self, e: formation_topology::ScenarioError) -> String {
        let mut text = e.to_string();
        if let Some(r) = self.robots {
            let (set, typed) = (format!("--set ros2.robots=\"{}\"", r.name()), format!("--robots {}", r.name()));
            text = text.replace(&format!("{set}: ros2.robots: `{}`:", r.name()), &format!("{typed}:"));
            text = text.replace(&set, &typed);
        }
        if self.ros2 {
            text = text.replace("--set ros2.enabled=true", "--ros2");
        }
        text
    }

    /// What a run says before it starts, once its input is known to be good:
    /// that its traffic is unauthenticated (without --tls), and the size of
    /// a run that would write more than a few GB; a run larger than its
    /// disk's free space is refused.
    pub fn warnings(&self, scenario: &Scenario, out: &Path) -> Result<(), CliError> {
        let less = if self.mcap { "a shorter duration or no --mcap" } else { "a shorter duration" };
        crate::runsize::check(scenario, 1, true, self.mcap, out, less)?;
        if self.tls.is_none() && !self.quiet {
            eprintln!("{}", formation_net::node::UNAUTHENTICATED);
        }
        Ok(())
    }
}

#[derive(Args, Debug, Clone)]
pub struct LaunchArgs {
    #[command(flatten)]
    pub opts: RunOptions,
    /// peer: router-less mesh; client: every node through a zenoh router child.
    #[arg(long, value_enum, default_value_t = LaunchMode::Peer)]
    pub mode: LaunchMode,
    /// Use consecutive loopback ports from this one [default: free ports].
    #[arg(long, value_name = "PORT")]
    pub base_port: Option<u16>,
    /// Followers per agent process (consecutive ids share one zenoh session,
    /// and what they say to each other stays in the process). 1 (the
    /// default) is one process per follower, as on separate machines; more
    /// fits large formations on few cores. Not with --tls.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub group: usize,
    /// Join this zenoh router (e.g. rmw_zenohd's, tcp/127.0.0.1:7447)
    /// instead of starting one: every node is its client, as ROS 2 nodes
    /// on rmw_zenoh are.
    #[arg(long, value_name = "ENDPOINT")]
    pub router: Option<String>,
    /// What the nodes' links to each other run over [default: unix; tcp
    /// with --tls or --router]. On a busy host unix sockets leave fewer
    /// messages late than loopback TCP (docs/performance.md); every node
    /// listens on its TCP port either way.
    #[arg(long, value_enum)]
    pub links: Option<Links>,
    /// A zenoh configuration file (json5, zenoh's format) for every node
    /// this launch starts, the router included: buffers, batching, access
    /// control, … It is checked once before anything starts, with a
    /// node's rules for --config (multicast stays off, QoS must stay on),
    /// and may not set id, mode, listen or connect: the launch gives each
    /// node its own. A lease it sets replaces the launch's 10 s.
    #[arg(long, value_name = "FILE.json5")]
    pub zenoh_config: Option<PathBuf>,
}

impl LaunchArgs {
    /// The links this launch uses (see [`LaunchArgs::links`]).
    pub fn links(&self) -> Result<Links, CliError> {
        let tcp_only = match (&self.opts.tls, &self.router) {
            (Some(_), _) => Some("--tls (TLS runs over TCP)"),
            (None, Some(_)) => Some("--router (every node dials that router)"),
            (None, None) => None,
        };
        match (self.links, tcp_only) {
            (Some(Links::Unix), Some(why)) => Err(CliError::Input(format!("--links unix cannot go with {why}"))),
            (Some(l), _) => Ok(l),
            (None, Some(_)) => Ok(Links::Tcp),
            (None, None) => Ok(Links::default()),
        }
    }
}

/// The child processes of a launch; every one still running is killed on drop.
pub struct Children {
    list: Vec<(String, Child)>,
}

impl Children {
    pub(crate) fn new() -> Self {
        Self { list: Vec::new() }
    }

    pub(crate) fn push(&mut self, name: String, child: Child) {
        self.list.push((name, child));
    }

    /// Asks every running child to stop (SIGTERM).
    fn terminate(&mut self, only: impl Fn(&str) -> bool) {
        for (name, child) in &mut self.list {
            if only(name) && matches!(child.try_wait(), Ok(None)) {
                let _ = Command::new("kill").args(["-TERM", &child.id().to_string()]).stderr(Stdio::null()).status();
            }
        }
    }

    /// Waits up to `limit` for the named child to exit.
    fn wait_for(&mut self, name: &str, limit: Duration) -> Option<ExitStatus> {
        let t = Instant::now();
        while t.elapsed() < limit {
            for (n, c) in &mut self.list {
                if n == name {
                    match c.try_wait() {
                        Ok(Some(s)) => return Some(s),
                        Ok(None) => {}
                        Err(_) => return None,
                    }
                }
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }

    /// Waits up to `limit` for every child but the router, then kills the rest.
    pub(crate) fn reap(&mut self, limit: Duration) {
        let t = Instant::now();
        // The router never ends by itself: wait for the nodes only.
        let running = |list: &mut Vec<(String, Child)>| {
            list.iter_mut().any(|(name, c)| name != "router" && matches!(c.try_wait(), Ok(None)))
        };
        while t.elapsed() < limit && running(&mut self.list) {
            std::thread::sleep(Duration::from_millis(20));
        }
        self.kill_all();
    }

    /// Lets the monitor write what it has (SIGTERM, up to 10 s) and the
    /// agents stop their robots (SIGTERM: an agent driving a robot through
    /// ROS 2 sends it zero velocity first), then kills every child.
    pub(crate) fn wind_down(&mut self) {
        self.terminate(|n| n == "monitor" || n.starts_with("agent"));
        let _ = self.wait_for("monitor", Duration::from_secs(10));
        let agents: Vec<String> = self.list.iter().map(|(n, _)| n.clone()).filter(|n| n.starts_with("agent")).collect();
        let t = Instant::now();
        for name in agents {
            let _ = self.wait_for(&name, Duration::from_secs(2).saturating_sub(t.elapsed()));
        }
        self.kill_all();
    }

    pub(crate) fn kill_all(&mut self) {
        for (_, child) in &mut self.list {
            if matches!(child.try_wait(), Ok(None)) {
                let _ = child.kill();
            }
            let _ = child.wait();
        }
    }

    /// The first child that has exited, with its status (removed from the set
    /// if it succeeded, so a finished node is not polled again).
    pub(crate) fn poll(&mut self) -> Option<(String, ExitStatus)> {
        for (name, child) in &mut self.list {
            if let Ok(Some(status)) = child.try_wait() {
                return Some((name.clone(), status));
            }
        }
        None
    }

    /// Kills the named child (SIGKILL: a crash, not a shutdown), reaps it and forgets it.
    pub(crate) fn kill(&mut self, name: &str) {
        for (n, child) in &mut self.list {
            if n == name {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
        self.remove(name);
    }

    pub(crate) fn remove(&mut self, name: &str) {
        self.list.retain(|(n, _)| n != name);
    }

    /// Process ids of the children still running.
    pub fn pids(&mut self) -> Vec<u32> {
        self.list.iter_mut().filter_map(|(_, c)| matches!(c.try_wait(), Ok(None)).then(|| c.id())).collect()
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        self.kill_all();
    }
}

fn ep(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

/// `count` loopback ports: consecutive from `base`, or free ones.
fn ports(base: Option<u16>, count: usize) -> Result<Vec<u16>, CliError> {
    if let Some(b) = base {
        if b == 0 {
            return Err(CliError::Input(
                "--base-port 0: give a port of 1 or more (or leave --base-port out for free ports)".into(),
            ));
        }
        // The ports are b, b + 1, …, b + count − 1.
        let last = u32::from(b) + count.saturating_sub(1) as u32;
        if last > u32::from(u16::MAX) {
            return Err(CliError::Input(format!("--base-port {b}: not enough ports above it for {count} nodes")));
        }
        return Ok((0..count as u16).map(|i| b + i).collect());
    }
    // Hold every listener until all are chosen, so no port is handed out twice.
    let listeners: Vec<TcpListener> = (0..count)
        .map(|_| TcpListener::bind("127.0.0.1:0"))
        .collect::<Result<_, _>>()
        .map_err(|e| CliError::Run(format!("finding free loopback ports: {e}")))?;
    listeners
        .iter()
        .map(|l| l.local_addr().map(|a| a.port()))
        .collect::<Result<_, _>>()
        .map_err(|e| CliError::Run(format!("finding free loopback ports: {e}")))
}

/// `formation launch`.
pub fn run(a: &LaunchArgs) -> Result<(), CliError> {
    if a.group == 0 {
        return Err(CliError::Input("--group 0: give 1 or more followers per agent process".into()));
    }
    if a.group > 1 && a.opts.tls.is_some() {
        return Err(CliError::Input(
            "--group with --tls: each follower has its own certificate and access rights, so each needs a process \
             of its own (leave --group out)"
                .into(),
        ));
    }
    a.links()?;
    let zfile = match &a.zenoh_config {
        Some(path) => {
            Some(session::SharedFile::check(path).map_err(|e| CliError::Input(format!("--zenoh-config: {e}")))?)
        }
        None => None,
    };
    if let Some(r) = &a.router {
        let z = session::ZenohArgs {
            mode: Some(session::ZenohMode::Client),
            connect: vec![r.clone()],
            ..Default::default()
        };
        z.to_config().map_err(|e| CliError::Input(format!("--router {r}: {e}")))?;
        if a.opts.tls.is_some() {
            return Err(CliError::Input(
                "--router with --tls: a router this launch does not start does not hold the run's certificates".into(),
            ));
        }
    }
    let (scenario, run, out) = a.opts.resolve()?;
    a.opts.warnings(&scenario, &out)?;
    let exe = std::env::current_exe().map_err(|e| CliError::Run(format!("locating this executable: {e}")))?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(|e| CliError::Run(format!("starting the async runtime: {e}")))?;
    let mut children = Children::new();
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
pub(crate) fn degraded_error(health: Option<(String, bool)>, out: &Path) -> Result<(), CliError> {
    match health {
        Some((line, true)) => Err(CliError::Degraded(format!(
            "the run was recorded to its end but is degraded ({}; {}/network.json has the evidence)",
            line.trim_start_matches("health: degraded: "),
            out.display()
        ))),
        _ => Ok(()),
    }
}

/// The links' lease of a launch whose nodes all run on this host (none
/// with `--router`, which may be elsewhere: its links keep the 1 s that
/// notices a cut link), nor when `--zenoh-config` set one (the file's is
/// kept). See [`session::LAUNCH_LEASE_MS`].
fn one_host_lease(a: &LaunchArgs, zfile: Option<&session::SharedFile>) -> Option<u64> {
    let own = zfile.and_then(|f| f.lease_ms).is_some();
    (a.router.is_none() && !own).then_some(session::LAUNCH_LEASE_MS)
}

/// `--config FILE` of `--zenoh-config`, for every node and the router.
fn zenoh_file_arg(c: &mut Command, zfile: Option<&session::SharedFile>) {
    if let Some(f) = zfile {
        c.arg("--config").arg(&f.path);
    }
}

fn node_command(exe: &Path, node: &str, a: &LaunchArgs, run: &str) -> Command {
    let mut c = Command::new(exe);
    node_args(&mut c, node, &a.opts, run);
    c
}

/// `node <node> --scenario … --run … --set …` of a run, stdin closed.
pub(crate) fn node_args(c: &mut Command, node: &str, opts: &RunOptions, run: &str) {
    c.args(["node", node]).arg("--run").arg(run);
    scenario_args(c, opts);
    tls_arg(c, opts);
    c.stdin(Stdio::null());
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

/// A node of a launch dies with it: should the launch itself be killed
/// (SIGKILL, the OOM killer), the kernel sends each child SIGTERM, and it
/// writes what it has and exits (they ran to the end of the run). Every
/// child is started from the launch's main thread, whose end is the
/// process's: the signal is tied to the thread that started the child.
pub(crate) fn dies_with_launch(c: &mut Command) {
    use std::os::unix::process::CommandExt;
    let parent = std::process::id();
    // SAFETY: between fork and exec only async-signal-safe calls (prctl,
    // getppid, _exit) run, on no shared state.
    unsafe {
        c.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The launch died before the line above: go now (not by a
            // signal: the launch's own handlers are still installed here).
            if libc::getppid() as u32 != parent {
                libc::_exit(1);
            }
            Ok(())
        });
    }
}

pub(crate) fn spawn(children: &mut Children, name: &str, mut c: Command) -> Result<(), CliError> {
    dies_with_launch(&mut c);
    zenoh_log::route(&mut c, name);
    let child = c.spawn().map_err(|e| CliError::Run(format!("starting {name}: {e}")))?;
    children.push(name.to_string(), child);
    Ok(())
}

/// Starts a router child and waits for its "router listening" line.
fn start_router(
    children: &mut Children,
    exe: &Path,
    listen: &[String],
    opts: &RunOptions,
    timing: formation_topology::Timing,
    lease: Option<u64>,
    zfile: Option<&session::SharedFile>,
) -> Result<(), CliError> {
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
    start_router_with(children, c)
}

/// Starts `c` (a `formation node router …` command) as the child "router"
/// and waits up to 30 s for its "router listening" line.
pub(crate) fn start_router_with(children: &mut Children, c: Command) -> Result<(), CliError> {
    start_router_named(children, "router", c)
}

/// [`start_router_with`] for a router known to `children` as `name`.
pub(crate) fn start_router_named(children: &mut Children, name: &str, mut c: Command) -> Result<(), CliError> {
    dies_with_launch(&mut c);
    zenoh_log::route(&mut c, name);
    c.stdin(Stdio::null()).stdout(Stdio::piped());
    let mut child = c.spawn().map_err(|e| CliError::Run(format!("starting {name}: {e}")))?;
    let stdout = child.stdout.take();
    children.push(name.into(), child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut lines = stdout.map(|s| BufReader::new(s).lines());
        let first = lines.as_mut().and_then(|l| l.next()).and_then(Result::ok);
        let _ = tx.send(first);
        // Keep draining so the router never blocks on a full pipe.
        if let Some(l) = lines {
            for _ in l {}
        }
    });
    match rx.recv_timeout(Duration::from_secs(30)) {
        Ok(Some(line)) if line.starts_with("router listening") => Ok(()),
        Ok(other) => Err(CliError::Run(format!("{name} did not start: {}", other.unwrap_or_default()))),
        Err(_) => Err(CliError::Run(format!("{name} did not start within 30 s"))),
    }
}

/// How every node of a launch reaches the others: its mode, its links'
/// endpoints and the zenoh settings it shares.
struct Wiring<'a> {
    mode: LaunchMode,
    links: Links,
    eps: Endpoints,
    router_ep: String,
    lease: Option<u64>,
    zfile: Option<&'a session::SharedFile>,
}

impl Wiring<'_> {
    /// A node's zenoh arguments: a client of the router, or a peer that
    /// listens on `listen` and dials `connect`.
    fn apply(&self, c: &mut Command, listen: Option<u16>, connect: &[u16]) {
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
    let (n, mode) = (scenario.followers.len(), wiring.mode);
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
        } + if robots == Robots::StandIn { " and a stand-in robot per follower" } else { "" },
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

/// The monitor and the leader, listening on their ports (peer mode).
fn spawn_monitor_and_leader(
    a: &LaunchArgs,
    run: &str,
    out: &Path,
    exe: &Path,
    wiring: &Wiring,
    (mon_port, lead_port): (u16, u16),
    children: &mut Children,
) -> Result<(), CliError> {
    let mut c = node_command(exe, "monitor", a, run);
    c.arg("--out").arg(out).stdout(Stdio::null());
    for (on, flag) in [(a.opts.quiet, "--quiet"), (a.opts.mcap, "--mcap"), (a.opts.rosbag2, "--rosbag2")] {
        if on {
            c.arg(flag);
        }
    }
    c.args(a.opts.web.to_args());
    wiring.apply(&mut c, Some(mon_port), &[]);
    spawn(children, "monitor", c)?;
    let mut c = node_command(exe, "leader", a, run);
    if let Some(x) = a.opts.time_scale {
        c.arg("--time-scale").arg(x.to_string());
    }
    wiring.apply(&mut c, Some(lead_port), &[mon_port]);
    spawn(children, "leader", c)
}

/// One agent process per group of followers (peer mode: each dials every
/// earlier process that holds a neighbour, or with the safety filter any
/// follower), and each follower's robot as the scenario says.
#[allow(clippy::too_many_arguments)]
fn spawn_agents(
    a: &LaunchArgs,
    scenario: &Scenario,
    run: &str,
    exe: &Path,
    wiring: &Wiring,
    groups: &[std::ops::Range<usize>],
    p: &[u16],
    robots: Robots,
    children: &mut Children,
) -> Result<(), CliError> {
    let peer = wiring.mode == LaunchMode::Peer;
    let (mon_port, lead_port) = if peer { (p[0], p[1]) } else { (0, 0) };
    for (g, members) in groups.iter().enumerate() {
        let ids: Vec<String> = members.clone().map(|i| scenario.graph.id(i).to_string()).collect();
        let mut c = node_command(exe, "agent", a, run);
        c.arg("--id").arg(ids.join(","));
        let mut connect = vec![mon_port, lead_port];
        if peer {
            let mut dial: Vec<usize> =
                members.clone().flat_map(|i| scenario.peers_of(i)).map(|j| j / a.group).filter(|&h| h < g).collect();
            dial.sort_unstable();
            dial.dedup();
            connect.extend(dial.into_iter().map(|h| p[2 + h]));
        }
        let listen = peer.then(|| p.get(2 + g).copied().unwrap_or(0));
        wiring.apply(&mut c, listen, &connect);
        let name = if ids.len() == 1 { format!("agent {}", ids[0]) } else { format!("agents {}", ids.join(",")) };
        spawn(children, &name, c)?;
        // A robot talks to its own agent only (peer), or through the router.
        for id in &ids {
            match robots {
                Robots::StandIn => {
                    let mut c = node_command(exe, "robot", a, run);
                    c.arg("--id").arg(id);
                    wiring.apply(&mut c, None, &listen.into_iter().collect::<Vec<_>>());
                    spawn(children, &format!("robot {id}"), c)?;
                }
                Robots::External if !a.opts.quiet => {
                    // A TCP endpoint: the unix sockets' folder is the launch's own.
                    let at = match listen {
                        Some(port) => ep(port),
                        None => a.router.clone().unwrap_or_else(|| ep(p[0])),
                    };
                    let domain = scenario.ros2.map_or(0, |r| r.domain_id);
                    eprintln!(
                        "waiting for robot {id}: publish /follower_{id}/odom (nav_msgs/msg/Odometry), take \
                         /follower_{id}/cmd_vel (geometry_msgs/msg/Twist), ROS domain {domain}, zenoh at {at}"
                    );
                }
                _ => {}
            }
        }
    }
    Ok(())
}

async fn launch(
    a: &LaunchArgs,
    zfile: Option<&session::SharedFile>,
    scenario: &Scenario,
    run: &str,
    out: &Path,
    exe: &Path,
    children: &mut Children,
) -> Result<Summary, CliError> {
    // Signals first: from here on Ctrl-C must reach the children's cleanup.
    let shutdown = crate::shutdown::from_now();
    let n = scenario.followers.len();
    let robots = match scenario.ros2.map(|r| r.robots) {
        Some(formation_topology::RobotSource::StandIn) => Robots::StandIn,
        Some(formation_topology::RobotSource::External) => Robots::External,
        _ => Robots::Simulated,
    };
    // Agent processes: followers by index, `group` consecutive ones each.
    let groups: Vec<std::ops::Range<usize>> = (0..n).step_by(a.group).map(|i| i..(i + a.group).min(n)).collect();
    // Ports: monitor, leader, agent processes (peer); or the router (client).
    // --router: every node a client of a router this launch does not own.
    let mode = if a.router.is_some() { LaunchMode::Client } else { a.mode };
    let own_router = mode == LaunchMode::Client && a.router.is_none();
    let count = if mode == LaunchMode::Peer { groups.len() + 2 } else { 1 };
    let p = ports(a.base_port, count)?;
    let links = a.links()?;
    let eps = Endpoints::new(links)?;
    let router_ep = a.router.clone().unwrap_or_else(|| eps.dial(p[0]));
    let wiring = Wiring { mode, links, eps, router_ep, lease: one_host_lease(a, zfile), zfile };
    if !a.opts.quiet {
        announce(a, scenario, run, groups.len(), own_router, robots, &wiring, p[0]);
    }
    if own_router {
        start_router(children, exe, &wiring.eps.listen(p[0]), &a.opts, scenario.timing, wiring.lease, zfile)?;
    }
    let node_ports = if mode == LaunchMode::Peer { (p[0], p[1]) } else { (0, 0) };
    spawn_monitor_and_leader(a, run, out, exe, &wiring, node_ports, children)?;
    spawn_agents(a, scenario, run, exe, &wiring, &groups, &p, robots, children)?;
    supervise(children, out, Duration::from_millis(50), shutdown, |_| Ok(())).await
}

/// The one supervision loop of `launch` and `lab`: every `every`, `each`
/// (the lab's fault events; an error ends the run with it), then whether the
/// run is over ([`settle`]); `shutdown` (a signal) stops every child
/// ([`interrupt`]).
pub(crate) async fn supervise(
    children: &mut Children,
    out: &Path,
    every: Duration,
    shutdown: impl std::future::Future<Output = formation_replay::watch::Signal>,
    mut each: impl FnMut(&mut Children) -> Result<(), CliError>,
) -> Result<Summary, CliError> {
    tokio::pin!(shutdown);
    let mut tick = tokio::time::interval(every);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            s = &mut shutdown => return Err(interrupt(children, out, crate::shutdown::number(s))),
        }
        each(children)?;
        if let Some(ended) = settle(children, out) {
            return ended;
        }
    }
}

/// Looks at the children that have exited: once the monitor has, the run is
/// over (its summary, or its failure); a node that failed stops the run
/// (the monitor first writes what it has). None while the run goes on.
pub(crate) fn settle(children: &mut Children, out: &Path) -> Option<Result<Summary, CliError>> {
    while let Some((name, status)) = children.poll() {
        if name == "monitor" {
            let degraded = status.code() == Some(i32::from(crate::error::DEGRADED));
            if !status.success() && !degraded {
                children.kill_all();
                return Some(Err(CliError::Run(format!("the monitor failed ({status})"))));
            }
            // The run is recorded; the nodes are done or about to be, and
            // a real-time stand-in robot is told to stop.
            children.remove("monitor");
            children.terminate(|n| n.starts_with("robot "));
            children.reap(Duration::from_secs(5));
            let path = out.join("summary.json");
            let read = std::fs::read_to_string(&path).map_err(|e| e.to_string());
            let summary = read.and_then(|text| serde_json::from_str(&text).map_err(|e| e.to_string()));
            return Some(summary.map_err(|e| CliError::Run(format!("reading {}: {e}", path.display()))));
        }
        if status.success() {
            children.remove(&name);
            continue;
        }
        // A node failed: let the monitor write what it has, stop the rest.
        children.wind_down();
        return Some(Err(CliError::Run(format!(
            "{name} failed ({status}); stopped every process; the run folder {} holds what the monitor received",
            out.display()
        ))));
    }
    None
}

/// Ctrl-C / SIGTERM (`signal`): stop the nodes, let the monitor flush, kill
/// the rest; the launch exits 128 + `signal`, as the monitor does.
pub(crate) fn interrupt(children: &mut Children, out: &Path, signal: i32) -> CliError {
    children.terminate(|n| n != "monitor" && n != "router");
    children.wind_down();
    CliError::Interrupted(
        format!("interrupted: stopped every process; {} holds what the monitor received", out.display()),
        signal as u8,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `launch scenarios/paper.toml` with `extra`, parsed.
    fn launch_args(extra: &[&str]) -> LaunchArgs {
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            l: LaunchArgs,
        }
        let mut args = vec!["launch", "scenarios/paper.toml"];
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
                Err(CliError::Input(m)) => assert!(m.starts_with(why), "{extra:?}: {m}"),
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
        assert!(matches!(ports(Some(0), 3), Err(CliError::Input(_))));
        assert_eq!(ports(Some(65533), 3).ok(), Some(vec![65533, 65534, 65535]));
        assert!(matches!(ports(Some(65534), 3), Err(CliError::Input(_))));
    }
}

/// Zenoh's own log lines of the nodes a launch starts: each node writes
/// them to a file of its own (the node shell's `FORMATION_ZENOH_LOG`)
/// rather than onto the terminal; at the end they go into the run folder's
/// `zenoh-log/` and the launch says in one line how many errors and
/// warnings which nodes logged, with the first error.
pub(crate) mod zenoh_log {
    use crate::error::CliError;
    use std::path::{Path, PathBuf};
    use std::process::Command;
    use std::sync::Mutex;

    /// The folder the nodes of this process's launch log into, while it runs.
    static DIR: Mutex<Option<PathBuf>> = Mutex::new(None);

    /// The run folder's subfolder that keeps the logs.
    pub const SUBDIR: &str = formation_net::session::ZENOH_LOG_SUBDIR;

    /// Starts collecting beside the run folder `out` (the monitor replaces
    /// `out` itself), in `<out>.zenoh-log`. One left there by a launch that
    /// was killed is replaced; a folder there that holds anything but
    /// zenoh logs is the user's, and refused.
    pub fn start(out: &Path) -> Result<Option<PathBuf>, CliError> {
        let dir = formation_record::folder::beside(out, formation_net::session::ZENOH_LOG_BESIDE);
        if let Ok(m) = std::fs::symlink_metadata(&dir) {
            let foreign = if m.is_dir() {
                formation_record::folder::names_in(&dir).unwrap_or_default().into_iter().find(|n| {
                    let p = dir.join(n);
                    !(n.to_string_lossy().ends_with(".log") && std::fs::symlink_metadata(p).is_ok_and(|m| m.is_file()))
                })
            } else {
                Some(std::ffi::OsString::new())
            };
            if let Some(name) = foreign {
                let what = if name.is_empty() {
                    "exists and is not a folder".to_string()
                } else {
                    format!("holds {}, which a launch does not write", name.to_string_lossy())
                };
                return Err(CliError::Input(format!(
                    "--out: {} (where a launch keeps zenoh's log lines while it runs) {what}: refusing to replace it \
                     (move it, or choose another --out)",
                    dir.display()
                )));
            }
            let _ = std::fs::remove_dir_all(&dir);
        }
        if std::fs::create_dir_all(&dir).is_err() {
            return Ok(None);
        }
        *DIR.lock().unwrap_or_else(|p| p.into_inner()) = Some(dir.clone());
        Ok(Some(dir))
    }

    /// Tells node `name`'s command where its zenoh lines go.
    pub fn route(c: &mut Command, name: &str) {
        if let Some(dir) = DIR.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
            let file: String = name.chars().map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '-' }).collect();
            c.env(formation_net::node::ZENOH_LOG_ENV, dir.join(format!("{file}.log")));
        }
    }

    /// [`finish`], and its lines on stderr: the sum (not with `quiet`) and
    /// the transports closed (always).
    pub fn finish_and_say(dir: Option<PathBuf>, out: &Path, quiet: bool) {
        if let Some(said) = finish(dir, out) {
            if !quiet {
                eprintln!("{}", said.line);
            }
            if let Some(closed) = said.closed {
                eprintln!("{closed}");
            }
        }
    }

    /// What zenoh logged in a run, summed up.
    pub struct Said {
        /// The line that sums it up.
        pub line: String,
        /// The transports zenoh closed, as one line (said even with `-q`).
        pub closed: Option<String>,
    }

    /// Moves what was logged into `out/zenoh-log/` (nothing logged: no
    /// folder), adds `zenoh_log` to `out/network.json`, and answers what
    /// sums it up, if anything was logged.
    pub fn finish(dir: Option<PathBuf>, out: &Path) -> Option<Said> {
        *DIR.lock().unwrap_or_else(|p| p.into_inner()) = None;
        let dir = dir?;
        let mut zids = Vec::new();
        let mut files: Vec<(String, String)> = std::fs::read_dir(&dir)
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| {
                let text = std::fs::read_to_string(e.path()).ok()?;
                let name = e.path().file_stem()?.to_string_lossy().into_owned();
                Some((name, text))
            })
            .collect();
        files.sort();
        // The nodes' own notes of their zids are not zenoh's lines.
        for (name, text) in &mut files {
            let (notes, rest): (Vec<&str>, Vec<&str>) =
                text.lines().partition(|l| l.starts_with(formation_net::session::ZID_NOTE));
            zids.extend(notes.iter().map(|l| (l[formation_net::session::ZID_NOTE.len()..].to_string(), name.clone())));
            *text = rest.iter().map(|l| format!("{l}\n")).collect();
        }
        files.retain(|(_, t)| !t.is_empty());
        if files.is_empty() {
            let _ = std::fs::remove_dir_all(&dir);
            return None;
        }
        // Into the run folder; where there is none (the monitor failed) they stay beside it.
        let kept = out.join(SUBDIR);
        let _ = std::fs::remove_dir_all(&kept);
        let kept = if out.is_dir() && std::fs::rename(&dir, &kept).is_ok() { kept } else { dir };
        let closed = closed_transports(&files, &zids);
        add_to_network_json(out, &files, &closed);
        Some(Said { line: summary(&files, &kept), closed: closed_line(&closed) })
    }

    /// (by, to, count) of zenoh's "Unable to push non droppable network
    /// message to ZID. Closing transport!", `to` named by the zids the
    /// nodes noted.
    pub fn closed_transports(files: &[(String, String)], zids: &[(String, String)]) -> Vec<(String, String, usize)> {
        let mut out: Vec<(String, String, usize)> = Vec::new();
        for (by, text) in files {
            for l in text.lines().filter(|l| l.contains("Closing transport")) {
                let zid = l.split_once(" message to ").map(|(_, r)| r.split(['.', ' ']).next().unwrap_or(""));
                let to =
                    zid.map(|z| zids.iter().find(|(id, _)| id == z).map_or(format!("zid {z}"), |(_, n)| n.clone()));
                let to = to.unwrap_or_else(|| "a peer".to_string());
                match out.iter_mut().find(|(b, t, _)| b == by && *t == to) {
                    Some(e) => e.2 += 1,
                    None => out.push((by.clone(), to, 1)),
                }
            }
        }
        out
    }

    fn closed_line(closed: &[(String, String, usize)]) -> Option<String> {
        if closed.is_empty() {
            return None;
        }
        let n: usize = closed.iter().map(|c| c.2).sum();
        let each: Vec<String> = closed
            .iter()
            .map(|(by, to, k)| if *k == 1 { format!("{by} → {to}") } else { format!("{by} → {to} ({k} times)") })
            .collect();
        Some(format!(
            "warning: zenoh closed {n} transport{} ({}): a message that may not be dropped found the queue to that \
             node full for zenoh's 5 s (the node starved of CPU, or its link stalled); it reconnected, and what it \
             missed meanwhile is in network.json (isolated, telemetry_resent)",
            if n == 1 { "" } else { "s" },
            each.join(", ")
        ))
    }

    /// `network.json`'s `zenoh_log`: errors and warnings per node, the
    /// transports closed, the folder.
    fn add_to_network_json(out: &Path, files: &[(String, String)], closed: &[(String, String, usize)]) {
        let path = out.join("network.json");
        let Some(mut v) =
            std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        else {
            return;
        };
        let count = |text: &str, level: &str| text.lines().filter(|l| l.contains(level)).count();
        let nodes: serde_json::Map<String, serde_json::Value> = files
            .iter()
            .map(|(n, t)| {
                (n.clone(), serde_json::json!({ "errors": count(t, " ERROR "), "warnings": count(t, " WARN ") }))
            })
            .collect();
        let closed: Vec<serde_json::Value> =
            closed.iter().map(|(by, to, k)| serde_json::json!({ "by": by, "to": to, "count": k })).collect();
        if let Some(o) = v.as_object_mut() {
            o.insert(
                "zenoh_log".into(),
                serde_json::json!({ "folder": SUBDIR, "nodes": nodes, "transports_closed": closed }),
            );
        }
        if let Ok(text) = serde_json::to_string_pretty(&v) {
            let _ = std::fs::write(&path, text + "\n");
        }
    }

    /// "zenoh logged 3 errors and 1 warning (agent-3: 3 errors; router: 1
    /// warning); the first error: …; every line is in OUT/zenoh-log/".
    pub fn summary(files: &[(String, String)], kept: &Path) -> String {
        let count = |text: &str, level: &str| text.lines().filter(|l| l.contains(level)).count();
        let mut per_node = Vec::new();
        let (mut errors, mut warnings) = (0, 0);
        for (name, text) in files {
            let (e, w) = (count(text, " ERROR "), count(text, " WARN "));
            errors += e;
            warnings += w;
            if e + w > 0 {
                per_node.push(format!("{name}: {}", counted(e, w)));
            }
        }
        let first = files.iter().flat_map(|(_, t)| t.lines()).find(|l| l.contains(" ERROR "));
        let first = first.map_or(String::new(), |l| {
            let msg = l.split_once(" ERROR ").map_or(l, |(_, m)| m).trim();
            let short: String = msg.chars().take(200).collect();
            format!("; the first error: {short}")
        });
        if per_node.is_empty() {
            let lines: usize = files.iter().map(|(_, t)| t.lines().count()).sum();
            return format!("zenoh logged {lines} lines, no errors or warnings; they are in {}", kept.display());
        }
        format!(
            "zenoh logged {} ({}){first}; every line is in {}",
            counted(errors, warnings),
            per_node.join("; "),
            kept.display()
        )
    }

    fn counted(errors: usize, warnings: usize) -> String {
        let plural = |n: usize, w: &str| format!("{n} {w}{}", if n == 1 { "" } else { "s" });
        match (errors, warnings) {
            (e, 0) => plural(e, "error"),
            (0, w) => plural(w, "warning"),
            (e, w) => format!("{} and {}", plural(e, "error"), plural(w, "warning")),
        }
    }

    #[cfg(test)]
    mod tests {
        #[test]
        fn the_summary_counts_errors_and_warnings_per_node_and_quotes_the_first_error() {
            let files = vec![
                ("agent-3".to_string(), "2026 ERROR zenoh::net: Unable to push non droppable network message. Closing transport!\n2026 ERROR zenoh::net: again\n".to_string()),
                ("router".to_string(), "2026  WARN zenoh::x: slow\n".to_string()),
            ];
            let line = super::summary(&files, std::path::Path::new("runs/x/zenoh-log"));
            assert_eq!(
                line,
                "zenoh logged 2 errors and 1 warning (agent-3: 2 errors; router: 1 warning); the first error: \
                 zenoh::net: Unable to push non droppable network message. Closing transport!; every line is in \
                 runs/x/zenoh-log"
            );
        }

        /// The transports zenoh closed, by the node that closed them and
        /// the node they went to (named by the zids the nodes noted).
        #[test]
        fn closed_transports_name_both_nodes() {
            let push = |zid: &str| {
                format!("2026-11-26T00:55:13Z ERROR zenoh_transport::unicast::universal::tx: Unable to push non droppable network message to {zid}. Closing transport!\n")
            };
            let files = vec![
                ("router".to_string(), push("893eaf0a") + &push("893eaf0a") + &push("77aa")),
                ("agent-1".to_string(), "2026 WARN zenoh::x: slow\n".to_string()),
            ];
            let zids = vec![("893eaf0a".to_string(), "agent-4".to_string())];
            let closed = super::closed_transports(&files, &zids);
            assert_eq!(
                closed,
                vec![
                    ("router".to_string(), "agent-4".to_string(), 2),
                    ("router".to_string(), "zid 77aa".to_string(), 1)
                ]
            );
            let line = super::closed_line(&closed).expect("a line");
            assert!(
                line.starts_with("warning: zenoh closed 3 transports (router → agent-4 (2 times), router → zid 77aa)"),
                "{line}"
            );
            assert_eq!(super::closed_line(&[]), None);
        }
    }
}
