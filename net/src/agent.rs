//! One follower as a networked node (the `agent` binary): a translation
//! between zenoh and the follower's protocol machine
//! ([`formation_protocol::follower::FollowerMachine`]), which holds every rule.
//! The node subscribes only to its neighbours' estimate keys (and the
//! leader's if a_i0 = 1), publishes what the machine says on its own key,
//! and hands the machine's telemetry to a courier for the monitor.
//!
//! The machine's loop is fed by the subscriber callbacks under one lock. In
//! real time it is a task on zenoh's own thread, woken by a precise timer,
//! so that what it publishes is written out in the same wake-up (a process
//! of several followers gives each loop a thread of its own); in lock-step
//! it runs on its own thread, waiting on a condition variable that the
//! step's last input signals. Start-up and shut-down are async.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use formation_plant::Pose;
use formation_protocol::follower::{self, Batch, FollowerMachine, Joining};
use formation_protocol::wire;
use formation_scenario::{Scenario, Timing};
use zenoh::pubsub::Publisher;
use zenoh::Wait;

use crate::checkpoint;
use crate::clock::{Clock, Timebase};
use crate::clock_sync;
use crate::courier::Courier;
use crate::node::NodeArgs;
use crate::ros2::driven::{self, DrivenRobot, OdomInbox};
use crate::ros2::rmw_node::{RosNode, RosSubscription};
use crate::ros2::topics::{FollowerTopics, Stamps};
use crate::startup;
use crate::telemetry;
use formation_exit::{zerr, Error};
use formation_protocol::barrier::{self, Start};
use formation_protocol::codec;
use formation_protocol::counters::AtomicRejects;
use formation_protocol::names::{self, Keys};
use formation_protocol::telemetry::{Delivery, EventKind};
use formation_sim::SimFollower;

use formation_protocol::follower::Body;

/// `agent` arguments.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct AgentArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// The follower this process runs, or several (`--id 1,2,3`) that share
    /// one zenoh session: what they say to each other stays inside the
    /// process (no socket, no router), which is how many agents fit on few
    /// cores. Each keeps its own control loop, inbox, telemetry and
    /// checkpoint; one failing ends the process.
    #[cfg_attr(feature = "clap", arg(long, value_delimiter = ',', required = true, value_name = "ID[,ID…]"))]
    pub id: Vec<u32>,
    /// Give up if lock-step inputs stop arriving for this long (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 60.0, value_name = "SECONDS"))]
    pub stall_timeout: f64,
    /// The network itself performs the fault table's `node = …` rows
    /// (`formation lab` takes the link down): do not drop their messages
    /// again in software. `link = …` rows are still applied here.
    #[cfg_attr(feature = "clap", arg(long, hide = true))]
    pub physical_node_faults: bool,
    /// Where the robot's pose is checkpointed every 100 ms, so that a
    /// restarted agent resumes from it (default: formation-checkpoints in
    /// the system's temporary folder).
    #[cfg_attr(feature = "clap", arg(long, value_name = "DIR"))]
    pub checkpoint_dir: Option<std::path::PathBuf>,
    /// A follower of this process leaves the run for good at run time
    /// SECONDS (repeatable): it takes no step from then on and tells its
    /// neighbours and the monitor, as SIGTERM would make it do, but at an
    /// exact step, so a lock-step run equals `formation sim` with the fault
    /// row `node = ID, from = SECONDS` to the end.
    #[cfg_attr(feature = "clap", arg(long = "leave", value_name = "ID@SECONDS"))]
    pub leave: Vec<String>,
    /// Leave (--leave, or the scenario's leave row) even if others would
    /// then no longer reach the leader, with the followers absent at the
    /// start (Lemma 1; else refused, naming them).
    #[cfg_attr(feature = "clap", arg(long))]
    pub even_if_cut_off: bool,
    /// No line of news (a follower leaving the run); warnings and errors
    /// are still said.
    #[cfg_attr(feature = "clap", arg(short, long))]
    pub quiet: bool,
}

/// `--id`'s first follower (the process's name), or one line for ids
/// given twice, none, or several with `--tls`.
fn first_id(args: &AgentArgs) -> Result<u32, Error> {
    let ids = &args.id;
    let first = *ids.first().ok_or_else(|| Error::Input("--id: give at least one follower id".into()))?;
    if let Some(twice) = ids.iter().enumerate().find_map(|(i, id)| ids[..i].contains(id).then_some(id)) {
        return Err(Error::Input(format!("--id: follower {twice} is given twice")));
    }
    if ids.len() > 1 && args.node.zenoh.tls.is_some() {
        return Err(Error::Input(
            "--id with several followers and --tls: each follower has its own certificate and access rights, so \
             each needs a process of its own"
                .into(),
        ));
    }
    Ok(first)
}

/// `--leave ID@SECONDS` of a process holding `ids`: per follower, the step
/// before which it leaves; one line naming the flag for a bad one.
pub fn leave_steps(leave: &[String], ids: &[u32], scenario: &Scenario) -> Result<Vec<(u32, u64)>, Error> {
    let mut out = Vec::new();
    for l in leave {
        let bad = || Error::Input(format!("--leave {l}: give ID@SECONDS, e.g. --leave 3@12.5"));
        let (id, t) = l.split_once('@').ok_or_else(bad)?;
        let (id, t): (u32, f64) = (id.trim().parse().map_err(|_| bad())?, t.trim().parse().map_err(|_| bad())?);
        if scenario.index_of(id).is_none() {
            let all: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
            return Err(Error::Input(format!(
                "--leave {l}: scenario {} has no follower {id} (ids: {})",
                scenario.name,
                all.join(", ")
            )));
        }
        if !ids.contains(&id) {
            return Err(Error::Input(format!("--leave {l}: follower {id} is not one of this process's (--id)")));
        }
        if !(t > 0.0 && t < scenario.duration_s) {
            return Err(Error::Input(format!(
                "--leave {l}: the time must be within the run, after 0 and before its end at {} s",
                scenario.duration_s
            )));
        }
        if out.iter().any(|&(i, _)| i == id) {
            return Err(Error::Input(format!("--leave: follower {id} is given twice")));
        }
        out.push((id, formation_control::math::step_at(t, scenario.dt_s)));
    }
    Ok(out)
}

/// Every leave a run is given: `--leave ID@SECONDS` (of any follower) and
/// the scenario's leave rows, as (id, run time in s).
pub fn planned_leaves(leave: &[String], scenario: &Scenario) -> Result<Vec<(u32, f64)>, Error> {
    let mut out: Vec<(u32, f64)> = leave_steps(leave, scenario.graph.ids(), scenario)?
        .into_iter()
        .map(|(id, k)| (id, k as f64 * scenario.dt_s))
        .collect();
    for &id in scenario.graph.ids() {
        if let Some(k) = scenario.leave_step(id).filter(|_| !out.iter().any(|l| l.0 == id)) {
            out.push((id, k as f64 * scenario.dt_s));
        }
    }
    Ok(out)
}

/// The leaves of this process's followers (`--leave`, and the scenario's
/// leave rows), as (id, step), refused in one line where they break Lemma 1.
fn own_leaves(args: &AgentArgs, scenario: &Scenario) -> Result<Vec<(u32, u64)>, Error> {
    let mut leave_at = leave_steps(&args.leave, &args.id, scenario)?;
    for &id in &args.id {
        // A died row's follower does not leave: it is killed (Node::die).
        let row = scenario.leave_step(id).filter(|_| !scenario.died(id));
        if let Some(k) = row.filter(|_| !leave_at.iter().any(|l| l.0 == id)) {
            leave_at.push((id, k));
        }
    }
    let planned: Vec<(u32, f64)> = leave_at.iter().map(|&(id, k)| (id, k as f64 * scenario.dt_s)).collect();
    match scenario.graph.cut_off_through(&[], &planned, &[]).filter(|_| !args.even_if_cut_off) {
        None => Ok(leave_at),
        Some(cut) => Err(Error::Input(format!(
            "{}: {cut}: their estimates of the leader would drift (--even-if-cut-off to leave anyway)",
            leaves_named(&planned)
        ))),
    }
}

/// "follower 3's leave at 5 s", "followers 2, 3's leaves at 5, 8 s".
fn leaves_named(leaves: &[(u32, f64)]) -> String {
    let ids: Vec<u32> = leaves.iter().map(|l| l.0).collect();
    let at: Vec<String> = leaves.iter().map(|l| l.1.to_string()).collect();
    match leaves.len() {
        1 => format!("follower {}'s leave at {} s", ids[0], at[0]),
        _ => format!("followers {}' leaves at {} s", formation_scenario::graph::id_list(&ids), at.join(", ")),
    }
}

/// Lemma 1 once the followers of `--leave` (every one of the formation's)
/// have left: refused in one line naming the followers they would cut off
/// from the leader (their estimates would drift on dead reckoning).
pub fn check_leaves(leave: &[String], scenario: &Scenario) -> Result<(), Error> {
    let gone: Vec<u32> = leave_steps(leave, scenario.graph.ids(), scenario)?.into_iter().map(|(id, _)| id).collect();
    match scenario.graph.cut_off_without(&gone) {
        None => Ok(()),
        Some(cut) => Err(Error::Input(format!(
            "--leave: {cut}: their estimates of the leader would drift; leave another follower, or fewer"
        ))),
    }
}

/// Runs the follower(s) of `--id` to the end of the scenario.
///
/// `shutdown` (SIGINT or SIGTERM in the binary) makes every follower leave
/// the run at its next step ([`FollowerMachine::handle_leave`]: its last telemetry
/// says so, and the monitor waits for nothing more from it), within
/// [`LEAVE_WITHIN`]; the signal is returned. With robots driven through
/// ROS 2, every follower's robot is sent zero velocity before the process
/// ends, however it ends (the run's end, an error, a refused start, the
/// signal).
pub async fn run(
    args: &AgentArgs,
    shutdown: impl std::future::Future<Output = formation_exit::shutdown::Signal>,
) -> Result<Option<formation_exit::shutdown::Signal>, Error> {
    let ids = &args.id;
    let first = first_id(args)?;
    let (scenario, keys) = args.node.load(&formation_protocol::names::agent_name(first))?;
    let mut indices = Vec::with_capacity(ids.len());
    for &id in ids {
        indices.push(scenario.index_of(id).ok_or_else(|| {
            let all: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
            Error::Input(format!("scenario {} has no follower {id} (ids: {})", scenario.name, all.join(", ")))
        })?);
    }
    let leave_at = own_leaves(args, &scenario)?;
    if !args.stall_timeout.is_finite() || args.stall_timeout <= 0.0 {
        return Err(Error::Input("--stall-timeout must be positive".into()));
    }
    let session = args.node.open(&formation_protocol::names::agent_name(first), &scenario).await?;
    tokio::spawn(crate::denials::report(
        session.clone(),
        formation_protocol::names::agent_name(first),
        Some(keys.run.clone()),
    ));
    let stall = Duration::from_secs_f64(args.stall_timeout);
    let quorum_wait = args.node.quorum_wait()?;
    let checkpoint_dir = args.checkpoint_dir.clone().unwrap_or_else(checkpoint::default_dir);
    let driven = scenario.ros2.is_some_and(|r| r.robots.driven());
    // One per follower: a signal sets them all, `formation leave` one.
    let leaves: Vec<Leave> = ids.iter().map(|_| Leave::default()).collect();
    let brakes: Vec<SharedTopics> = ids.iter().map(|_| Arc::new(Mutex::new(None))).collect();
    let _asked = listen_for_leave(&session, &scenario, &keys, ids, &leaves, &brakes, &args.node.clock).await?;
    let mut followers: futures_util::stream::FuturesUnordered<_> = ids
        .iter()
        .zip(&indices)
        .zip(&brakes)
        .zip(&leaves)
        .map(|(((&id, &index), brake), leave)| {
            let odometry = driven.then(|| Arc::new(OdomInbox::for_robot(&scenario, index, &args.node.clock)));
            let opts = FollowerOptions {
                protocol: follower::Options { stall_timeout: stall, physical_node_faults: args.physical_node_faults },
                checkpoint: Some(checkpoint::path(&checkpoint_dir, &keys.run, id)),
                odometry: odometry.clone(),
                on_zenoh_thread: ids.len() == 1,
                topics: brake.clone(),
                clock: args.node.clock.clone(),
                leave: leave.clone(),
                leave_at: leave_at.iter().find(|l| l.0 == id).map(|l| l.1),
                die_at: scenario.died(id).then(|| scenario.leave_step(id)).flatten(),
                even_if_cut_off: args.even_if_cut_off,
                quorum_wait,
                quiet: args.quiet,
            };
            let body: Box<dyn Body> = match odometry {
                Some(inbox) => Box::new(DrivenRobot::new(&scenario, index, inbox)),
                None => Box::new(SimFollower::new(&scenario, index)),
            };
            run_follower(&session, &scenario, &keys, index, body, opts)
        })
        .collect();
    // The first failure ends the process (its neighbours in here would only
    // wait for it); the others' ends are not waited for.
    let work = async {
        while let Some(r) = futures_util::StreamExt::next(&mut followers).await {
            r?;
        }
        Ok(())
    };
    tokio::pin!(work);
    let (result, signal) = tokio::select! {
        r = &mut work => (r, None),
        s = shutdown => {
            let why = match s {
                formation_exit::shutdown::Signal::Interrupt => "Ctrl-C",
                formation_exit::shutdown::Signal::Terminate => "SIGTERM",
            };
            // docs/ros2.md: a driven robot stops at once, not after the
            // leave below (a step and the last telemetry's acknowledgement);
            // its topics are taken, so no later step commands it again.
            if driven {
                stop_robots(&session, &scenario, ids, &brakes, why, &args.node.clock, true).await;
            }
            // Each follower leaves at its next step, tells the monitor in
            // its last batch, and ends (a bounded wait).
            leaves.iter().for_each(|l| _ = l.set(why));
            let r = tokio::time::timeout(LEAVE_WITHIN, &mut work).await.unwrap_or(Ok(()));
            (r, Some(s))
        }
    };
    drop(followers);
    if driven && signal.is_none() {
        // docs/ros2.md: an agent that ends stops its robot first.
        let why = if result.is_ok() { "the run ended" } else { "the agent stopped on an error" };
        stop_robots(&session, &scenario, ids, &brakes, why, &args.node.clock, false).await;
    }
    let close = if signal.is_some() { Duration::from_secs(1) } else { Duration::from_secs(5) };
    let _ = tokio::time::timeout(close, session.close()).await;
    result.map(|()| signal)
}

/// [`stop_robot`] for every follower of this process; `take`: and no later
/// step commands its robot again.
async fn stop_robots(
    session: &zenoh::Session,
    scenario: &Scenario,
    ids: &[u32],
    brakes: &[SharedTopics],
    why: &str,
    clock: &Clock,
    take: bool,
) {
    for (&id, brake) in ids.iter().zip(brakes) {
        stop_robot(session, scenario, id, brake, why, clock).await;
        if take {
            brake.lock().unwrap_or_else(|p| p.into_inner()).take();
        }
    }
}

/// Why a follower asked by `formation leave` leaves (its telemetry says so).
pub const ASKED_TO_LEAVE: &str = "formation leave";

/// `formation leave --id ID` for a follower of this process: it leaves the
/// run at its next step ([`FollowerMachine::handle_leave`]), and a robot driven
/// through ROS 2 is sent zero velocity at once.
async fn listen_for_leave(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    ids: &[u32],
    leaves: &[Leave],
    brakes: &[SharedTopics],
    clock: &crate::clock::Clock,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, Error> {
    let driven = scenario.ros2.is_some_and(|r| r.robots.driven());
    let mut subs = Vec::with_capacity(ids.len());
    for ((&id, leave), brake) in ids.iter().zip(leaves).zip(brakes) {
        let (leave, brake, s, sc, c) = (leave.clone(), brake.clone(), session.clone(), scenario.clone(), clock.clone());
        let sub = session
            .declare_subscriber(keys.leave(id))
            .callback(move |_| {
                if leave.set(ASKED_TO_LEAVE).is_ok() && driven {
                    let (s, sc, brake, c) = (s.clone(), sc.clone(), brake.clone(), c.clone());
                    tokio::spawn(async move {
                        stop_robot(&s, &sc, id, &brake, ASKED_TO_LEAVE, &c).await;
                        brake.lock().unwrap_or_else(|p| p.into_inner()).take();
                    });
                }
            })
            .await
            .map_err(|e| zerr("listening for formation leave", e))?;
        subs.push(sub);
    }
    Ok(subs)
}

/// Sends follower `id`'s robot zero velocity on its `cmd_vel` and says so:
/// through the agent's own publisher once the run began, else through one
/// declared for it (a start refused or interrupted: a robot left moving by
/// an earlier agent stops too).
async fn stop_robot(
    session: &zenoh::Session,
    scenario: &Scenario,
    id: u32,
    topics: &SharedTopics,
    why: &str,
    clock: &Clock,
) {
    let now_ns = clock.unix_ns() as i64;
    let sent = {
        let mut t = topics.lock().unwrap_or_else(|p| p.into_inner());
        t.as_mut().map(|t| t.stop(now_ns))
    };
    let sent = match sent {
        Some(r) => r,
        None => {
            let domain = scenario.ros2.map_or(0, |r| r.domain_id);
            let namespace = crate::ros2::follower_namespace(id);
            match RosNode::declare(session, domain, &namespace, "agent").await {
                Ok(node) => match node
                    .publisher::<formation_ros2::msgs::Twist>(
                        "cmd_vel",
                        crate::ros2::topics::QOS,
                        zenoh::qos::CongestionControl::Block,
                    )
                    .await
                {
                    Ok(mut p) => p.put(&formation_ros2::msgs::Twist::default(), now_ns),
                    Err(e) => Err(e),
                },
                Err(e) => Err(e),
            }
        }
    };
    match sent {
        Ok(()) => crate::node::say(&format!("follower {id}: {why}: sent its robot zero velocity")),
        Err(e) => crate::node::say(&format!("follower {id}: {why}: could not send its robot zero velocity: {e}")),
    }
}

/// How a follower process runs, beyond its scenario.
pub struct FollowerOptions {
    /// What the machine needs to know (stall timeout, physical faults).
    pub protocol: follower::Options,
    /// Where the robot's pose is checkpointed (real time), for a restart.
    pub checkpoint: Option<std::path::PathBuf>,
    /// The robot is driven through ROS 2: its odometry arrives here.
    pub odometry: Option<Arc<OdomInbox>>,
    /// Real time: run the loop as a task on zenoh's application thread
    /// (one follower in the process), not on a thread of its own (several,
    /// which one thread would serialise).
    pub on_zenoh_thread: bool,
    /// The follower's ROS 2 publishers once the run began: who ends the
    /// process sends the robot zero velocity through them.
    pub topics: SharedTopics,
    /// The node's clock.
    pub clock: Clock,
    /// Set when the process is told to stop (why: "SIGTERM", "Ctrl-C"):
    /// the follower leaves the run at its next step ([`FollowerMachine::handle_leave`]).
    pub leave: Leave,
    /// `--leave`: the step before which this follower leaves the run.
    pub leave_at: Option<u64>,
    /// Lock-step, the fault table's died row: the first step L whose
    /// estimate never comes; the process kills itself once every node
    /// holds what it sent before (Node::die).
    pub die_at: Option<u64>,
    /// `--even-if-cut-off`: its leave is not checked against those absent at the start.
    pub even_if_cut_off: bool,
    /// `--quorum-wait`: ready from then on without the neighbours not heard.
    pub quorum_wait: Option<Duration>,
    /// `--quiet`: no line of news.
    pub quiet: bool,
}

/// A process's request that its followers leave the run, and why.
pub type Leave = Arc<std::sync::OnceLock<&'static str>>;

/// How long a process told to stop waits for its followers to leave: their
/// last telemetry out and acknowledged (the monitor acknowledges every
/// 100 ms), and the robots stopped.
pub const LEAVE_WITHIN: Duration = Duration::from_secs(3);

/// The machine, shared by the subscriber callbacks and the loop's thread.
struct Shared {
    machine: crate::node::Shared<FollowerMachine>,
    /// Messages refused on arrival, counted without the machine's lock (a
    /// flood of garbage must not hold the loop); handed over each wake-up.
    refused: AtomicRejects,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, FollowerMachine> {
        self.machine.lock()
    }
}

/// In lock-step a follower the run started without (a quorum start) ends
/// here: it does not join later (a real-time one joins: see `rejoin`).
fn not_absent(id: u32, start: &Start, keys: &Keys, scenario: &Scenario) -> Result<(), Error> {
    if !start.absent.contains(&id) || scenario.timing == Timing::Realtime {
        return Ok(());
    }
    // docs/model.md §14: in lock-step every neighbour would have to agree,
    // before any of them passes it, on the step from which it waits for
    // the newcomer; real time needs no agreement.
    Err(Error::Run(format!(
        "follower {id}: run {} started without it (not ready within the leader's quorum wait); in lock-step a \
         follower absent at the start does not join later (in real time it joins at the step due)",
        keys.run
    )))
}

/// What the start may refuse for this follower: to be absent from it in
/// lock-step, and a leave that, with those absent, breaks Lemma 1.
fn may_start(id: u32, opts: &FollowerOptions, start: &Start, keys: &Keys, scenario: &Scenario) -> Result<(), Error> {
    not_absent(id, start, keys, scenario)?;
    own_leave_keeps_lemma_1(id, opts, start, scenario)
}

/// A follower that will leave (--leave, a leave row) checks Lemma 1 again
/// once the start says who is absent: with them out as well, its leave
/// must not cut a present follower off from the leader.
fn own_leave_keeps_lemma_1(id: u32, opts: &FollowerOptions, start: &Start, scenario: &Scenario) -> Result<(), Error> {
    let Some(k) = opts.leave_at.filter(|_| !opts.even_if_cut_off && !start.absent.is_empty()) else { return Ok(()) };
    let absent: Vec<(u32, Option<f64>)> = start.absent.iter().map(|&a| (a, None)).collect();
    let leave = [(id, k as f64 * scenario.dt_s)];
    match scenario.graph.cut_off_through(&absent, &leave, &[]) {
        None => Ok(()),
        Some(cut) => Err(Error::Input(format!(
            "follower {id}: {} with followers {} absent at the start: {cut}: not started (--even-if-cut-off \
             starts anyway)",
            leaves_named(&leave),
            formation_scenario::graph::id_list(&start.absent)
        ))),
    }
}

/// Starts the machine; the other followers absent from the start have
/// their links cut from step 0, as the model's node fault (docs/model.md
/// §14), until (real time) they join.
fn start_machine(
    m: &mut FollowerMachine,
    start: &Start,
    resume: Option<(u64, Pose)>,
    now: formation_protocol::Now,
    me: u32,
) {
    m.start(start, resume, now);
    for &gone in start.absent.iter().filter(|&&g| g != me) {
        m.handle_absent(gone);
    }
}

/// Runs the follower at `index` with `body` on an open session.
pub async fn run_follower(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    index: usize,
    body: Box<dyn Body>,
    opts: FollowerOptions,
) -> Result<(), Error> {
    let id = scenario.graph.id(index);
    // Nothing of this process goes out before it knows it has no twin.
    let claiming = startup::refuse_twin(session, keys, id, scenario.steps(), &opts.clock).await?;
    // The run's timebase is the leader's: ask it from now on.
    let timebase = Timebase::estimated(&opts.clock);
    // A clock known worse than a quarter step is said on stderr; in a
    // `launch`, the run's health sums up every follower's in one line
    // instead (a hundred agents on a busy host said it a hundred times).
    let quarter_step_ns = match std::env::var_os(crate::node::LAUNCHED_ENV) {
        Some(_) => f64::INFINITY,
        None => scenario.dt_s / barrier::positive_scale(scenario.network.time_scale) * 1e9 / 4.0,
    };
    let sync = clock_sync::follow(session.clone(), keys, timebase.clone(), format!("follower {id}"), quarter_step_ns);
    let mut machine = FollowerMachine::new(scenario, index, body, &opts.protocol);
    opts.leave_at.inspect(|&k| machine.schedule_leave(k));
    let sources = machine.source_ids().to_vec();
    let neighbours: Vec<u32> = sources.iter().copied().filter(|&s| s != wire::LEADER_ID).collect();
    let shared = Arc::new(Shared { machine: crate::node::Shared::new(machine), refused: Default::default() });
    // Subscribers first (the start barrier relies on it), one per source.
    let subscribers = subscribe(session, keys, &sources, &shared, &timebase).await?;
    let (pose_sub, pose_pub) = match scenario.control.guard.safety.is_some() {
        true => {
            let (s, p) = pose_channel(session, scenario, keys, id, &shared, &timebase).await?;
            (Some(s), Some(p))
        }
        false => (None, None),
    };
    // ROS 2: the topics go out once the run's epoch is known; a driven
    // robot's odometry is heard from now on.
    let topics: SharedTopics = opts.topics.clone();
    let (ros_node, odometry) = ros_side(session, scenario, id, &opts, &shared, &timebase).await?;
    let estimate_pub = crate::node::control_publisher(session, keys.estimate(id), scenario, "estimate").await?;

    let lockstep = scenario.timing == Timing::Lockstep;
    let Ends { done_subs, neighbours_done, token, deaths } =
        watch_ends(session, keys, scenario, id, &neighbours).await?;
    let needs = start_needs(scenario, index, &sources);
    let start =
        startup::wait_for_start(session, keys, &id.to_string(), &needs, scenario, &opts.clock, opts.quorum_wait)
            .await?;
    may_start(id, &opts, &start, keys, scenario)?;
    // Started: a later twin hears this follower's estimates from now on.
    drop(claiming);
    clock_sync::wait_for_estimate(&timebase, keys, &format!("follower {id}"), TIME_LIMIT).await?;
    let resume = rejoin(&shared, &start, scenario, index, &timebase, opts.checkpoint.as_deref()).await?;
    let latest: checkpoint::Latest = Arc::new(Mutex::new(None));
    let fingerprint = barrier::fingerprint(scenario);
    let checkpoint_path = opts.checkpoint.clone();
    let writer = opts.checkpoint.map(|p| checkpoint::start_writer(p, fingerprint, start.epoch_unix_ns, latest.clone()));
    if let Some(node) = &ros_node {
        let driven = opts.odometry.is_some();
        let t = FollowerTopics::declare(node, scenario, id, driven, start.epoch_unix_ns).await?;
        *topics.lock().unwrap_or_else(|p| p.into_inner()) = Some(t);
    }
    start_machine(&mut shared.lock(), &start, resume, timebase.now(), id);
    let watcher = watch_router(session, &shared, lockstep).await;
    // Telemetry leaves the loop through a bounded store and a thread of its
    // own, so a slow or dead link to the monitor never holds a step; it is
    // kept until the monitor acknowledges it.
    let (delivery, acks) = telemetry::start_delivery(session, keys, id, scenario, &opts.clock).await?;
    let node = Node {
        shared: shared.clone(),
        publisher: estimate_pub,
        pose_publisher: pose_pub,
        courier: delivery.courier.clone(),
        timebase: timebase.clone(),
        latest,
        neighbours_done,
        deaths,
        die_at: opts.die_at.filter(|_| lockstep),
        lockstep,
        incarnation: opts.clock.unix_ns(),
        topics: topics.clone(),
        leave: opts.leave.clone(),
        quiet: opts.quiet,
    };
    let outcome = if lockstep || !opts.on_zenoh_thread {
        tokio::task::spawn_blocking(move || node.drive()).await.map_err(|e| e.to_string())
    } else {
        crate::timer::on_zenoh_thread(node.drive_on_zenoh()).await
    }
    .map_err(|e| Error::Run(format!("follower {id}: control loop panicked: {e}")))?;
    telemetry::finish_delivery(delivery, &format!("follower {id}")).await;
    // Its token goes only once the monitor holds its last telemetry.
    drop(token);
    wind_up(id, outcome.is_ok(), writer, checkpoint_path.as_deref(), opts.odometry.as_deref());
    drop((acks, sync, subscribers, pose_sub, done_subs, odometry, ros_node));
    if let Some(w) = watcher {
        w.abort();
    }
    outcome.map_err(|e| Error::Run(format!("follower {id}: {e}")))
}

/// Lock-step: how a follower learns that its neighbours are through.
struct Ends {
    done_subs: Vec<zenoh::pubsub::Subscriber<()>>,
    /// Which neighbours completed the final step, left, or were killed.
    neighbours_done: telemetry::Ends,
    /// Its liveliness token, held while the process lives (crate::died).
    token: Option<zenoh::liveliness::LivelinessToken>,
    /// Followers killed without a word (crate::died).
    deaths: Option<crate::died::Watch>,
}

/// [`Ends`] for follower `id` of a lock-step run (nothing in real time).
async fn watch_ends(
    session: &zenoh::Session,
    keys: &formation_protocol::names::Keys,
    scenario: &Scenario,
    id: u32,
    neighbours: &[u32],
) -> Result<Ends, Error> {
    if scenario.timing != Timing::Lockstep {
        return Ok(Ends { done_subs: Vec::new(), neighbours_done: Default::default(), token: None, deaths: None });
    }
    let fingerprint = barrier::fingerprint(scenario);
    let (done_subs, neighbours_done) = telemetry::watch_done(session, keys, neighbours, scenario).await?;
    let token = Some(crate::died::declare_token(session, keys, id).await?);
    let deaths = Some(crate::died::Watch::start(session, keys, id, fingerprint).await?);
    Ok(Ends { done_subs, neighbours_done, token, deaths })
}

/// The fault table's died row, performed (lock-step, docs/model.md §14):
/// follower `id`'s process kills itself with SIGKILL, as a crash would end
/// it, with no last word; its estimate of step `l` never comes.
fn die(id: u32, l: u64) -> ! {
    crate::node::say(&format!(
        "follower {id}: killed before its estimate of step {l}, as the fault table's died row says (SIGKILL)"
    ));
    // SAFETY: raise has no preconditions; SIGKILL ends the process here.
    unsafe {
        libc::raise(libc::SIGKILL);
    }
    std::process::abort()
}

/// ROS 2 on: the agent's node `/follower_<id>/agent` and, for a driven
/// robot, its odometry subscription (heard from now on).
async fn ros_side(
    session: &zenoh::Session,
    scenario: &Scenario,
    id: u32,
    opts: &FollowerOptions,
    shared: &Arc<Shared>,
    timebase: &Timebase,
) -> Result<(Option<RosNode>, Option<RosSubscription>), Error> {
    let Some(r) = scenario.ros2 else { return Ok((None, None)) };
    let node = RosNode::declare(session, r.domain_id, &crate::ros2::follower_namespace(id), "agent").await?;
    let odometry = match &opts.odometry {
        Some(inbox) => Some(subscribe_odometry(&node, scenario, inbox.clone(), shared, &opts.topics, timebase).await?),
        None => None,
    };
    Ok((Some(node), odometry))
}

/// After the loop: the checkpoint writer stops (a run that ended has
/// nothing to rejoin: its checkpoint, which would only pile up in
/// $TMPDIR/formation-checkpoints, goes), and a driven robot's refused
/// odometry is said.
fn wind_up(
    id: u32,
    ended: bool,
    writer: Option<checkpoint::Writer>,
    checkpoint_path: Option<&std::path::Path>,
    odometry: Option<&OdomInbox>,
) {
    if let Some(w) = writer {
        w.stop();
        if let (true, Some(p)) = (ended, checkpoint_path) {
            let _ = std::fs::remove_file(p);
        }
    }
    if let Some(line) = odometry.and_then(|inbox| inbox.refused.summary()) {
        crate::node::say(&format!(
            "follower {id}: odometry refused on {}/odom: {line}",
            crate::ros2::follower_namespace(id)
        ));
    }
}

/// One subscriber per source, each handing what arrives to the machine.
async fn subscribe(
    session: &zenoh::Session,
    keys: &Keys,
    sources: &[u32],
    shared: &Arc<Shared>,
    timebase: &Timebase,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, Error> {
    let mut subscribers = Vec::new();
    let checker = shared.lock().checker();
    for &src in sources {
        let (shared, timebase, checker) = (shared.clone(), timebase.clone(), checker.clone());
        let sub = session
            .declare_subscriber(keys.estimate(src))
            .callback(move |sample| {
                let key_id = names::last_chunk(sample.key_expr().as_str()).parse::<u32>().ok();
                let bytes = sample.payload().to_bytes();
                // Checked, and the receipt read on the run's timebase, before the lock.
                let (source, msg) = match checker.check(key_id, &bytes) {
                    Ok(m) => m,
                    Err(r) => return shared.refused.add(r),
                };
                let at = timebase.now_ns().map(|ns| Duration::from_nanos(ns.max(0) as u64));
                let arrival = shared.lock().handle_checked(source, &msg, at);
                if let Some(sent_ns) = arrival.leader_sent_ns {
                    // The leader's own stamp: a floor for its clock (clockguard).
                    timebase.leader_sent(sent_ns);
                }
                if arrival.wake {
                    shared.machine.wake();
                }
            })
            .await
            .map_err(|e| zerr("declaring a subscriber", e))?;
        subscribers.push(sub);
    }
    Ok(subscribers)
}

/// Who the start waits to hear: every node this follower hears (its
/// sources, and with the safety filter every follower whose pose it takes).
fn start_needs(scenario: &Scenario, index: usize, sources: &[u32]) -> Vec<String> {
    let mut hears = sources.to_vec();
    hears.extend(scenario.peers_of(index).iter().map(|&j| scenario.graph.id(j)).filter(|j| !sources.contains(j)));
    hears.iter().map(u32::to_string).collect()
}

/// docs/model.md §16, the safety filter on: every other follower's pose
/// to the machine (this follower's own, heard back on the same key
/// expression, is skipped), and the publisher of its robot's.
async fn pose_channel(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    own: u32,
    shared: &Arc<Shared>,
    timebase: &Timebase,
) -> Result<(zenoh::pubsub::Subscriber<()>, Publisher<'static>), Error> {
    let (shared, timebase) = (shared.clone(), timebase.clone());
    let subscriber = session
        .declare_subscriber(keys.pose_all())
        .callback(move |sample| {
            let key_id = names::last_chunk(sample.key_expr().as_str()).parse::<u32>().ok();
            if key_id == Some(own) {
                return;
            }
            let bytes = sample.payload().to_bytes();
            let now = timebase.now();
            if shared.lock().handle_pose(key_id, &bytes, now).wake {
                shared.machine.wake();
            }
        })
        .await
        .map_err(|e| zerr("declaring the pose subscriber", e))?;
    let publisher = crate::node::control_publisher(session, keys.pose(own), scenario, "pose").await?;
    Ok((subscriber, publisher))
}

/// The follower's ROS 2 publishers, once the run's epoch is known.
pub type SharedTopics = Arc<Mutex<Option<FollowerTopics>>>;

/// A driven robot's odometry into `inbox`: a lock-step step's wakes the
/// loop; a repeat of the step before is answered with its command again.
async fn subscribe_odometry(
    node: &RosNode,
    scenario: &Scenario,
    inbox: Arc<OdomInbox>,
    shared: &Arc<Shared>,
    topics: &SharedTopics,
    timebase: &Timebase,
) -> Result<RosSubscription, Error> {
    let s = shared.clone();
    let wake = Arc::new(move || {
        // Under the lock, so that the loop cannot miss it between its check and its wait.
        drop(s.lock());
        s.machine.wake();
    });
    let t = topics.clone();
    let repeat = Arc::new(move |k: u64| {
        if let Some(topics) = t.lock().unwrap_or_else(|p| p.into_inner()).as_mut() {
            let _ = topics.repeat_command(k);
        }
    });
    // Lock-step odometry names its step by its stamp, k Δt.
    let stamps = Stamps::of(scenario, 0);
    driven::subscribe_odometry(node, scenario, inbox, stamps, timebase.clone(), wake, repeat).await
}

/// Where this process begins: None for a run only starting; a restart's
/// step and the pose its robot stopped at (the checkpoint's, or the
/// initial pose if there is none).
async fn rejoin(
    shared: &Shared,
    start: &Start,
    scenario: &Scenario,
    index: usize,
    timebase: &Timebase,
    checkpoint_path: Option<&std::path::Path>,
) -> Result<Option<(u64, Pose)>, Error> {
    let id = scenario.graph.id(index);
    let since_s = timebase.since_s(start.epoch_unix_ns as i64).unwrap_or(0.0);
    let first_step = match follower::joining(start, since_s, scenario, index).map_err(Error::Run)? {
        Joining::Fresh => 0,
        Joining::At(k) => k,
        Joining::ListenFirst(listen) => {
            tokio::time::sleep(listen).await;
            // A loaded host may deliver the neighbours' repeats late: listen
            // on in turns until every neighbour is heard, for at most
            // LISTEN_LIMIT of this node's own time awake (a neighbour gone
            // meanwhile is not waited for longer).
            let clock = timebase.clock();
            let mut patience = formation_protocol::patience::Patience::new(clock.mono(), LISTEN_TURN);
            while !shared.lock().lockstep_heard_every_neighbour() && patience.look(clock.mono()) < LISTEN_LIMIT {
                tokio::time::sleep(LISTEN_TURN).await;
            }
            shared.lock().lockstep_resume_step()
        }
    };
    if first_step == 0 {
        return Ok(None);
    }
    let at = |k: u64| k as f64 * scenario.dt_s;
    if start.absent.contains(&id) {
        // docs/model.md §14: a join, its robot where the scenario puts it.
        crate::node::say(&format!(
            "follower {id}: joining the running formation at t = {:.3} s (step {first_step}; absent at the start), \
             the robot at its initial pose",
            at(first_step)
        ));
        return Ok(Some((first_step, scenario.followers[index].pose)));
    }
    let found = checkpoint_path.map(|p| checkpoint::read(p, barrier::fingerprint(scenario), start.epoch_unix_ns));
    let pose = match found {
        Some(Ok(c)) => {
            crate::node::say(&format!(
                "follower {id}: rejoining the running formation at t = {:.3} s (step {first_step}), the robot \
                 stopped at the pose checkpointed at t = {:.3} s",
                at(first_step),
                at(c.k)
            ));
            c.pose()
        }
        Some(Err(why)) => {
            crate::node::say(&format!(
                "follower {id}: rejoining the running formation at t = {:.3} s (step {first_step}) from the \
                 initial pose: {why}",
                at(first_step)
            ));
            scenario.followers[index].pose
        }
        None => scenario.followers[index].pose,
    };
    Ok(Some((first_step, pose)))
}

/// Client mode, real time: tells the machine when the router goes and
/// comes back (for the timeline). A peer has no router, and no such events.
async fn watch_router(
    session: &zenoh::Session,
    shared: &Arc<Shared>,
    lockstep: bool,
) -> Option<tokio::task::JoinHandle<()>> {
    let has_router = session.info().routers_zid().await.next().is_some();
    if !has_router || lockstep {
        return None;
    }
    let (session, shared) = (session.clone(), shared.clone());
    Some(tokio::spawn(async move {
        let mut had = true;
        loop {
            tokio::time::sleep(Duration::from_millis(50)).await;
            let has = session.info().routers_zid().await.next().is_some();
            if has != had {
                had = has;
                shared.lock().handle_event(if has { EventKind::RouterBack } else { EventKind::RouterLost });
            }
        }
    }))
}

/// What a turn sends, kept between turns so that a step allocates no
/// vectors of its own.
#[derive(Default)]
struct Outbox {
    transmit: Vec<Vec<u8>>,
    poses: Vec<Vec<u8>>,
    batches: Vec<Batch>,
}

/// The loop's side of the node: the machine, and where its answers go.
struct Node {
    shared: Arc<Shared>,
    publisher: Publisher<'static>,
    /// The robot's pose (safety filter on).
    pose_publisher: Option<Publisher<'static>>,
    courier: Arc<Courier>,
    timebase: Timebase,
    /// The robot's latest pose, for the checkpoint writer.
    latest: checkpoint::Latest,
    /// Lock-step: neighbours that reported their final step.
    neighbours_done: telemetry::Ends,
    /// Lock-step: followers killed without a word (crate::died).
    deaths: Option<crate::died::Watch>,
    /// Lock-step, a died row: the step L its estimate never comes.
    die_at: Option<u64>,
    lockstep: bool,
    /// This process's start (ns since the Unix epoch), sent with telemetry.
    incarnation: u64,
    /// ROS 2 on: each step's topics.
    topics: SharedTopics,
    leave: Leave,
    quiet: bool,
}

impl Node {
    /// Feeds the machine the time until it is done, sleeping between turns
    /// until the machine's next deadline (real time) or until its step's
    /// inputs are in (lock-step): on a thread of its own.
    fn drive(self) -> Result<(), String> {
        let mut out = Outbox::default();
        loop {
            if let Some(r) = self.turn(&mut out) {
                return r;
            }
            self.sleep();
        }
    }

    /// The same in real time as a task on zenoh's application thread, the
    /// one that writes to the sockets: the estimate a turn publishes goes
    /// out in the same wake-up, instead of waking that thread from this
    /// one. Measured (60 agents, one process each, 100 Hz, this project's
    /// 2-core VM): docs/performance.md. Nothing in a turn waits on the
    /// network: estimates and topics are droppable, telemetry goes to the
    /// courier's thread. A turn holds zenoh's thread for its few
    /// microseconds; the subscriber callbacks, on the same thread, never
    /// wait for the machine's lock.
    async fn drive_on_zenoh(self) -> Result<(), String> {
        let timer = crate::timer::Timer::new().map_err(|e| format!("a timer for the loop: {e}"))?;
        let mut out = Outbox::default();
        loop {
            if let Some(r) = self.turn(&mut out) {
                return r;
            }
            match self.deadline() {
                Some(at) => {
                    timer.sleep_until(at, self.timebase.clock()).await.map_err(|e| format!("the loop's timer: {e}"))?
                }
                // Due already: let zenoh's tasks run before the next turn.
                None => tokio::task::yield_now().await,
            }
        }
    }

    /// One turn: the machine is told the time and what the node noticed,
    /// and what it answers goes out with its lock released. Some(outcome)
    /// once the machine is done.
    fn turn(&self, out: &mut Outbox) -> Option<Result<(), String>> {
        let mut m = self.shared.lock();
        let t = self.timebase.now();
        self.tell(&mut m);
        if let Some(l) = self.die_at {
            // Round L − 2 is out: it takes no step more, and dies once
            // every node holds that round.
            if m.step().is_some_and(|k| k + 1 >= l) {
                let held = m.heard_past(l.saturating_sub(1));
                let id = m.id();
                drop(m);
                if held {
                    die(id, l);
                }
                return None;
            }
        }
        m.handle_timeout(t);
        out.transmit.extend(std::iter::from_fn(|| m.poll_transmit()));
        out.poses.extend(std::iter::from_fn(|| m.poll_pose()));
        out.batches.extend(std::iter::from_fn(|| m.poll_telemetry()));
        let mut said: Vec<String> = std::iter::from_fn(|| m.poll_say()).collect();
        let news = std::iter::from_fn(|| m.poll_news());
        if self.quiet {
            news.for_each(drop);
        } else {
            said.extend(news);
        }
        let checkpoint = m.checkpoint();
        let outcome = m.outcome().cloned();
        let sample = m.take_sample();
        drop(m);
        if let Some(s) = sample {
            if let Some(t) = self.topics.lock().unwrap_or_else(|p| p.into_inner()).as_mut() {
                if let Err(e) = t.publish(&s) {
                    return Some(Err(e.to_string()));
                }
            }
        }
        for bytes in out.transmit.drain(..) {
            if let Err(e) = self.publisher.put(bytes).wait() {
                return Some(Err(zerr("publishing", e).to_string()));
            }
        }
        for bytes in out.poses.drain(..) {
            if let Some(Err(e)) = self.pose_publisher.as_ref().map(|p| p.put(bytes).wait()) {
                return Some(Err(zerr("publishing the pose", e).to_string()));
            }
        }
        for b in out.batches.drain(..) {
            self.send(b);
        }
        for line in said {
            crate::node::say(&line);
        }
        if checkpoint.is_some() {
            *self.latest.lock().unwrap_or_else(|p| p.into_inner()) = checkpoint;
        }
        outcome
    }

    /// What the node noticed that the machine cannot see: messages refused
    /// on arrival, a second clock on `control/time`, neighbours done (lock-step).
    fn tell(&self, m: &mut FollowerMachine) {
        if let Some(refused) = self.shared.refused.take() {
            m.handle_rejected(&refused);
        }
        if self.timebase.second_clock() {
            m.handle_event(EventKind::SecondClock);
        }
        if self.lockstep {
            for (&id, &end) in self.neighbours_done.lock().unwrap_or_else(|p| p.into_inner()).iter() {
                match end {
                    None => m.handle_done(id),
                    Some(k) => m.handle_gone(id, k),
                }
            }
        }
        if let Some(d) = &self.deaths {
            d.tell(m);
        }
        if let Some(why) = self.leave.get() {
            m.handle_leave(why);
        }
    }

    /// A telemetry batch to the courier, with how delivery goes and the
    /// node's estimate of the leader's clock.
    fn send(&self, b: Batch) {
        let (first_k, end_k) = (b.first_k, b.end_k);
        let delivery = Delivery {
            available_from: self.courier.available_from(first_k),
            incarnation: self.incarnation,
            courier: self.courier.stats(),
        };
        let t = b.into_telemetry(delivery, self.timebase.report());
        self.courier.push(first_k, end_k, codec::encode(&t));
    }

    /// The instant of the machine's next deadline in real time, on this
    /// node's monotonic clock; None if it is due already.
    fn deadline(&self) -> Option<std::time::Instant> {
        let at = self.shared.lock().poll_timeout()?;
        self.timebase.wake_instant(at)
    }

    /// Until the machine's next deadline: a precise sleep in real time; in
    /// lock-step a wait that the step's last input ends early.
    fn sleep(&self) {
        self.shared.machine.sleep(&self.timebase, self.lockstep, |m| m.poll_timeout());
    }
}

/// How long a node waits after the start for its first estimate of the
/// leader's clock.
const TIME_LIMIT: Duration = Duration::from_secs(5);

/// A lock-step restart listening for its neighbours' repeats: how often it
/// looks whether all were heard, and for how long at most.
const LISTEN_TURN: Duration = Duration::from_millis(100);
const LISTEN_LIMIT: Duration = Duration::from_secs(10);
