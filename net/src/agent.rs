//! One follower as a networked node (the `agent` binary).
//!
//! The follower's step is the simulator's ([`SimFollower::step`], behind the
//! [`Body`] seam), so a lock-step run gives the simulator's numbers bit for
//! bit; only who delivers the neighbours' messages differs. The node
//! subscribes only to its neighbours' estimate keys (and the leader's if
//! a_i0 = 1), publishes only docs/model.md §13's estimate message on its own key, and
//! sends telemetry for the monitor on a separate key.
//!
//! The control loop runs on its own OS thread (precise sleeps for the
//! real-time mode; condition-variable waits for lock-step), fed by zenoh
//! subscriber callbacks through a shared [`Inbox`]; start-up and shut-down
//! are async.

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use formation_agent::{Hearing, LeaderState, Message};
use formation_plant::Pose;
use formation_topology::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use formation_topology::{Scenario, Timing};
use zenoh::pubsub::Publisher;
use zenoh::Wait;

use crate::error::{zerr, Error};

use crate::barrier::{self, Start};
use crate::checkpoint;
use crate::clock;
use crate::codec;
use crate::counters::Counters;
use crate::courier::Courier;
use crate::gate::{self, Kept};
use crate::hearing::EarLog;
use crate::inbox::{self, Inbox, Source};
use crate::names::{self, Keys};
use crate::node::{estimate_congestion, NodeArgs};
use crate::startup;
use crate::telemetry::{self, EventKind, NetEvent, Telemetry};
use crate::timesync;
use crate::timing::Pacer;
use formation_record::hearing::Resume;
use formation_record::{FollowerSample, Heard};
use formation_sim::SimFollower;

/// The seam between the network node and the robot: one follower's step.
///
/// [`SimFollower`] (brain + simulated robot + noise) is the implementation
/// the simulator uses too. A real robot's driver implements this with the
/// same brain ([`formation_agent::Follower::step`]) fed by its own pose and
/// wheel-speed measurement, and applies the torques to the motors.
pub trait Body: Send {
    /// Step k at t = k Δt with the leader's state (if heard) and the
    /// neighbours' messages for k in ascending id; returns the step's
    /// telemetry sample and this follower's message for k + 1.
    fn step(
        &mut self,
        t_s: f64,
        dt_s: f64,
        leader: Option<&LeaderState>,
        neighbours: &[Message],
        last: bool,
    ) -> (FollowerSample, Message);
    /// The message for step 0.
    fn initial_message(&self) -> Message;
    /// The first quantity that is not finite, if any.
    fn check_finite(&self) -> Result<(), &'static str>;
    /// Consecutive steps without any source (docs/model.md §14's isolation).
    fn silent_steps(&self) -> u64;
    /// A restarted agent: go on from step `k`, the robot stopped at `pose`,
    /// with a fresh brain that adopts its estimate (docs/model.md §14).
    fn resume(&mut self, k: u64, pose: Pose);
    /// Waiting for a first source to adopt an estimate from.
    fn adopting(&self) -> bool;
}

impl Body for SimFollower {
    fn step(
        &mut self,
        t_s: f64,
        dt_s: f64,
        leader: Option<&LeaderState>,
        neighbours: &[Message],
        last: bool,
    ) -> (FollowerSample, Message) {
        SimFollower::step(self, t_s, dt_s, leader, neighbours, last)
    }
    fn initial_message(&self) -> Message {
        self.brain.tagged_message()
    }
    fn check_finite(&self) -> Result<(), &'static str> {
        SimFollower::check_finite(self)
    }
    fn silent_steps(&self) -> u64 {
        self.brain.silent_steps()
    }
    fn resume(&mut self, k: u64, pose: Pose) {
        SimFollower::resume(self, k, pose);
    }
    fn adopting(&self) -> bool {
        self.brain.adopting()
    }
}

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
}

/// Inbox shared between the subscriber callbacks and the control thread.
pub(crate) struct Shared {
    pub inbox: Mutex<Inbox>,
    pub arrived: Condvar,
    /// Network events noticed outside the loop (the router watcher), for the next telemetry batch.
    pub events: Mutex<Vec<NetEvent>>,
}

/// Runs the follower(s) of `--id` to the end of the scenario.
pub async fn run(args: &AgentArgs) -> Result<(), Error> {
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
    let (scenario, keys) = args.node.load(&crate::names::agent_name(first))?;
    let mut indices = Vec::with_capacity(ids.len());
    for &id in ids {
        indices.push(scenario.index_of(id).ok_or_else(|| {
            let all: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
            Error::Input(format!("scenario {} has no follower {id} (ids: {})", scenario.name, all.join(", ")))
        })?);
    }
    if !args.stall_timeout.is_finite() || args.stall_timeout <= 0.0 {
        return Err(Error::Input("--stall-timeout must be positive".into()));
    }
    let session = args.node.open(&crate::names::agent_name(first), &scenario).await?;
    tokio::spawn(crate::denials::report(session.clone(), crate::names::agent_name(first), Some(keys.run.clone())));
    let stall = Duration::from_secs_f64(args.stall_timeout);
    let checkpoint_dir = args.checkpoint_dir.clone().unwrap_or_else(checkpoint::default_dir);
    let mut followers: futures_util::stream::FuturesUnordered<_> = ids
        .iter()
        .zip(&indices)
        .map(|(&id, &index)| {
            let opts = FollowerOptions {
                stall_timeout: stall,
                physical_node_faults: args.physical_node_faults,
                checkpoint: Some(checkpoint::path(&checkpoint_dir, &keys.run, id)),
            };
            let body = Box::new(SimFollower::new(&scenario, index));
            run_follower(&session, &scenario, &keys, index, body, opts)
        })
        .collect();
    // The first failure ends the process (its neighbours in here would only
    // wait for it); the others' ends are not waited for.
    let mut result = Ok(());
    while let Some(r) = futures_util::StreamExt::next(&mut followers).await {
        if r.is_err() {
            result = r;
            break;
        }
    }
    drop(followers);
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    result
}

/// How a follower process runs, beyond its scenario.
pub struct FollowerOptions {
    /// Lock-step: give up when inputs stop arriving for this long.
    pub stall_timeout: Duration,
    /// The network performs the fault table's `node` rows (the lab).
    pub physical_node_faults: bool,
    /// Where the robot's pose is checkpointed (real time), for a restart.
    pub checkpoint: Option<std::path::PathBuf>,
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
    let FollowerOptions { stall_timeout, physical_node_faults, checkpoint } = opts;
    let mut body = body;
    let id = scenario.graph.id(index);
    // Nothing of this process goes out before it knows it has no twin.
    startup::refuse_twin(session, keys, id, scenario.steps()).await?;
    // The run's timebase is the leader's: ask it from now on.
    let timebase = clock::Timebase::estimated();
    let quarter_step_ns = scenario.dt_s / barrier::positive_scale(scenario.network.time_scale) * 1e9 / 4.0;
    let sync = timesync::follow(session.clone(), keys, timebase.clone(), format!("follower {id}"), quarter_step_ns);
    let hears_leader = scenario.graph.hears_leader(index);
    let neighbour_ids: Vec<u32> = scenario.graph.neighbours(index).iter().map(|&j| scenario.graph.id(j)).collect();
    let lockstep = scenario.timing == Timing::Lockstep;
    let slots = neighbour_ids.len() + usize::from(hears_leader);
    let mut inbox = Inbox::new(slots, lockstep);
    // docs/model.md §14: the fault table applies at the receiver, per incoming link.
    let mut table = scenario.clone();
    if physical_node_faults {
        table.faults.retain(|f| !matches!(f.target, formation_topology::FaultTarget::Node(_)));
    }
    inbox.set_links(scenario.sources_of(index).iter().map(|&src| table.link_loss(src, id)).collect());
    // Before any message can arrive (the leader may run ahead before this node hears the start).
    set_window(&mut inbox, scenario, slots, hears_leader, scenario.network.time_scale);
    let shared = Arc::new(Shared { inbox: Mutex::new(inbox), arrived: Condvar::new(), events: Mutex::new(Vec::new()) });

    // Subscribers first (the start barrier relies on it), one per source.
    let mut sources: Vec<u32> = neighbour_ids.clone();
    if hears_leader {
        sources.push(wire::LEADER_ID);
    }
    let mut subscribers = Vec::new();
    for &src in &sources {
        let shared = shared.clone();
        let neighbour_ids = neighbour_ids.clone();
        let n = neighbour_ids.len();
        let timebase = timebase.clone();
        let sub = session
            .declare_subscriber(keys.estimate(src))
            .callback(move |sample| {
                let key_id = names::last_chunk(sample.key_expr().as_str()).parse::<u32>().ok();
                let bytes = sample.payload().to_bytes();
                // The receipt, on the run's timebase (read before the inbox is locked).
                let now = timebase.now_ns();
                let mut inbox = shared.inbox.lock().unwrap_or_else(|p| p.into_inner());
                match inbox::check(key_id, &bytes, hears_leader, &neighbour_ids) {
                    Ok((source, msg)) => {
                        let slot = if let Source::Neighbour(slot) = source { slot } else { n };
                        if slot == n {
                            // The leader's own stamp: a floor for its clock (clockguard).
                            timebase.leader_sent(msg.header.sent_ns);
                        }
                        if let (true, Some(now)) = (inbox.accept(slot, &msg), now) {
                            inbox.note_latency(slot, msg.header.sent_ns, now);
                        }
                    }
                    Err(r) => inbox.reject(r),
                }
                // Wake the control loop only when its step is complete: one
                // wake-up per step instead of one per message.
                let wake = inbox.completes_wait();
                drop(inbox);
                if wake {
                    shared.arrived.notify_all();
                }
            })
            .await
            .map_err(|e| zerr("declaring a subscriber", e))?;
        subscribers.push(sub);
    }
    let estimate_pub = session
        .declare_publisher(keys.estimate(id))
        .congestion_control(estimate_congestion(scenario))
        .priority(crate::node::priority::ESTIMATE)
        .express(crate::node::estimate_express(scenario))
        .await
        .map_err(|e| zerr("declaring the estimate publisher", e))?;

    // Lock-step: which neighbours have completed the final step (see the end of control_loop).
    let (done_subs, neighbours_done) = if lockstep {
        telemetry::watch_done(session, keys, &neighbour_ids, scenario.steps()).await?
    } else {
        (Vec::new(), Default::default())
    };
    let mut needs: Vec<String> = neighbour_ids.iter().map(u32::to_string).collect();
    if hears_leader {
        needs.push(wire::LEADER_ID.to_string());
    }
    let fingerprint = barrier::fingerprint(scenario);
    let start = startup::wait_for_start(session, keys, &id.to_string(), &needs, scenario).await?;
    timesync::wait_for_estimate(&timebase, keys, &format!("follower {id}"), TIME_LIMIT).await?;
    let epoch_ns = start.epoch_unix_ns as i64;
    // A run that began a while ago: this process is a restart (docs/model.md §14).
    let late = timebase.since_s(epoch_ns).is_some_and(|s| s > LATE.as_secs_f64());
    let first_step = if lockstep {
        if late {
            lockstep_rejoin_step(&shared, neighbour_ids.len()).await?
        } else {
            0
        }
    } else {
        rejoin_step(&start, scenario, &timebase)?
    };
    let mut resumed = None;
    if first_step > 0 {
        let found = checkpoint.as_deref().map(|p| checkpoint::read(p, fingerprint, start.epoch_unix_ns));
        let pose = match found {
            Some(Ok(c)) => {
                eprintln!(
                    "follower {id}: rejoining the running formation at t = {:.3} s (step {first_step}), the robot \
                     stopped at the pose checkpointed at t = {:.3} s",
                    first_step as f64 * scenario.dt_s,
                    c.k as f64 * scenario.dt_s
                );
                c.pose()
            }
            Some(Err(why)) => {
                eprintln!(
                    "follower {id}: rejoining the running formation at t = {:.3} s (step {first_step}) from the \
                     initial pose: {why}",
                    first_step as f64 * scenario.dt_s
                );
                scenario.followers[index].pose
            }
            None => scenario.followers[index].pose,
        };
        body.resume(first_step, pose);
        resumed = Some(Resume { k: first_step, pose: [pose.x, pose.y, pose.theta] });
    }
    let latest: checkpoint::Latest = Arc::new(Mutex::new(None));
    let writer = checkpoint.map(|p| checkpoint::start_writer(p, fingerprint, start.epoch_unix_ns, latest.clone()));
    if !lockstep {
        // The shared clock bounds how far ahead a genuine message can be.
        let mut inbox = shared.inbox.lock().unwrap_or_else(|p| p.into_inner());
        let scale = start.scale();
        set_window(&mut inbox, scenario, slots, hears_leader, scale);
        let epoch = timebase.instant_at(epoch_ns).unwrap_or_else(Instant::now);
        inbox.set_clock(epoch, Duration::from_secs_f64(scenario.dt_s / scale));
    }
    let loop_ctx = LoopCtx {
        id,
        steps: scenario.steps(),
        dt_s: scenario.dt_s,
        batch: scenario.network.telemetry_batch.max(1) as usize,
        lockstep,
        has_leader: hears_leader,
        neighbours: neighbour_ids.len(),
        silence_steps: scenario.silence_steps(),
        delay_steps: scenario.network.delay_steps,
        rejoin_after_steps: scenario.control.rejoin.after_steps,
        first_step,
        resumed,
        hearing_record: scenario.network.hearing_record,
        latest,
        start,
        timebase: timebase.clone(),
        stall_timeout,
        incarnation: clock::unix_ns(),
        neighbours_done,
        source_ids: sources.clone(),
        source_names: sources
            .iter()
            .map(|&s| if s == wire::LEADER_ID { "the leader".to_string() } else { format!("follower {s}") })
            .collect(),
    };
    // Client mode, real time: note when the router goes and comes back (for
    // the timeline). A peer has no router, and no such events.
    let has_router = session.info().routers_zid().await.next().is_some();
    let watcher = (has_router && !lockstep).then(|| {
        let session = session.clone();
        let shared = shared.clone();
        let epoch = timebase.instant_at(epoch_ns).unwrap_or_else(Instant::now);
        let step = Duration::from_secs_f64(scenario.dt_s / start.scale());
        tokio::spawn(async move {
            let mut had = true;
            loop {
                tokio::time::sleep(Duration::from_millis(50)).await;
                let has = session.info().routers_zid().await.next().is_some();
                if has != had {
                    had = has;
                    let k = (epoch.elapsed().as_secs_f64() / step.as_secs_f64()) as u64;
                    let what = if has { EventKind::RouterBack } else { EventKind::RouterLost };
                    shared.events.lock().unwrap_or_else(|p| p.into_inner()).push(NetEvent { k, what });
                }
            }
        })
    });
    // Telemetry leaves the loop through a bounded store and a thread of its
    // own, so a slow or dead link to the monitor never holds a step; it is
    // kept until the monitor acknowledges it.
    let (delivery, acks) = telemetry::start_delivery(session, keys, id, scenario).await?;
    let courier = delivery.courier.clone();
    let outcome = tokio::task::spawn_blocking(move || control_loop(loop_ctx, body, &shared, &estimate_pub, &courier))
        .await
        .map_err(|e| Error::Run(format!("follower {id}: control loop panicked: {e}")))?;
    telemetry::finish_delivery(delivery, &format!("follower {id}")).await;
    if let Some(w) = writer {
        w.stop();
    }
    drop(acks);
    drop(sync);
    if let Some(w) = watcher {
        w.abort();
    }
    drop(subscribers);
    drop(done_subs);
    outcome.map_err(|e| Error::Run(format!("follower {id}: {e}")))
}

/// How far ahead of this node's step a genuine message can be (further:
/// `Reject::Future`). Lock-step: neighbours 2 steps, the leader (last slot)
/// its window + 2. Real time: 0.1 s of wall time (at least
/// [`crate::inbox::REALTIME_AHEAD`] steps) beyond the shared clock's step.
fn set_window(inbox: &mut Inbox, scenario: &Scenario, slots: usize, hears_leader: bool, time_scale: f64) {
    if scenario.timing == Timing::Lockstep {
        // A fault lets a node run ahead of a receiver that does not wait for
        // it (an isolated follower runs freely through its window), by at
        // most the longest window plus one step per hop of the graph.
        let faulted = scenario.faults.iter().map(|f| {
            let (a, b) = f.steps(scenario.dt_s);
            b - a + scenario.followers.len() as u64
        });
        let ahead = faulted.max().map_or(inbox::LOCKSTEP_AHEAD, |w| w + inbox::LOCKSTEP_AHEAD);
        for slot in 0..slots {
            inbox.set_ahead(slot, ahead);
        }
        if hears_leader {
            inbox.set_ahead(slots - 1, ahead + gate::WINDOW);
        }
    } else {
        let period = scenario.dt_s / barrier::positive_scale(time_scale);
        let slack = ((0.1 / period).ceil() as u64).max(inbox::REALTIME_AHEAD);
        for slot in 0..slots {
            inbox.set_ahead(slot, slack);
        }
    }
}

struct LoopCtx {
    id: u32,
    steps: u64,
    dt_s: f64,
    batch: usize,
    lockstep: bool,
    has_leader: bool,
    neighbours: usize,
    silence_steps: u64,
    /// Real time: step k uses the newest messages stamped at or before k − d.
    delay_steps: u64,
    /// `network.rejoin_after` in steps (docs/model.md §14).
    rejoin_after_steps: u64,
    /// The first step this process computes (> 0: a restart).
    first_step: u64,
    /// A restart: where it resumed (the hearing record's).
    resumed: Option<Resume>,
    /// `network.hearing_record`.
    hearing_record: bool,
    /// The robot's latest pose, for the checkpoint writer.
    latest: checkpoint::Latest,
    start: Start,
    /// The run's timebase as this node knows it (real-time pacing).
    timebase: clock::Timebase,
    stall_timeout: Duration,
    /// This process's start (ns since the Unix epoch), sent with telemetry.
    incarnation: u64,
    /// Lock-step: neighbours that reported their final step.
    neighbours_done: Arc<Mutex<std::collections::BTreeSet<u32>>>,
    /// "follower 2", …, "the leader", by inbox slot.
    source_names: Vec<String>,
    /// The sources' ids (0: the leader), by inbox slot.
    source_ids: Vec<u32>,
}

fn put(p: &Publisher<'_>, bytes: &[u8]) -> Result<(), Error> {
    p.put(bytes.to_vec()).wait().map_err(|e| zerr("publishing", e))
}

/// Real time: the step a process that hears the start `start` should begin
/// at. 0 for a run that has not begun (or began less than [`LATE`] ago);
/// otherwise a restart, which resumes [`LATE`] ahead of the run's current
/// step (time to set up before that step is due).
fn rejoin_step(start: &Start, scenario: &Scenario, timebase: &clock::Timebase) -> Result<u64, Error> {
    let since = timebase.since_s(start.epoch_unix_ns as i64).unwrap_or(0.0).max(0.0);
    let elapsed_s = since * start.scale();
    if elapsed_s < LATE.as_secs_f64() {
        return Ok(0);
    }
    let k = ((elapsed_s + LATE.as_secs_f64()) / scenario.dt_s).ceil() as u64;
    if k >= scenario.steps() {
        return Err(Error::Run(format!(
            "run {} began {elapsed_s:.1} s ago and is over (T = {} s): nothing to rejoin",
            scenario.name, scenario.duration_s
        )));
    }
    Ok(k)
}

/// Lock-step: where a restarted process resumes. Its neighbours, waiting
/// for its message of the step they are at, repeat their last `gate::REPEATED`
/// messages every 100 ms; a process that hears them well past step 0 is a restart
/// and resumes one step before the least advanced of them (it adopts from
/// their messages of that step and publishes the message they wait for).
/// 0 for a run that is only starting.
async fn lockstep_rejoin_step(shared: &Shared, neighbours: usize) -> Result<u64, Error> {
    if neighbours == 0 {
        return Ok(0);
    }
    tokio::time::sleep(LATE + Duration::from_millis(100)).await;
    let heard: Vec<Option<u64>> = {
        let inbox = shared.inbox.lock().unwrap_or_else(|p| p.into_inner());
        (0..neighbours).map(|slot| inbox.heard_max(slot)).collect()
    };
    Ok(gate::resume_step(&heard))
}

/// How long a node waits after the start for its first estimate of the
/// leader's clock.
const TIME_LIMIT: Duration = Duration::from_secs(5);

/// A process that hears a start older than this is a restart.
const LATE: Duration = Duration::from_millis(200);

/// Per inbox slot, whether the source is heard now (real time).
struct HeardNow(Vec<bool>);

impl HeardNow {
    /// Records a change of whether `slot` is heard at step k.
    fn note(&mut self, slot: usize, k: u64, now: bool, ids: &[u32], events: &mut Vec<NetEvent>) {
        if self.0[slot] != now {
            self.0[slot] = now;
            let what = if now { EventKind::Heard(ids[slot]) } else { EventKind::Silent(ids[slot]) };
            events.push(NetEvent { k, what });
        }
    }
}

fn control_loop(
    c: LoopCtx,
    mut body: Box<dyn Body>,
    shared: &Shared,
    estimate_pub: &Publisher<'_>,
    telemetry: &Courier,
) -> Result<(), Error> {
    let msg = |k: u64, m: Message| EstimateMsg {
        header: Header {
            version: FORMAT_VERSION,
            sender: c.id,
            step: k,
            time_s: k as f64 * c.dt_s,
            sent_ns: c.timebase.now_ns().unwrap_or(0),
        },
        state: m.state,
        fresh: m.fresh,
    };
    let mut sent = 0u64;
    let mut republished = 0u64;
    // The messages published, oldest first, the last KEPT of them
    // (republished while waiting). A restart publishes nothing until it has
    // adopted an estimate.
    let mut recent = Kept::new(gate::FOLLOWER_KEPT);
    if c.first_step == 0 {
        let first = wire::encode(&msg(0, body.initial_message()));
        put(estimate_pub, &first)?;
        sent += 1;
        recent.push(0, first);
    }

    let mut pacer = (!c.lockstep).then(|| Pacer::new(&c.start, c.dt_s, c.timebase.clone()));
    let mut inputs: Vec<Message> = Vec::with_capacity(c.neighbours + 1);
    // Lock-step: each source's step-k message (None: removed by the fault
    // table), and the newest delivered one per source (docs/model.md §14).
    let mut taken: Vec<Option<Message>> = Vec::with_capacity(c.neighbours + 1);
    let mut hearing = Hearing::new(c.neighbours + usize::from(c.has_leader), c.silence_steps);
    // Real time: who is heard, for the timeline.
    let mut heard = HeardNow(vec![false; c.neighbours + usize::from(c.has_leader)]);
    let mut events: Vec<NetEvent> = Vec::new();
    let mut second_clock_named = false;
    let mut batch: Vec<FollowerSample> = Vec::with_capacity(c.batch);
    // The hearing record of the batch's steps.
    let slots = c.neighbours + usize::from(c.has_leader);
    let mut ear =
        if c.hearing_record { EarLog::new(c.source_ids.clone(), RESCUE_BATCHES * c.batch) } else { EarLog::off() };
    let mut first_k = c.first_step;
    for k in c.first_step..=c.steps {
        let last = k == c.steps;
        let t = k as f64 * c.dt_s;
        if let Some(p) = pacer.as_mut() {
            p.wait(k);
        }
        // The inputs of step k: neighbours in ascending id, and the leader.
        let leader = {
            let mut inbox = shared.inbox.lock().unwrap_or_else(|p| p.into_inner());
            inbox.set_step(k);
            if c.lockstep {
                let mut wait = gate::Wait::new(Instant::now(), gate::FOLLOWER_REPEAT_EVERY, c.stall_timeout);
                while !inbox.has_all(k) {
                    // Woken by every message that arrives (others' repeats included).
                    let (g, _) = shared
                        .arrived
                        .wait_timeout(inbox, gate::FOLLOWER_REPEAT_EVERY)
                        .unwrap_or_else(|p| p.into_inner());
                    inbox = g;
                    if inbox.has_all(k) {
                        break;
                    }
                    let now = Instant::now();
                    let mut missing = || {
                        let names: Vec<&str> = inbox.missing(k).iter().map(|&s| c.source_names[s].as_str()).collect();
                        (names.join(" and "), names.len())
                    };
                    let gate::WaitStep::Wait { repeat, warn } = wait.poll(now) else {
                        let (names, n) = missing();
                        return Err(Error::Run(format!(
                            "{names} stopped answering: no input for step {k} from {} for {:.0} s (stall timeout; a \
                             process that is down, or a link that does not carry its messages)",
                            if n == 1 { "it" } else { "them" },
                            c.stall_timeout.as_secs_f64()
                        )));
                    };
                    if warn {
                        crate::node::say(&format!(
                            "follower {}: waiting {:.0} s for step {k} from {} (stall timeout {:.0} s); repeating its \
                             last messages meanwhile",
                            c.id,
                            wait.waited(now).as_secs_f64(),
                            missing().0,
                            c.stall_timeout.as_secs_f64()
                        ));
                    }
                    if repeat {
                        // A sender that keeps us waiting may be gone, with its
                        // last telemetry: its messages we used go to the
                        // monitor (once: the rescue empties what was kept).
                        for s in inbox.missing(k) {
                            ear.rescue(s);
                        }
                        // Safety net for messages lost on the way: say again
                        // what the neighbours still need.
                        let slowest = inbox.slowest_heard(c.neighbours);
                        drop(inbox);
                        for bytes in recent.follower_repeats(slowest) {
                            put(estimate_pub, bytes)?;
                            sent += 1;
                            republished += 1;
                        }
                        inbox = shared.inbox.lock().unwrap_or_else(|p| p.into_inner());
                    }
                }
                // Slots 0..n are the neighbours, slot n the leader.
                inbox.take(k, &mut taken);
                for (slot, m) in taken.iter().enumerate() {
                    if let Some(m) = m {
                        hearing.deliver(slot, k, *m);
                    }
                }
                for slot in 0..slots {
                    let used = hearing.heard_at(slot, k);
                    let h = match used {
                        Some((s, _)) => Heard::used(k, s),
                        None if taken[slot].is_none() => Heard::Removed,
                        None => Heard::Silent,
                    };
                    ear.note(slot, h, used);
                }
                ear.end_step();
                inputs.clear();
                inputs.extend((0..c.neighbours).filter_map(|slot| hearing.heard(slot, k)).copied());
                if c.has_leader {
                    hearing.heard(c.neighbours, k).map(|m| m.state)
                } else {
                    None
                }
            } else {
                // Latest values as of step k − d (network.delay_steps); a
                // source silent too long is left out.
                inputs.clear();
                let sent_k = k.saturating_sub(c.delay_steps);
                let mut leader = None;
                for slot in 0..slots {
                    let s = inbox.latest(slot, sent_k, c.silence_steps);
                    heard.note(slot, k, s.is_some(), &c.source_ids, &mut events);
                    let h = match s {
                        Some((stamp, _)) => Heard::used(k, stamp),
                        None if inbox.removed(slot, sent_k) => Heard::Removed,
                        None => Heard::Silent,
                    };
                    ear.note(slot, h, s.as_ref().map(|(stamp, m)| (*stamp, m)));
                    match s {
                        Some((_, m)) if slot < c.neighbours => inputs.push(m),
                        Some((_, m)) => leader = Some(m.state),
                        None => {}
                    }
                }
                ear.end_step();
                leader
            }
        };
        let was_silent = body.silent_steps();
        let (sample, next) = body.step(t, c.dt_s, leader.as_ref(), &inputs, last);
        match body.silent_steps() {
            s if s == c.rejoin_after_steps => events.push(NetEvent { k, what: EventKind::Isolated }),
            0 if was_silent >= c.rejoin_after_steps => events.push(NetEvent { k, what: EventKind::Rejoined }),
            _ => {}
        }

        // Publish the message for k + 1 at once, then telemetry.
        batch.push(sample);
        let diverged = body.check_finite().err();
        if k % 10 == 0 {
            *c.latest.lock().unwrap_or_else(|p| p.into_inner()) = Some((k, sample.pose));
        }
        // Real time: an isolated follower keeps its dead-reckoned estimate to
        // itself until it hears a source again. In the model its links are
        // down both ways; a real link comes back one way first, and when its
        // neighbours heard it one step before it heard them, their estimates
        // were pulled twice as far (lab, follower 3 cut off 8–11 s: 0.033 m
        // against the simulator's 0.018; see docs/decisions.md).
        let silent = body.silent_steps();
        let isolated = !c.lockstep && silent > 0 && silent >= c.rejoin_after_steps;
        if !last && diverged.is_none() && !body.adopting() && !isolated {
            let bytes = wire::encode(&msg(k + 1, next));
            put(estimate_pub, &bytes)?;
            sent += 1;
            recent.push(k + 1, bytes);
        }
        if batch.len() >= c.batch || last || diverged.is_some() {
            // A second clock on control/time, once, at the step it was noticed.
            if !second_clock_named && c.timebase.second_clock() {
                second_clock_named = true;
                events.push(NetEvent { k, what: EventKind::SecondClock });
            }
            let (mut counters, links): (Counters, _) = {
                let inbox = shared.inbox.lock().unwrap_or_else(|p| p.into_inner());
                (inbox.counters, inbox.link_stats(&c.source_ids))
            };
            counters.sent = sent;
            counters.republished = republished;
            let done = last || diverged.is_some();
            if done {
                // A source that dies near the end never falls silent here:
                // what this follower used of each goes out with its last batch.
                for slot in 0..slots {
                    ear.rescue(slot);
                }
            }
            let (heard, rescued) = ear.take();
            let t = Telemetry::Follower {
                id: c.id,
                first_k,
                samples: std::mem::take(&mut batch),
                counters,
                done,
                loop_stats: if done { pacer.as_ref().map(Pacer::stats) } else { None },
                delivery: telemetry::Delivery {
                    available_from: telemetry.available_from(first_k),
                    incarnation: c.incarnation,
                    courier: telemetry.stats(),
                },
                events: {
                    let mut outside = shared.events.lock().unwrap_or_else(|p| p.into_inner());
                    events.append(&mut outside);
                    events.sort_unstable();
                    std::mem::take(&mut events)
                },
                clock: c.timebase.report(),
                links,
                heard,
                rescued,
                resumed: c.resumed,
                diverged: diverged.map(str::to_string),
            };
            telemetry.push(first_k, k + 1, codec::encode(&t));
            first_k = k + 1;
        }
        if let Some(q) = diverged {
            return Err(Error::Run(format!("{q} is not finite at step {k} (t = {t} s); the run diverged")));
        }
    }
    if c.lockstep {
        // A neighbour may still wait for our final message (lost?): say it
        // again until every neighbour reports its final step, for at most LINGER.
        let mut linger = gate::Wait::new(Instant::now(), gate::LINGER_REPEAT_EVERY, LINGER);
        while let gate::WaitStep::Wait { repeat, .. } = linger.poll(Instant::now()) {
            if shared_len(&c.neighbours_done) >= c.neighbours {
                break;
            }
            if repeat {
                let slowest = shared.inbox.lock().unwrap_or_else(|p| p.into_inner()).slowest_heard(c.neighbours);
                for bytes in recent.follower_repeats(slowest) {
                    put(estimate_pub, bytes)?;
                }
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    Ok(())
}

/// How many telemetry batches' worth of each source's last messages a
/// follower keeps for a rescue ([`EarLog`]): more than a killed sender can
/// have left unacknowledged (one batch being filled, one or two in flight).
const RESCUE_BATCHES: usize = 4;

/// Lock-step: how long a follower keeps republishing its final message after its last step.
const LINGER: Duration = Duration::from_secs(1);

fn shared_len(s: &Mutex<std::collections::BTreeSet<u32>>) -> usize {
    s.lock().unwrap_or_else(|p| p.into_inner()).len()
}
