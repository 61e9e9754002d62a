//! What a launch (and a lab run) is asked to do: the command's arguments
//! and the options every run of nodes shares, checked before anything is
//! planned or started.

use std::path::{Path, PathBuf};

use formation_protocol::barrier::{quorum_wait, Quorum};
use formation_scenario::args::ScenarioArgs;
use formation_scenario::Scenario;

use formation_exit::Error;

/// How the launched nodes reach each other.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum LaunchMode {
    /// Router-less peers, each listening on its own loopback port.
    Peer,
    /// Clients of a `router` child.
    Client,
}

/// What the launched nodes' links to each other run over.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
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

/// What every command that runs the whole networked formation takes
/// (`launch`, `lab`).
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct RunOptions {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub scenario: ScenarioArgs,
    /// Run folder the monitor writes [default: runs/<run name>]. Replaced if it is a run folder; any other existing folder is refused.
    #[cfg_attr(feature = "clap", arg(long))]
    pub out: Option<PathBuf>,
    /// Run name (key namespace formation/<run>/…) [default: scenario name].
    #[cfg_attr(feature = "clap", arg(long, value_name = "NAME"))]
    pub run: Option<String>,
    /// Real-time mode: run seconds per wall-clock second [default: network.time_scale].
    #[cfg_attr(feature = "clap", arg(long, value_name = "X"))]
    pub time_scale: Option<f64>,
    /// Print nothing but errors (and no live line).
    #[cfg_attr(feature = "clap", arg(long, short))]
    pub quiet: bool,
    /// Mutual TLS on every link and access control from the topology, with
    /// the certificates in DIR (made by `formation certs SCENARIO --out DIR`).
    #[cfg_attr(feature = "clap", arg(long, value_name = "DIR"))]
    pub tls: Option<PathBuf>,
    /// Also write run.mcap: the CSVs' rows as an MCAP recording that
    /// Foxglove and the mcap tools open (poses as foxglove.PoseInFrame, every
    /// column as numbers, network events). About 1.6 KB per follower row:
    /// combine with --every for long runs.
    #[cfg_attr(feature = "clap", arg(long))]
    pub mcap: bool,
    /// Also write rosbag2/: the CSVs' rows as a ROS 2 bag (metadata.yaml and
    /// an MCAP file of CDR messages: odom, cmd_vel, leader_estimate, /tf,
    /// /clock) that `ros2 bag` and Foxglove open (docs/ros2.md).
    #[cfg_attr(feature = "clap", arg(long))]
    pub rosbag2: bool,
    #[cfg_attr(feature = "clap", command(flatten))]
    pub web: formation_net::monitor::WebArgs,
    /// Real time: run every node under the OS's real-time scheduling
    /// (SCHED_FIFO) at this priority, 1–99, so that other work on the
    /// machine cannot hold a step or a message up (needs root or
    /// CAP_SYS_NICE). On a 2-core machine with 52 processes it took the
    /// 50-agent ring from 2–50 late link-steps in 10 s to 0–4.
    #[cfg_attr(feature = "clap", arg(long, value_name = "N"))]
    pub rt_priority: Option<u8>,
    /// Publish the formation on ROS 2's wire (rmw_zenoh): each follower's
    /// odom, cmd_vel and leader_estimate in /follower_<i>, /leader/odom,
    /// /tf, and /clock in lock-step (the scenario's [ros2] table; docs/ros2.md).
    #[cfg_attr(feature = "clap", arg(long))]
    pub ros2: bool,
    /// Who moves the robots: simulated (in each agent), stand-in (a
    /// `formation robot` process per follower, driven through ROS 2's
    /// cmd_vel and odom) or external (real robots or Gazebo; the run waits
    /// for their odometry). stand-in and external need robot.model =
    /// "velocity" and turn --ros2 on.
    #[cfg_attr(feature = "clap", arg(long, value_enum, value_name = "WHO"))]
    pub robots: Option<Robots>,
    /// Follower ID leaves the run for good at run time SECONDS
    /// (repeatable): it takes no step from then on, tells its neighbours
    /// and the monitor, and its robot stops; the others run on. The model
    /// of it is the fault row `node = ID, from = SECONDS` to the end.
    #[cfg_attr(feature = "clap", arg(long = "leave", value_name = "ID@SECONDS"))]
    pub leave: Vec<String>,
    /// Start with those present: once --quorum-wait has passed, the run
    /// starts when N followers (and the monitor) are ready; the others are
    /// absent, named in one line and in network.json, and cut off from the
    /// start in the run and its model [default: every follower].
    #[cfg_attr(feature = "clap", arg(long, value_name = "N"))]
    pub quorum: Option<usize>,
    /// With --quorum: how long every node waits for the others before the
    /// leader starts with those present (s) [default: 10].
    #[cfg_attr(feature = "clap", arg(long, value_name = "SECONDS", requires = "quorum"))]
    pub quorum_wait: Option<f64>,
    /// With --quorum: start even if, without the absent, some present
    /// followers no longer reach the leader (else refused, naming them).
    #[cfg_attr(feature = "clap", arg(long, requires = "quorum"))]
    pub even_if_cut_off: bool,
    /// Do not start follower ID's agent (repeatable; with --quorum): a
    /// fleet with a robot missing.
    #[cfg_attr(feature = "clap", arg(long, value_name = "ID", requires = "quorum"))]
    pub absent: Vec<u32>,
}

/// `--robots`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
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
fn real_time_scheduling(priority: u8) -> Result<(), Error> {
    if !(1..=99).contains(&priority) {
        return Err(Error::Input(format!("--rt-priority must be 1 to 99, not {priority}")));
    }
    let param = libc::sched_param { sched_priority: i32::from(priority) };
    // SAFETY: a plain system call on this process with a valid parameter.
    if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } != 0 {
        let e = std::io::Error::last_os_error();
        return Err(Error::Input(format!(
            "--rt-priority {priority}: the OS refused real-time scheduling ({e}); run as root, with CAP_SYS_NICE, or \
             with a real-time priority limit (ulimit -r)"
        )));
    }
    Ok(())
}

impl RunOptions {
    /// The scenario, the run name and the run folder, checked (bad input: exit 2).
    pub fn resolve(&self) -> Result<(Scenario, String, PathBuf), Error> {
        let scenario =
            Scenario::load(&self.scenario.scenario, &self.overrides()).map_err(|e| Error::Input(self.as_typed(e)))?;

        formation_net::node::networked(&scenario)?;
        let run = self.run.clone().unwrap_or_else(|| scenario.name.clone());
        formation_protocol::names::validate_run_name(&run).map_err(|e| Error::Input(e.to_string()))?;
        if let Some(x) = self.time_scale {
            if !(x.is_finite() && x > 0.0) {
                return Err(Error::Input(format!("--time-scale must be a positive number, not {x}")));
            }
        }
        let out = self.out.clone().unwrap_or_else(|| Path::new("runs").join(&run));
        formation_record::out_path::check_out_path("--out", &out, formation_record::out_path::MAX_OUT_NAME_BYTES)
            .map_err(Error::Input)?;
        // The monitor would refuse it too, but only once every node runs.
        formation_record::refuse_replacing_foreign(&out).map_err(|e| Error::Input(format!("--out: {e}")))?;
        if let Some(p) = self.rt_priority {
            if scenario.timing != formation_scenario::Timing::Realtime {
                return Err(Error::Input(format!(
                    "--rt-priority {p}: a lock-step run waits for its inputs and has no period to meet (set timing = \
                     \"realtime\")"
                )));
            }
            real_time_scheduling(p)?;
        }
        if let Some(dir) = &self.tls {
            // Every node's files, checked before any process starts.
            formation_net::identity::check_all(dir, &scenario).map_err(|e| Error::Input(e.0))?;
        }
        Ok((scenario, run, out))
    }

    /// The scenario's overrides, with what --ros2 and --robots set.
    pub fn overrides(&self) -> Vec<String> {
        let mut o = self.scenario.all_overrides();
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
    fn as_typed(&self, e: formation_scenario::ScenarioError) -> String {
        let mut text = e.to_string();
        if let Some(r) = self.robots {
            let (set, typed) = (format!("--set ros2.robots=\"{}\"", r.name()), format!("--robots {}", r.name()));
            text = text.replace(&format!("{set}: ros2.robots: `{}`:", r.name()), &format!("{typed}:"));
            text = text.replace(&set, &typed);
        }
        if self.ros2 {
            text = text.replace("--set ros2.enabled=true", "--ros2");
        }
        if let Some(l) = &self.scenario.leader {
            text = text.replace(&format!("--set leader.source=\"{l}\""), &format!("--leader {l}"));
        }
        text
    }

    /// What a run says before it starts, once its input is known to be good:
    /// that its traffic is unauthenticated (without --tls), and the size of
    /// a run that would write more than a few GB; a run larger than its
    /// disk's free space is refused.
    /// The `--leave ID@SECONDS` values of follower `id`, for its agent's
    /// command line (checked by [`RunOptions::warnings`]).
    pub fn leaves_of(&self, id: u32) -> impl Iterator<Item = &String> {
        self.leave.iter().filter(move |l| l.split_once('@').is_some_and(|(i, _)| i.trim().parse() == Ok(id)))
    }

    /// `--quorum`, `--quorum-wait` and `--absent`, in the leader's words.
    fn check_quorum(&self, scenario: &Scenario) -> Result<(), Error> {
        let Some(followers) = self.quorum else { return Ok(()) };
        let wait = quorum_wait(self.quorum_wait()).map_err(Error::Input)?;
        let q = Quorum { followers, wait, even_if_cut_off: self.even_if_cut_off };
        q.check(scenario.graph.len()).map_err(Error::Input)?;
        if let Some(id) = self.absent.iter().find(|id| !scenario.graph.ids().contains(id)) {
            return Err(Error::Input(format!("--absent {id}: no follower {id} in this scenario")));
        }
        let list = formation_scenario::graph::id_list;
        let present = scenario.graph.len() - self.absent.len();
        if present < followers {
            return Err(Error::Input(format!(
                "--quorum {followers} with followers {} absent: only {present} can be ready",
                list(&self.absent)
            )));
        }
        if let Some(cut) = scenario.graph.cut_off_without(&self.absent).filter(|_| !self.even_if_cut_off) {
            return Err(Error::Input(format!(
                "--absent {}: {cut}: not started (--even-if-cut-off starts anyway)",
                list(&self.absent)
            )));
        }
        Ok(())
    }

    /// The quorum wait every node is given (s).
    pub fn quorum_wait(&self) -> f64 {
        self.quorum_wait.unwrap_or(formation_net::leader::QUORUM_WAIT.as_secs_f64())
    }

    /// Lemma 1 through every membership change the run is given: `--absent`
    /// (each joining at its time in `joins`, the lab's `--join`), `--leave`
    /// and the scenario's leave rows, together. One line naming the flags,
    /// unless --even-if-cut-off.
    pub fn check_membership(
        &self,
        scenario: &Scenario,
        joins: &[(u32, f64)],
        kills: &[(u32, f64)],
    ) -> Result<(), Error> {
        let mut leaves = formation_net::agent::planned_leaves(&self.leave, scenario)?;
        leaves.extend(kills.iter().filter(|k| !leaves.iter().any(|l| l.0 == k.0)).copied().collect::<Vec<_>>());
        let absent: Vec<(u32, Option<f64>)> =
            self.absent.iter().map(|&id| (id, joins.iter().find(|j| j.0 == id).map(|j| j.1))).collect();
        let Some(cut) = scenario.graph.cut_off_through(&absent, &leaves, &[]) else { return Ok(()) };
        if self.even_if_cut_off {
            return Ok(());
        }
        let mut given: Vec<String> = Vec::new();
        if !self.absent.is_empty() {
            given.push(format!("--absent {}", formation_scenario::graph::id_list(&self.absent)));
        }
        given.extend(self.leave.iter().map(|l| format!("--leave {l}")));
        given.extend(kills.iter().map(|k| format!("--kill-agent {}@{}", k.0, k.1)));
        if scenario.faults.iter().any(|f| f.leave) {
            given.push("the scenario's leave rows".into());
        }
        Err(Error::Input(format!(
            "{}: {cut}: their estimates of the leader would drift; not started (--even-if-cut-off starts anyway)",
            given.join(" with ")
        )))
    }

    /// `joins` and `kills`: the lab's `--join` and `--kill-agent` (id, s).
    pub fn warnings(
        &self,
        scenario: &Scenario,
        out: &Path,
        joins: &[(u32, f64)],
        kills: &[(u32, f64)],
    ) -> Result<(), Error> {
        // Checked here, in the agents' own words, before anything starts.
        formation_net::agent::check_leaves(&self.leave, scenario)?;
        self.check_quorum(scenario)?;
        self.check_membership(scenario, joins, kills)?;
        let less = if self.mcap { "a shorter duration or no --mcap" } else { "a shorter duration" };
        crate::runsize::check(scenario, 1, true, self.mcap, out, less)?;
        if self.tls.is_none() && !self.quiet {
            eprintln!("{}", formation_net::node::UNAUTHENTICATED);
        }
        Ok(())
    }
}

#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct LaunchArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub opts: RunOptions,
    /// peer: router-less mesh; client: every node through a zenoh router child.
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = LaunchMode::Peer))]
    pub mode: LaunchMode,
    /// Use consecutive loopback ports from this one [default: free ports].
    #[cfg_attr(feature = "clap", arg(long, value_name = "PORT"))]
    pub base_port: Option<u16>,
    /// Followers per agent process (consecutive ids share one zenoh session,
    /// and what they say to each other stays in the process). 1 (the
    /// default) is one process per follower, as on separate machines; more
    /// fits large formations on few cores. Not with --tls.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1, value_name = "N"))]
    pub group: usize,
    /// Join this zenoh router (e.g. rmw_zenohd's, tcp/127.0.0.1:7447)
    /// instead of starting one: every node is its client, as ROS 2 nodes
    /// on rmw_zenoh are.
    #[cfg_attr(feature = "clap", arg(long, value_name = "ENDPOINT"))]
    pub router: Option<String>,
    /// What the nodes' links to each other run over [default: unix; tcp
    /// with --tls or --router]. On a busy host unix sockets leave fewer
    /// messages late than loopback TCP (docs/performance.md); every node
    /// listens on its TCP port either way.
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub links: Option<Links>,
    /// A zenoh configuration file (json5, zenoh's format) for every node
    /// this launch starts, the router included: buffers, batching, access
    /// control, … It is checked once before anything starts, with a
    /// node's rules for --config (multicast stays off, QoS must stay on),
    /// and may not set id, mode, listen or connect: the launch gives each
    /// node its own. A lease it sets replaces the launch's 10 s.
    #[cfg_attr(feature = "clap", arg(long, value_name = "FILE.json5"))]
    pub zenoh_config: Option<PathBuf>,
    /// Start a standby leader beside the leader (client mode): should the
    /// leader die (`kill -9` it to try), the standby takes the run over
    /// after --take-over-after seconds of silence, with the same trajectory
    /// and timebase, and the run goes on; the monitor names the handover.
    #[cfg_attr(feature = "clap", arg(long))]
    pub standby: bool,
    /// With --standby: the leader's silence (s) after which the standby takes over.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.5, value_name = "SECONDS", requires = "standby"))]
    pub take_over_after: f64,
}

impl LaunchArgs {
    /// `--standby`: one line for a standby this launch cannot wire, or a
    /// bad wait.
    pub fn check_standby(&self) -> Result<(), Error> {
        if !self.standby {
            return Ok(());
        }
        if self.mode != LaunchMode::Client && self.router.is_none() {
            return Err(Error::Input(
                "--standby needs --mode client (or --router): the standby reaches every node through the router, \
                 as on a host of its own"
                    .into(),
            ));
        }
        if !(self.take_over_after.is_finite() && self.take_over_after > 0.0) {
            return Err(Error::Input(format!(
                "--take-over-after must be a positive number of seconds, not {}",
                self.take_over_after
            )));
        }
        Ok(())
    }

    /// The links this launch uses (see [`LaunchArgs::links`]).
    pub fn links(&self) -> Result<Links, Error> {
        let tcp_only = match (&self.opts.tls, &self.router) {
            (Some(_), _) => Some("--tls (TLS runs over TCP)"),
            (None, Some(_)) => Some("--router (every node dials that router)"),
            (None, None) => None,
        };
        match (self.links, tcp_only) {
            (Some(Links::Unix), Some(why)) => Err(Error::Input(format!("--links unix cannot go with {why}"))),
            (Some(l), _) => Ok(l),
            (None, Some(_)) => Ok(Links::Tcp),
            (None, None) => Ok(Links::default()),
        }
    }
}
