//! One follower of the formation as one machine (quinn-proto's `Connection`
//! is the model): it owns the inbox, the lock-step gate, the real-time
//! pacing on the run's timebase, the freshness and silence rules, the
//! hearing record, the publish rule and what goes to telemetry. It is fed
//! the messages that arrive ([`FollowerMachine::handle_estimate`]), what the node
//! noticed ([`FollowerMachine::handle_event`], [`FollowerMachine::handle_done`]) and the
//! time ([`FollowerMachine::handle_timeout`]); it answers what to publish
//! ([`FollowerMachine::poll_transmit`]), what to send to the monitor
//! ([`FollowerMachine::poll_telemetry`]), what to say on stderr
//! ([`FollowerMachine::poll_say`]) and when to be woken ([`FollowerMachine::poll_timeout`]).
//!
//! The follower's step itself is the simulator's ([`SimFollower::step`],
//! behind the [`Body`] seam), so a lock-step run gives the simulator's
//! numbers bit for bit; only who delivers the neighbours' messages differs.
//!
//! Time ([`Now`]) is the run's timebase (the leader's clock) as the node
//! estimates it, as a duration since the Unix epoch: steps are due at
//! `epoch + k Δt / time_scale` on it, and messages are stamped with it.

use std::collections::VecDeque;
use std::time::Duration;

use crate::wire::{self, EstimateMsg, Header, Reject, FORMAT_VERSION};
use formation_control::{Hearing, LinkLoss, LossWindow, Message, Nearby};
use formation_leader::LeaderState;
use formation_plant::Pose;
use formation_record::hearing::{HeardRuns, Rescued, Resume};
use formation_record::{FollowerSample, Heard};
use formation_scenario::{FaultTarget, Scenario, Timing};
use formation_sim::{SimFollower, SimRobot};

use crate::barrier::{self, Start};
use crate::counters::{Counters, RejectCounts};
use crate::gate::{self, Kept, Phase};
use crate::hearing::EarLog;
use crate::inbox::{self, Inbox, Source};
use crate::loop_timing::{LoopStats, LoopTimer};
use crate::poses::Poses;
use crate::telemetry::{ClockReport, Delivery, EventKind, Left, LinkStats, NetEvent, Telemetry, MAX_LEFT_WHY};
use crate::Now;

/// The seam between the protocol and the robot: one follower's step.
///
/// [`SimFollower`] (brain + simulated robot + noise) is the implementation
/// the simulator uses too. A real robot's driver implements this with the
/// same brain ([`formation_control::Follower::step`]) fed by its own pose and
/// wheel-speed measurement, and applies the torques to the motors.
pub trait Body: Send {
    /// Step k at t = k Δt with the leader's state (if heard), the
    /// neighbours' messages for k in ascending id and the other robots'
    /// poses (the safety filter's; [`Nearby::NONE`] without it); returns
    /// the step's telemetry sample and this follower's message for k + 1.
    fn step(
        &mut self,
        t_s: f64,
        dt_s: f64,
        leader: Option<&LeaderState>,
        neighbours: &[Message],
        nearby: Nearby<'_>,
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
    /// Lock-step: whether the robot's input for step k is in. A robot driven
    /// through ROS 2 must have reported its odometry of step k; a simulated
    /// robot always has.
    fn robot_ready(&self, _k: u64) -> bool {
        true
    }
    /// The robot's pose now, after its last step's move (the pose of the
    /// next step), where known: a leaving follower's last pose message.
    fn pose(&self) -> Option<Pose> {
        None
    }
    /// Who [`Body::robot_ready`] waits for, for the operator.
    fn robot_name(&self) -> std::borrow::Cow<'_, str> {
        "the robot".into()
    }
}

impl Body for SimFollower {
    fn step(
        &mut self,
        t_s: f64,
        dt_s: f64,
        leader: Option<&LeaderState>,
        neighbours: &[Message],
        nearby: Nearby<'_>,
        last: bool,
    ) -> (FollowerSample, Message) {
        self.step_disturbed(self.robot.disturbance_at(t_s), dt_s, leader, neighbours, nearby, last)
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
    fn pose(&self) -> Option<Pose> {
        Some(self.robot.seen_pose())
    }
}

/// How a follower runs, beyond its scenario.
#[derive(Clone, Debug)]
pub struct Options {
    /// Lock-step: give up when a step's inputs stop arriving for this long.
    pub stall_timeout: Duration,
    /// The network performs the fault table's `node` rows (the lab): they
    /// are not applied again here.
    pub physical_node_faults: bool,
}

/// How many telemetry batches' worth of each source's last messages a
/// follower keeps for a rescue ([`EarLog`]): more than a killed sender can
/// have left unacknowledged (one batch being filled, one or two in flight).
pub const RESCUE_BATCHES: usize = 4;

/// The most bytes one rescued message takes in a telemetry batch (bincode,
/// varints: the source at most 5, the stamp 9, the state 64, `fresh` 1).
pub const RESCUED_BYTES: u64 = 80;

/// The most bytes of rescued messages one batch of a follower with
/// `sources` sources can carry, with batches of `batch` steps: its last
/// batch rescues every source's last [`RESCUE_BATCHES`] batches' worth.
pub fn most_rescued_bytes(sources: usize, batch: u32) -> u64 {
    sources as u64 * RESCUE_BATCHES as u64 * u64::from(batch.max(1)) * RESCUED_BYTES
}

/// Lock-step: how long a follower keeps republishing its final message
/// after its last step, waiting for its neighbours to report theirs.
pub const LINGER: Duration = Duration::from_secs(1);

/// A process that hears a start older than this is a restart.
pub const LATE: Duration = Duration::from_millis(200);

/// The arrival checks of one follower ([`FollowerMachine::checker`]).
#[derive(Clone, Debug)]
pub struct Checker {
    hears_leader: bool,
    neighbours: Vec<u32>,
}

impl Checker {
    /// [`inbox::check`] for this follower: the message and its source, or why not.
    pub fn check(&self, key_id: Option<u32>, bytes: &[u8]) -> Result<(Source, EstimateMsg), Reject> {
        inbox::check(key_id, bytes, self.hears_leader, &self.neighbours)
    }
}

/// What arrived on an estimate key, once checked.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Arrival {
    /// The leader's own stamp (ns on its clock), when the message is the
    /// leader's: a floor for the node's estimate of that clock.
    pub leader_sent_ns: Option<i64>,
    /// The step the loop waits for is now complete: wake it.
    pub wake: bool,
}

/// A telemetry batch as the machine knows it; the node adds how its
/// delivery goes and its estimate of the leader's clock
/// ([`Batch::into_telemetry`]).
#[derive(Clone, Debug)]
pub struct Batch {
    pub first_k: u64,
    /// One past the batch's last step.
    pub end_k: u64,
    id: u32,
    samples: Vec<FollowerSample>,
    counters: Counters,
    done: bool,
    loop_stats: Option<LoopStats>,
    events: Vec<NetEvent>,
    links: Vec<LinkStats>,
    heard: HeardRuns,
    rescued: Vec<Rescued>,
    resumed: Option<Resume>,
    diverged: Option<String>,
    left: Option<Left>,
}

impl Batch {
    /// The message for the monitor.
    pub fn into_telemetry(self, delivery: Delivery, clock: Option<ClockReport>) -> Telemetry {
        Telemetry::Follower {
            id: self.id,
            first_k: self.first_k,
            samples: self.samples,
            counters: self.counters,
            done: self.done,
            loop_stats: self.loop_stats,
            delivery,
            events: self.events,
            clock,
            links: self.links,
            heard: self.heard,
            rescued: self.rescued,
            resumed: self.resumed,
            diverged: self.diverged,
            left: self.left,
        }
    }
}

/// The rules of the run that the machine keeps.
#[derive(Clone, Debug)]
struct Rules {
    id: u32,
    steps: u64,
    dt_s: f64,
    batch: usize,
    lockstep: bool,
    /// Neighbours' ids, ascending: inbox slots 0..n; the leader (if heard) is slot n.
    neighbours: Vec<u32>,
    hears_leader: bool,
    silence_steps: u64,
    /// Real time: step k uses the newest messages stamped at or before k − d.
    delay_steps: u64,
    /// `network.rejoin_after` in steps (docs/model.md §14).
    rejoin_after_steps: u64,
    stall_timeout: Duration,
    /// The sources' ids (0: the leader), by inbox slot.
    source_ids: Vec<u32>,
    /// "follower 2", …, "the leader", by inbox slot.
    source_names: Vec<String>,
    /// The fault table's longest window (steps, plus one per hop), for the
    /// lock-step look-ahead.
    faulted_ahead: Option<u64>,
    /// The fault table's seed and, per slot, its windows for the link
    /// (a neighbour that leaves adds one: [`FollowerMachine::handle_gone`]).
    seed: u64,
    fault_windows: Vec<Vec<LossWindow>>,
}

/// One follower: see the module documentation.
pub struct FollowerMachine {
    rules: Rules,
    body: Box<dyn Body>,
    inbox: Inbox,
    phase: Phase,
    /// Real time: the run's epoch and step period on the timebase.
    epoch: Now,
    period: Duration,
    timer: Option<LoopTimer>,
    /// Lock-step: the wait for the current step's inputs, once it waits.
    wait: Option<gate::Wait>,
    /// The messages published, oldest first, the last [`gate::FOLLOWER_KEPT`]
    /// of them (republished while waiting).
    recent: Kept,
    hearing: Hearing,
    /// Real time, per slot: whether the source is heard now (for the timeline).
    heard_now: Vec<bool>,
    ear: EarLog,
    events: Vec<NetEvent>,
    second_clock_named: bool,
    /// Lock-step: the neighbours that reported their final step.
    done_neighbours: Vec<u32>,
    /// Real time: neighbours absent at the start, whose first message
    /// opens their links from its step on (a join, docs/model.md §14).
    joinable: Vec<u32>,
    samples: Vec<FollowerSample>,
    first_k: u64,
    resumed: Option<Resume>,
    sent: u64,
    republished: u64,
    /// The robot's pose every 10 steps, for the node's checkpoint.
    checkpoint: Option<(u64, Pose)>,
    /// The time of the last call that passed one.
    last_now: Now,
    inputs: Vec<Message>,
    taken: Vec<Option<Message>>,
    transmit: VecDeque<Vec<u8>>,
    telemetry: VecDeque<Batch>,
    say: VecDeque<String>,
    /// Lines of news for the operator (it left the run): not warnings.
    news: VecDeque<String>,
    /// The sample of the last step computed, until taken.
    latest: Option<FollowerSample>,
    /// The other robots' poses, with the safety filter on.
    poses: Option<Poses>,
    pose_transmit: VecDeque<Vec<u8>>,
    /// This follower left the run for good ([`FollowerMachine::handle_leave`]).
    left: Option<Left>,
    /// It leaves before this step ([`FollowerMachine::schedule_leave`]), and why.
    leave_at: Option<u64>,
    leave_why: &'static str,
}

impl FollowerMachine {
    /// The follower at `index` of `scenario`, stepping `body`. It accepts
    /// messages from now on (a leader may run ahead before this node hears
    /// the start) and steps once [`FollowerMachine::start`] is called.
    pub fn new(scenario: &Scenario, index: usize, body: Box<dyn Body>, opts: &Options) -> Self {
        let id = scenario.graph.id(index);
        let hears_leader = scenario.graph.hears_leader(index);
        let neighbours: Vec<u32> = scenario.graph.neighbours(index).iter().map(|&j| scenario.graph.id(j)).collect();
        let lockstep = scenario.timing == Timing::Lockstep;
        let mut source_ids = neighbours.clone();
        if hears_leader {
            source_ids.push(wire::LEADER_ID);
        }
        let slots = source_ids.len();
        // docs/model.md §14: the fault table applies at the receiver, per incoming link.
        let mut table = scenario.clone();
        if opts.physical_node_faults {
            table.faults.retain(|f| !matches!(f.target, FaultTarget::Node(_)));
        }
        let mut inbox = Inbox::new(slots, lockstep);
        inbox.set_links(scenario.sources_of(index).iter().map(|&src| table.link_loss(src, id)).collect());
        let fault_windows = scenario.sources_of(index).iter().map(|&src| table.link_windows(src, id)).collect();
        let faulted_ahead = scenario
            .faults
            .iter()
            .map(|f| {
                let (a, b) = f.steps(scenario.dt_s);
                b - a + scenario.followers.len() as u64
            })
            .max();
        let rules = Rules {
            id,
            steps: scenario.steps(),
            dt_s: scenario.dt_s,
            batch: scenario.network.telemetry_batch.max(1) as usize,
            lockstep,
            hears_leader,
            silence_steps: scenario.silence_steps(),
            delay_steps: scenario.network.delay_steps,
            rejoin_after_steps: scenario.control.rejoin.after_steps,
            stall_timeout: opts.stall_timeout,
            source_names: source_ids
                .iter()
                .map(|&s| if s == wire::LEADER_ID { "the leader".to_string() } else { format!("follower {s}") })
                .collect(),
            source_ids,
            neighbours,
            faulted_ahead,
            seed: scenario.seed,
            fault_windows,
        };
        let ear = if scenario.network.hearing_record {
            EarLog::new(rules.source_ids.clone(), RESCUE_BATCHES * rules.batch)
        } else {
            EarLog::off()
        };
        let mut f = Self {
            hearing: Hearing::new(slots, rules.silence_steps),
            heard_now: vec![false; slots],
            samples: Vec::with_capacity(rules.batch),
            inputs: Vec::with_capacity(slots),
            taken: Vec::with_capacity(slots),
            body,
            inbox,
            phase: Phase::Waiting,
            epoch: Now::ZERO,
            period: Duration::ZERO,
            timer: None,
            wait: None,
            recent: Kept::new(gate::FOLLOWER_KEPT),
            ear,
            events: Vec::new(),
            second_clock_named: false,
            done_neighbours: Vec::new(),
            joinable: Vec::new(),
            first_k: 0,
            resumed: None,
            sent: 0,
            republished: 0,
            checkpoint: None,
            last_now: Now::ZERO,
            transmit: VecDeque::new(),
            telemetry: VecDeque::new(),
            say: VecDeque::new(),
            news: VecDeque::new(),
            latest: None,
            leave_at: None,
            leave_why: "",
            poses: scenario.control.guard.safety.is_some().then(|| {
                let initial = (0..scenario.followers.len()).map(|j| SimRobot::new(scenario, j).seen_pose()).collect();
                Poses::new(scenario, index, initial)
            }),
            pose_transmit: VecDeque::new(),
            left: None,
            rules,
        };
        f.set_window(scenario.network.time_scale);
        f
    }

    /// This follower's id.
    pub fn id(&self) -> u32 {
        self.rules.id
    }

    /// The sources' ids by inbox slot (neighbours ascending, then 0 for the leader).
    pub fn source_ids(&self) -> &[u32] {
        &self.rules.source_ids
    }

    /// How far ahead of this node's step a genuine message can be (further:
    /// `Reject::Future`). Lock-step: neighbours [`inbox::LOCKSTEP_AHEAD`]
    /// steps, the leader its window more. A fault lets a node run ahead of
    /// a receiver that does not wait for it (an isolated follower runs
    /// freely through its window), by at most the longest window plus one
    /// step per hop of the graph. Real time: 0.1 s of wall time (at least
    /// [`inbox::REALTIME_AHEAD`] steps) beyond the shared clock's step.
    fn set_window(&mut self, time_scale: f64) {
        let slots = self.rules.source_ids.len();
        if self.rules.lockstep {
            let ahead = self.rules.faulted_ahead.map_or(inbox::LOCKSTEP_AHEAD, |w| w + inbox::LOCKSTEP_AHEAD);
            for slot in 0..slots {
                self.inbox.set_ahead(slot, ahead);
            }
            if self.rules.hears_leader {
                self.inbox.set_ahead(slots - 1, ahead + gate::WINDOW);
            }
        } else {
            let period = self.rules.dt_s / barrier::positive_scale(time_scale);
            let slack = ((0.1 / period).ceil() as u64).max(inbox::REALTIME_AHEAD);
            for slot in 0..slots {
                self.inbox.set_ahead(slot, slack);
            }
        }
    }

    /// A message on the estimate key of `key_id` (None: the key's last part
    /// is not an id), received at `now` (None: the timebase not yet known).
    pub fn handle_estimate(&mut self, key_id: Option<u32>, bytes: &[u8], now: Option<Now>) -> Arrival {
        match self.checker().check(key_id, bytes) {
            Ok((source, msg)) => self.handle_checked(source, &msg, now),
            Err(r) => {
                self.inbox.reject(r);
                Arrival::default()
            }
        }
    }

    /// A message on `pose/<key_id>` (the safety filter's, docs/model.md
    /// §16), received at `now`: kept, or counted as refused. Wakes a
    /// lock-step loop whose step it completes.
    pub fn handle_pose(&mut self, key_id: Option<u32>, bytes: &[u8], now: Now) -> Arrival {
        let step = match self.phase {
            Phase::Stepping(k) => k,
            Phase::Waiting => 0,
            _ => self.rules.steps,
        };
        let Some(poses) = self.poses.as_mut() else {
            self.inbox.reject(Reject::NotNeighbour);
            return Arrival::default();
        };
        if let Err(r) = poses.handle(key_id, bytes, now, step) {
            self.inbox.reject(r);
            return Arrival::default();
        }
        let wake = self.rules.lockstep
            && matches!(self.phase, Phase::Stepping(_))
            && poses.has_all(step)
            && self.inbox.has_all(step);
        Arrival { wake, ..Arrival::default() }
    }

    /// The next pose message to publish on this follower's `pose/<id>`.
    pub fn poll_pose(&mut self) -> Option<Vec<u8>> {
        self.pose_transmit.pop_front()
    }

    /// The checks every message passes before it reaches the machine
    /// (docs/model.md §13), to run where messages arrive, without the
    /// machine: decoding, the key's sender, a source this follower hears.
    pub fn checker(&self) -> Checker {
        Checker { hears_leader: self.rules.hears_leader, neighbours: self.rules.neighbours.clone() }
    }

    /// A message that passed the [`Checker`], received at `now`.
    pub fn handle_checked(&mut self, source: Source, msg: &EstimateMsg, now: Option<Now>) -> Arrival {
        let n = self.rules.neighbours.len();
        let mut arrival = Arrival::default();
        self.inbox.set_time(now);
        let slot = if let Source::Neighbour(slot) = source { slot } else { n };
        if slot < n && !self.joinable.is_empty() {
            self.handle_joined(msg.header.sender, msg.header.step);
        }
        // Real time, before this follower's start: a joining or restarted
        // process hears the running formation's messages, far ahead of its
        // step 0; they are early for it, not forged (its first step is the
        // one then due, and it takes what it hears from then on).
        if !self.rules.lockstep && matches!(self.phase, Phase::Waiting) && self.inbox.beyond(slot, msg.header.step) {
            return arrival;
        }
        if slot == n {
            arrival.leader_sent_ns = Some(msg.header.sent_ns);
        }
        if let (true, Some(now)) = (self.inbox.accept(slot, msg), now) {
            self.inbox.note_latency(slot, msg.header.sent_ns, now.as_nanos() as i64);
        }
        // Wake the loop only when its step is complete: one wake-up per
        // step instead of one per message.
        arrival.wake = self.inbox.completes_wait();
        arrival
    }

    /// Messages the [`Checker`] refused, counted where they arrived.
    pub fn handle_rejected(&mut self, counts: &RejectCounts) {
        self.inbox.counters.rejected.merge(counts);
    }

    /// Something the node noticed outside the messages (the router lost or
    /// back, a second clock on `control/time`), at the current step.
    pub fn handle_event(&mut self, what: EventKind) {
        if what == EventKind::SecondClock {
            if self.second_clock_named {
                return;
            }
            self.second_clock_named = true;
        }
        let k = match self.phase {
            Phase::Stepping(k) => k,
            _ => self.rules.steps,
        };
        self.events.push(NetEvent { k, what });
    }

    /// This follower leaves the run before step `at_k` (`agent --leave
    /// ID@SECONDS`): it takes step `at_k` − 1 but sends no message for
    /// step `at_k`, then leaves as [`FollowerMachine::handle_leave`] says. So a
    /// leave is as repeatable as the fault table: lock-step runs with it
    /// equal the simulator with the follower's node cut off from `at_k` on.
    pub fn schedule_leave(&mut self, at_k: u64) {
        self.leave_at = Some(at_k.max(1));
        self.leave_why = "--leave, as scheduled";
    }

    /// Neighbour `id` left the run before step `at_k` (lock-step: its last
    /// telemetry said so): from then on its link is cut, as a fault-table
    /// row `node = id` from that step to the end would cut it, so this
    /// follower does not wait for its messages; and it is not waited for
    /// at the end.
    pub fn handle_gone(&mut self, id: u32, at_k: u64) {
        let Some(slot) = self.rules.source_ids.iter().position(|&s| s == id && s != wire::LEADER_ID) else { return };
        if self.done_neighbours.contains(&id) {
            return;
        }
        self.done_neighbours.push(id);
        let windows = &mut self.rules.fault_windows[slot];
        windows.push(LossWindow { from_k: at_k, to_k: self.rules.steps + 1, loss: 1.0 });
        let link = LinkLoss::new(self.rules.seed, id, self.rules.id, windows);
        self.inbox.set_link(slot, link);
    }

    /// What this follower holds of follower `id`, which died (lock-step,
    /// [`crate::died`]): the newest step of its estimate heard (if it is a
    /// source) and of its pose (if the filter is on).
    pub fn holding_of(&self, id: u32, fingerprint: u64) -> crate::died::Holding {
        let slot = self.rules.source_ids.iter().position(|&s| s == id && s != wire::LEADER_ID);
        let newest = self.poses.as_ref().and_then(|p| p.newest_of(id));
        crate::died::Holding {
            fingerprint,
            sender: self.rules.id,
            died: id,
            estimate: slot.and_then(|s| self.inbox.heard_max(s)),
            pose: newest.map(|(k, _)| k),
            pose_at: newest.map(|(_, p)| [p.x, p.y, p.theta]),
            estimates: slot.map_or([None; 2], |s| self.inbox.newest_heard(s)),
        }
    }

    /// Lock-step: whether every other node this follower's messages feed
    /// has taken step `k`, by what it heard of them: each running
    /// neighbour's estimate of step k + 1 (sent after its step k, which
    /// took this follower's estimate of k) and, with the filter on, each
    /// running robot's pose of step k (its step k took this one's pose of
    /// k − 1). A fault-table death waits for it, so that what it sent up
    /// to there is held by every node before it dies ([`crate::died`]).
    pub fn heard_past(&self, k: u64) -> bool {
        let estimates = self.rules.source_ids.iter().enumerate().all(|(slot, &s)| {
            s == wire::LEADER_ID || self.done_neighbours.contains(&s) || self.inbox.heard_max(slot) > Some(k)
        });
        estimates && self.poses.as_ref().is_none_or(|p| p.heard_past(k))
    }

    /// Follower `id` died, its links cut from step `at_k` as the monitor
    /// named it (lock-step, [`crate::died`]): as a neighbour that left
    /// ([`FollowerMachine::handle_gone`]), but with no last pose: its robot stands
    /// at its pose of step `at_k` − 2 from step `at_k` − 1 on, for this
    /// follower's filter. Its last messages, those of the steps before
    /// `at_k` that this follower lacks, come with `died` (a peer's last
    /// fan-out may have reached some nodes only).
    pub fn handle_died(&mut self, died: &crate::died::Died) {
        let (id, at_k) = (died.follower, died.at_k);
        let slot = self.rules.source_ids.iter().position(|&s| s == id && s != wire::LEADER_ID);
        if let (Some(slot), Some(m)) = (slot, died.estimate) {
            if m.header.sender == id && m.header.step < at_k && !self.inbox.holds(slot, m.header.step) {
                let _ = self.handle_checked(Source::Neighbour(slot), &m, None);
            }
        }
        self.handle_gone(id, at_k);
        if let Some(p) = self.poses.as_mut() {
            if let (Some(k), Some(pose)) = (at_k.checked_sub(2), died.pose) {
                p.fill(id, k, pose, self.last_now);
            }
            p.died(id, at_k);
        }
    }

    /// Follower `id` was absent at the start (a quorum start): its links
    /// are cut from step 0, as the row `{ node = id, from = 0 }`; in real
    /// time its first message, if it joins later, opens them again from
    /// that message's step ([`FollowerMachine::handle_checked`]).
    pub fn handle_absent(&mut self, id: u32) {
        self.handle_gone(id, 0);
        if let Some(p) = self.poses.as_mut() {
            p.absent(id);
        }
        if !self.rules.lockstep && self.rules.neighbours.contains(&id) && !self.joinable.contains(&id) {
            self.joinable.push(id);
        }
    }

    /// Real time: absent neighbour `id` joined the run with its message of
    /// step `k`: its links are cut over [0, k) only, the row
    /// `{ node = id, from = 0, to = k Δt }`.
    fn handle_joined(&mut self, id: u32, k: u64) {
        let Some(i) = self.joinable.iter().position(|&j| j == id) else { return };
        let Some(slot) = self.rules.source_ids.iter().position(|&s| s == id) else { return };
        self.joinable.swap_remove(i);
        self.done_neighbours.retain(|&d| d != id);
        let end = self.rules.steps + 1;
        let windows = &mut self.rules.fault_windows[slot];
        if let Some(w) = windows.iter_mut().find(|w| w.from_k == 0 && w.to_k == end && w.loss >= 1.0) {
            w.to_k = k.clamp(1, end);
        }
        let link = LinkLoss::new(self.rules.seed, id, self.rules.id, windows);
        self.inbox.set_link(slot, link);
    }

    /// This follower leaves the run for good: its process was told to stop
    /// (`why`: "SIGTERM", "Ctrl-C"). Its message for the step it takes next
    /// is already out, so it takes that step, sends nothing for the one
    /// after, and leaves before it ([`FollowerMachine::schedule_leave`]'s rule):
    /// what it computed goes out in a last batch marked done and [`Left`]
    /// (the monitor then waits for nothing more from it; its neighbours in
    /// lock-step and the run's model cut its links from that step on, as
    /// docs/model.md §14's node fault), and the machine ends well. Before
    /// the start there is nothing to leave: the machine ends as it is.
    pub fn handle_leave(&mut self, why: &'static str) {
        match self.phase {
            Phase::Stepping(k) => {
                if self.leave_at.is_none_or(|at| at > k + 1) {
                    self.leave_at = Some(k + 1);
                    self.leave_why = why;
                }
            }
            Phase::Waiting => self.finish(Ok(())),
            Phase::Lingering(_) | Phase::Done(_) => {}
        }
    }

    /// Leaves before step `at_k`, having taken every step before it.
    fn leave_now(&mut self, at_k: u64) {
        let why = self.leave_why;
        self.left = Some(Left { at_k, why: why.chars().take(MAX_LEFT_WHY).collect() });
        // Where its robot stopped, the pose of step at_k, marked left: the
        // others stop waiting for its poses and keep clear of it there.
        let stopped = self.body.pose().or(self.latest.map(|s| s.pose));
        if let (Some(p), Some(pose)) = (self.poses.as_mut(), stopped) {
            self.pose_transmit.push_back(p.publish(at_k, pose, true, self.last_now, self.rules.dt_s));
        }
        self.close_batch(at_k - 1, true, None);
        self.news.push_back(format!("follower {}: leaves the run before step {at_k}: {why}", self.rules.id));
        self.finish(Ok(()));
    }

    /// Lock-step: neighbour `id` reported its final step.
    pub fn handle_done(&mut self, id: u32) {
        if !self.done_neighbours.contains(&id) {
            self.done_neighbours.push(id);
        }
    }

    /// Lock-step: where a restarted process resumes. Its neighbours, waiting
    /// for its message of the step they are at, repeat their last
    /// [`gate::REPEATED`] messages every 100 ms; a process that hears them
    /// well past step 0 is a restart and resumes one step before the least
    /// advanced of them (it adopts from their messages of that step and
    /// publishes the message they wait for). 0 for a run only starting.
    pub fn lockstep_resume_step(&self) -> u64 {
        let heard: Vec<Option<u64>> = (0..self.rules.neighbours.len()).map(|s| self.inbox.heard_max(s)).collect();
        gate::resume_step(&heard)
    }

    /// Lock-step, a restart listening: whether every neighbour has been
    /// heard (where the least advanced waits is known only then).
    pub fn lockstep_heard_every_neighbour(&self) -> bool {
        (0..self.rules.neighbours.len()).all(|s| self.inbox.heard_max(s).is_some())
    }

    /// The run begins: `start` as the leader announced it, at `now`; from
    /// step 0, or a restart's `resume` step with its robot stopped at the pose.
    pub fn start(&mut self, start: &Start, resume: Option<(u64, Pose)>, now: Now) {
        self.last_now = now;
        if !self.rules.lockstep {
            // The shared clock bounds how far ahead a genuine message can be.
            let scale = start.scale();
            self.set_window(scale);
            self.epoch = Duration::from_nanos(start.epoch_unix_ns);
            self.period = Duration::from_secs_f64(self.rules.dt_s / scale);
            self.inbox.set_clock(self.epoch, self.period);
            self.timer = Some(LoopTimer::new(self.period.as_secs_f64()));
            if let Some(p) = self.poses.as_mut() {
                p.start(self.epoch, scale, self.rules.dt_s);
            }
        }
        let first_step = resume.map_or(0, |(k, _)| k);
        if let Some((k, pose)) = resume.filter(|&(k, _)| k > 0) {
            self.body.resume(k, pose);
            self.resumed = Some(Resume { k, pose: [pose.x, pose.y, pose.theta] });
        } else {
            // A restart publishes nothing until it has adopted an estimate.
            let first = self.body.initial_message();
            self.publish(0, first, now);
        }
        self.first_k = first_step;
        self.phase = Phase::Stepping(first_step);
    }

    /// Does what is due at `now`: at most one step, or a wait's repeat,
    /// warning or end.
    pub fn handle_timeout(&mut self, now: Now) {
        self.last_now = now;
        match self.phase {
            Phase::Waiting | Phase::Done(_) => {}
            Phase::Stepping(k) => self.step_if_ready(k, now),
            Phase::Lingering(_) => self.linger(now),
        }
    }

    /// When the machine next wants [`FollowerMachine::handle_timeout`]: None
    /// before the start and after the end; `Now::ZERO` (at once) when a
    /// lock-step step's inputs are in.
    pub fn poll_timeout(&mut self) -> Option<Now> {
        match &self.phase {
            Phase::Waiting | Phase::Done(_) => None,
            Phase::Stepping(k) if !self.rules.lockstep => Some(self.due(*k)),
            Phase::Stepping(k) => {
                let k = *k;
                if self.inbox.has_all(k) && self.body.robot_ready(k) && self.poses_in(k) {
                    Some(Now::ZERO)
                } else {
                    Some(self.wait.as_ref().map_or(Now::ZERO, gate::Wait::next_wake))
                }
            }
            Phase::Lingering(w) => Some(w.next_wake().min(self.last_now + gate::LINGER_LOOK_EVERY)),
        }
    }

    /// The next estimate message to publish (encoded, stamped).
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.transmit.pop_front()
    }

    /// The next telemetry batch for the monitor.
    pub fn poll_telemetry(&mut self) -> Option<Batch> {
        self.telemetry.pop_front()
    }

    /// The next line for the operator (stderr): a warning.
    pub fn poll_say(&mut self) -> Option<String> {
        self.say.pop_front()
    }

    /// The next line of news for the operator (the follower left the run),
    /// which a quiet node keeps to itself.
    pub fn poll_news(&mut self) -> Option<String> {
        self.news.pop_front()
    }

    /// The sample of the last step computed, once (for a node that publishes
    /// each step's state as it happens, such as its ROS 2 topics).
    pub fn take_sample(&mut self) -> Option<FollowerSample> {
        self.latest.take()
    }

    /// The end of the run: None while it runs; Err says why it failed.
    pub fn outcome(&self) -> Option<&Result<(), String>> {
        self.phase.outcome()
    }

    /// What the inbox counted so far (sent and republished are counted in
    /// the telemetry batches).
    pub fn counters(&self) -> Counters {
        self.inbox.counters
    }

    /// The robot's latest pose (every 10 steps), for a checkpoint.
    pub fn checkpoint(&self) -> Option<(u64, Pose)> {
        self.checkpoint
    }

    /// The step this machine computes next (or waits for).
    pub fn step(&self) -> Option<u64> {
        self.phase.step()
    }

    /// Real time: when step k is due on the timebase.
    fn due(&self, k: u64) -> Now {
        gate::due(self.epoch, self.period, k)
    }

    fn step_if_ready(&mut self, k: u64, now: Now) {
        let leader = if self.rules.lockstep {
            self.inbox.set_step(k);
            if !self.inbox.has_all(k) || !self.body.robot_ready(k) || !self.poses_in(k) {
                self.wait_for_inputs(k, now);
                return;
            }
            self.wait = None;
            self.lockstep_inputs(k)
        } else {
            let due = self.due(k);
            if now < due {
                return;
            }
            self.inbox.set_step(k);
            // Lateness against the step's own due time.
            if let Some(t) = self.timer.as_mut() {
                t.push(k, k as f64 * self.period.as_secs_f64() + (now - due).as_secs_f64());
            }
            self.realtime_inputs(k)
        };
        self.compute(k, leader, now);
    }

    /// Lock-step: the step's inputs are not all in; repeat, warn or give up.
    fn wait_for_inputs(&mut self, k: u64, now: Now) {
        let stall = self.rules.stall_timeout;
        // Whatever the sources it waits for send (a waiting neighbour
        // repeats its last messages) says they are alive: the stall timeout
        // counts from their last word, in time this node was awake to watch.
        let signs = self.inbox.signs_of_life(k);
        let wait = self.wait.get_or_insert_with(|| gate::Wait::new(now, gate::FOLLOWER_REPEAT_EVERY, stall));
        wait.alive(now, signs);
        let waited = wait.waited(now);
        let gate::WaitStep::Wait { repeat, warn } = wait.poll(now) else {
            let (names, n) = self.missing(k);
            self.finish(Err(format!(
                "{names} stopped answering: no input for step {k} from {} for {:.0} s (stall timeout; a process \
                 that is down, or a link that does not carry its messages)",
                if n == 1 { "it" } else { "them" },
                stall.as_secs_f64()
            )));
            return;
        };
        if warn {
            let (names, _) = self.missing(k);
            let line = format!(
                "follower {}: waiting {:.0} s for step {k} from {} (stall timeout {:.0} s); repeating its last \
                 messages meanwhile",
                self.rules.id,
                waited.as_secs_f64(),
                names,
                stall.as_secs_f64()
            );
            self.say.push_back(line);
        }
        if repeat {
            // A sender that keeps us waiting may be gone, with its last
            // telemetry: its messages we used go to the monitor (once: the
            // rescue empties what was kept).
            for s in self.inbox.missing(k) {
                self.ear.rescue(s);
            }
            // Safety net for messages lost on the way: say again what the
            // neighbours still need.
            self.repeat_for_the_slowest();
        }
    }

    fn missing(&mut self, k: u64) -> (String, usize) {
        let mut names: Vec<std::borrow::Cow<'_, str>> =
            self.inbox.missing(k).iter().map(|&s| self.rules.source_names[s].as_str().into()).collect();
        if !self.body.robot_ready(k) {
            names.push(self.body.robot_name());
        }
        if let Some(p) = &self.poses {
            names.extend(p.missing(k).map(|id| format!("follower {id}'s pose").into()));
        }
        (names.join(" and "), names.len())
    }

    fn repeat_for_the_slowest(&mut self) {
        let slowest = self.inbox.slowest_heard(self.rules.neighbours.len());
        for bytes in self.recent.follower_repeats(slowest) {
            self.transmit.push_back(bytes.clone());
            self.sent += 1;
            self.republished += 1;
        }
        self.repeat_poses();
    }

    /// Lock-step: whether the other robots' poses step k needs are in.
    fn poses_in(&self, k: u64) -> bool {
        self.poses.as_ref().is_none_or(|p| p.has_all(k))
    }

    /// Lock-step: this follower's last poses again (one lost keeps every
    /// other robot waiting).
    fn repeat_poses(&mut self) {
        if let Some(p) = &self.poses {
            self.pose_transmit.extend(p.repeats().cloned());
        }
    }

    /// Lock-step: step k's messages (slots 0..n the neighbours, n the
    /// leader) into the hearing; the neighbours' into `inputs`; the leader's state.
    fn lockstep_inputs(&mut self, k: u64) -> Option<LeaderState> {
        let n = self.rules.neighbours.len();
        self.inbox.take(k, &mut self.taken);
        for (slot, m) in self.taken.iter().enumerate() {
            if let Some(m) = m {
                self.hearing.deliver(slot, k, *m);
            }
        }
        for slot in 0..self.rules.source_ids.len() {
            let used = self.hearing.heard_at(slot, k);
            let h = match used {
                Some((s, _)) => Heard::used(k, s),
                None if self.taken[slot].is_none() => Heard::Removed,
                None => Heard::Silent,
            };
            self.ear.note(slot, h, used);
        }
        self.ear.end_step();
        self.inputs.clear();
        self.inputs.extend((0..n).filter_map(|slot| self.hearing.heard(slot, k)).copied());
        if self.rules.hears_leader {
            self.hearing.heard(n, k).map(|m| m.state)
        } else {
            None
        }
    }

    /// Real time: the newest messages as of step k − d (network.delay_steps);
    /// a source silent too long is left out.
    fn realtime_inputs(&mut self, k: u64) -> Option<LeaderState> {
        let n = self.rules.neighbours.len();
        self.inputs.clear();
        let sent_k = k.saturating_sub(self.rules.delay_steps);
        let mut leader = None;
        for slot in 0..self.rules.source_ids.len() {
            let s = self.inbox.latest(slot, sent_k, self.rules.silence_steps);
            if self.heard_now[slot] != s.is_some() {
                self.heard_now[slot] = s.is_some();
                let src = self.rules.source_ids[slot];
                let what = if s.is_some() { EventKind::Heard(src) } else { EventKind::Silent(src) };
                self.events.push(NetEvent { k, what });
            }
            let h = match s {
                Some((stamp, _)) => Heard::used(k, stamp),
                None if self.inbox.removed(slot, sent_k) => Heard::Removed,
                None => Heard::Silent,
            };
            self.ear.note(slot, h, s.as_ref().map(|(stamp, m)| (*stamp, m)));
            match s {
                Some((_, m)) if slot < n => self.inputs.push(m),
                Some((_, m)) => leader = Some(m.state),
                None => {}
            }
        }
        self.ear.end_step();
        leader
    }

    /// Step k with its inputs: the body's step, isolation events, the
    /// publish rule, the telemetry batch, and what comes next.
    fn compute(&mut self, k: u64, leader: Option<LeaderState>, now: Now) {
        let last = k == self.rules.steps;
        let t = k as f64 * self.rules.dt_s;
        let was_silent = self.body.silent_steps();
        let nearby = match self.poses.as_mut() {
            Some(p) => {
                let own = p.own();
                let (poses, seen, lost) = p.view(k, now);
                Nearby { poses, own, seen, lost }
            }
            None => Nearby::NONE,
        };
        let (sample, next) = self.body.step(t, self.rules.dt_s, leader.as_ref(), &self.inputs, nearby, last);
        if let (Some(p), false) = (self.poses.as_mut(), last) {
            self.pose_transmit.push_back(p.publish(k, sample.pose, false, now, self.rules.dt_s));
        }
        let rejoin = self.rules.rejoin_after_steps;
        match self.body.silent_steps() {
            s if s == rejoin => self.events.push(NetEvent { k, what: EventKind::Isolated }),
            0 if was_silent >= rejoin => self.events.push(NetEvent { k, what: EventKind::Rejoined }),
            _ => {}
        }
        self.samples.push(sample);
        self.latest = Some(sample);
        let diverged = self.body.check_finite().err();
        if k % 10 == 0 {
            self.checkpoint = Some((k, sample.pose));
        }
        // A follower that leaves after this step sends no message for the next.
        let leaving = !last && diverged.is_none() && self.leave_at.is_some_and(|at| k + 1 >= at);
        if !last && !leaving && diverged.is_none() && self.publishes() {
            self.publish(k + 1, next, now);
        }
        if leaving {
            return self.leave_now(k + 1);
        }
        if self.samples.len() >= self.rules.batch || last || diverged.is_some() {
            self.close_batch(k, last || diverged.is_some(), diverged);
        }
        if let Some(q) = diverged {
            self.finish(Err(format!("{q} is not finite at step {k} (t = {t} s); the run diverged")));
        } else if !last {
            self.phase = Phase::Stepping(k + 1);
        } else if self.rules.lockstep {
            // A neighbour may still wait for our final message (lost?): say
            // it again until every neighbour reports its final step.
            self.phase = Phase::Lingering(gate::Wait::new(now, gate::LINGER_REPEAT_EVERY, LINGER));
        } else {
            self.finish(Ok(()));
        }
    }

    /// The publish rule. A restart publishes nothing until it has adopted
    /// an estimate. Real time: an isolated follower keeps its dead-reckoned
    /// estimate to itself until it hears a source again. In the model its
    /// links are down both ways; a real link comes back one way first, and
    /// when its neighbours heard it one step before it heard them, their
    /// estimates were pulled twice as far (lab, follower 3 cut off 8–11 s:
    /// 0.033 m against the simulator's 0.018; see docs/decisions.md).
    fn publishes(&self) -> bool {
        let silent = self.body.silent_steps();
        let isolated = !self.rules.lockstep && silent > 0 && silent >= self.rules.rejoin_after_steps;
        !self.body.adopting() && !isolated
    }

    /// Publishes this follower's message for step k, stamped `now`.
    fn publish(&mut self, k: u64, m: Message, now: Now) {
        let msg = EstimateMsg {
            header: Header {
                version: FORMAT_VERSION,
                sender: self.rules.id,
                step: k,
                time_s: k as f64 * self.rules.dt_s,
                sent_ns: now.as_nanos() as i64,
            },
            state: m.state,
            fresh: m.fresh,
            term: self.inbox.term(),
        };
        let bytes = wire::encode(&msg);
        self.transmit.push_back(bytes.clone());
        self.sent += 1;
        self.recent.push(k, bytes);
    }

    /// The telemetry batch that ends at step k.
    fn close_batch(&mut self, k: u64, done: bool, diverged: Option<&'static str>) {
        let mut counters = self.inbox.counters;
        counters.sent = self.sent;
        counters.republished = self.republished;
        if done {
            // A source that dies near the end never falls silent here: what
            // this follower used of each goes out with its last batch.
            for slot in 0..self.rules.source_ids.len() {
                self.ear.rescue(slot);
            }
        }
        let (heard, rescued) = self.ear.take();
        self.events.sort_unstable();
        self.telemetry.push_back(Batch {
            first_k: self.first_k,
            end_k: k + 1,
            id: self.rules.id,
            samples: std::mem::take(&mut self.samples),
            counters,
            done,
            loop_stats: if done { self.timer.as_ref().map(LoopTimer::stats) } else { None },
            events: std::mem::take(&mut self.events),
            links: self.inbox.link_stats(&self.rules.source_ids),
            heard,
            rescued,
            resumed: self.resumed,
            diverged: diverged.map(str::to_string),
            left: self.left.clone().filter(|_| done),
        });
        self.first_k = k + 1;
    }

    /// Lock-step, after the last step: repeat until every neighbour is done.
    fn linger(&mut self, now: Now) {
        let Phase::Lingering(wait) = &mut self.phase else { return };
        let step = wait.poll(now);
        let all_done = self.rules.neighbours.iter().all(|id| self.done_neighbours.contains(id));
        match step {
            gate::WaitStep::Wait { .. } if all_done => self.finish(Ok(())),
            gate::WaitStep::Wait { repeat: true, .. } => {
                let slowest = self.inbox.slowest_heard(self.rules.neighbours.len());
                for bytes in self.recent.follower_repeats(slowest) {
                    self.transmit.push_back(bytes.clone());
                }
                self.repeat_poses();
            }
            gate::WaitStep::Wait { .. } => {}
            gate::WaitStep::Over => self.finish(Ok(())),
        }
    }

    fn finish(&mut self, r: Result<(), String>) {
        self.phase = Phase::Done(r);
    }
}

/// How a follower's process that hears the start joins the run: the one
/// rule for both timings (docs/model.md §14).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Joining {
    /// From step 0: the run has not begun (or began less than [`LATE`] ago).
    Fresh,
    /// Real time, a restart: at this step ([`rejoin_step`]).
    At(u64),
    /// Lock-step, a restart: listen this long to the neighbours' repeats,
    /// then resume where they wait ([`FollowerMachine::lockstep_resume_step`]).
    ListenFirst(Duration),
}

/// How follower `index` of `scenario`, hearing `start` `since_s` seconds
/// (on the timebase) after its epoch, joins. Real time: [`rejoin_step`].
/// Lock-step: a run that began more than [`LATE`] ago is under way, and a
/// follower with neighbours learns where from their repeats (every 100 ms:
/// it listens [`LATE`] + 0.1 s); one without neighbours starts afresh.
/// Err: the run is over.
pub fn joining(start: &Start, since_s: f64, scenario: &Scenario, index: usize) -> Result<Joining, String> {
    if scenario.timing == Timing::Lockstep {
        let under_way = since_s > LATE.as_secs_f64() && !scenario.graph.neighbours(index).is_empty();
        return Ok(if under_way { Joining::ListenFirst(LATE + Duration::from_millis(100)) } else { Joining::Fresh });
    }
    Ok(match rejoin_step(start, since_s, scenario)? {
        0 => Joining::Fresh,
        k => Joining::At(k),
    })
}

/// Real time: the step a process that hears the start `start` at
/// `since_s` seconds (on the timebase) after its epoch should begin at. 0
/// for a run that has not begun (or began less than [`LATE`] ago);
/// otherwise a restart, which resumes [`LATE`] ahead of the run's current
/// step (time to set up before that step is due). Err: the run is over.
pub fn rejoin_step(start: &Start, since_s: f64, scenario: &Scenario) -> Result<u64, String> {
    let elapsed_s = since_s.max(0.0) * start.scale();
    if elapsed_s < LATE.as_secs_f64() {
        return Ok(0);
    }
    let k = ((elapsed_s + LATE.as_secs_f64()) / scenario.dt_s).ceil() as u64;
    if k >= scenario.steps() {
        return Err(format!(
            "run {} began {elapsed_s:.1} s ago and is over (T = {} s): nothing to rejoin",
            scenario.name, scenario.duration_s
        ));
    }
    Ok(k)
}
