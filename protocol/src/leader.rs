//! The leader of the formation as one machine, with the follower's surface
//! ([`crate::follower::FollowerMachine`]): it owns the virtual leader's trajectory,
//! the lock-step window, the real-time pacing on the run's timebase, the
//! stamping of its messages, what it repeats and for how long it lingers,
//! and its telemetry batches. It is fed what arrives from the followers
//! that hear it ([`LeaderMachine::handle_estimate`], [`LeaderMachine::handle_done`]) and
//! the time ([`LeaderMachine::handle_timeout`]); it answers what to publish
//! ([`LeaderMachine::poll_transmit`]), what to send to the monitor
//! ([`LeaderMachine::poll_telemetry`]), what to say ([`LeaderMachine::poll_say`]) and when
//! to be woken ([`LeaderMachine::poll_timeout`]). No socket, no clock, no thread.
//!
//! The leader's rules (docs/model.md §13):
//!
//! - it publishes (k, t, P_r, Ṗ_r, v_r, ω_r) for step k + 1 once step k is
//!   done; in real time step k is due at epoch + k Δt / time_scale; in
//!   lock-step it publishes step k only once every follower that hears it
//!   has published step k − [`WINDOW`] ([`gate::leader_needs`]), and repeats
//!   what the slowest may lack while it waits;
//! - a follower counts only on its own key and for a step it can have
//!   reached: at most one past the leader's newest ([`note_reached`]);
//! - after its last step, in lock-step, it repeats its last messages until
//!   every hearing follower reports its final step, for at most [`LINGER`].

use std::collections::{BTreeSet, VecDeque};
use std::time::Duration;

use crate::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use formation_leader::{Leader as Trajectory, LeaderState};
use formation_scenario::{Scenario, Timing};

use crate::barrier::Start;
use crate::counters::Counters;
use crate::gate::{self, Kept, Phase, WINDOW};
use crate::loop_timing::{LoopStats, LoopTimer};
use crate::steering::Steering;
use crate::telemetry::{Delivery, Handover, Telemetry, Term};
use crate::Now;
use formation_plant::{Pose, Velocity};

/// Lock-step: how long the leader keeps repeating after its last step.
pub const LINGER: Duration = Duration::from_secs(2);

/// How long a standby hears nothing from the leader before it takes the
/// run over, by default: 200 steps in real time at 1 kHz; in lock-step the
/// leader, even while it waits, repeats every [`gate::LEADER_REPEAT_EVERY`].
pub const TAKE_OVER_AFTER: Duration = Duration::from_millis(500);

/// The term of the leader a run starts with; each standby that takes the
/// run over leads the next one (docs/model.md §14).
pub const FIRST_TERM: u32 = 1;

/// How far back of the newest step heard from the leader a standby sends
/// the leader's states to the monitor when it takes over (the steps the
/// leader that is gone may not have delivered), besides two batches.
const RECORD_BACK: Duration = Duration::from_secs(1);

/// A standby leader before it takes over: what it heard of the leader.
struct Standby {
    after: Duration,
    start: Option<Start>,
    /// The newest step heard from the leader.
    heard: Option<u64>,
    /// When the leader was last heard (or the start, before that).
    heard_at: Now,
    /// The highest term heard on the leader's key.
    term: u32,
}

/// A telemetry batch as the machine knows it; the node adds how its
/// delivery goes and its clock server's count ([`LeaderBatch::into_telemetry`]).
#[derive(Clone, Debug)]
pub struct LeaderBatch {
    pub first_k: u64,
    /// One past the batch's last step.
    pub end_k: u64,
    states: Vec<LeaderState>,
    counters: Counters,
    done: bool,
    loop_stats: Option<LoopStats>,
    handover: Option<Handover>,
    term: Term,
}

impl LeaderBatch {
    /// The message for the monitor, with the clock server's (questions
    /// answered, peak per second).
    pub fn into_telemetry(self, delivery: Delivery, time_queries: (u64, u64)) -> Telemetry {
        let mut counters = self.counters;
        (counters.time_queries, counters.time_queries_peak_per_s) = time_queries;
        Telemetry::Leader {
            first_k: self.first_k,
            states: self.states,
            counters,
            done: self.done,
            loop_stats: self.loop_stats,
            delivery,
            handover: self.handover,
            term: self.term,
        }
    }
}

/// The leader: see the module documentation.
pub struct LeaderMachine {
    steps: u64,
    dt_s: f64,
    batch_len: usize,
    lockstep: bool,
    /// The followers that hear the leader, ascending: `reached`'s slots.
    hearing: Vec<u32>,
    trajectory: Trajectory,
    /// The leader's state at the step being done.
    state: LeaderState,
    phase: Phase,
    /// Real time: the run's epoch and step period on the timebase.
    epoch: Now,
    period: Duration,
    timer: Option<LoopTimer>,
    /// Lock-step: the newest step each hearing follower has published.
    reached: Vec<Option<u64>>,
    /// Per hearing follower, its messages counted in `reached`: signs that
    /// it lives ([`gate::Wait::alive`]).
    heard_from: Vec<u64>,
    /// The newest step the leader has published.
    published: u64,
    /// Lock-step: the wait for the window, once it waits.
    wait: Option<gate::Wait>,
    /// Lock-step: the messages the slowest follower may still lack.
    recent: Kept,
    /// Hearing followers that reported their final step.
    done: BTreeSet<u32>,
    counters: Counters,
    states: Vec<LeaderState>,
    first_k: u64,
    last_now: Now,
    transmit: VecDeque<Vec<u8>>,
    telemetry: VecDeque<LeaderBatch>,
    say: VecDeque<String>,
    /// The state of the last step done, until taken.
    latest: Option<(u64, LeaderState)>,
    /// A standby, until it takes over.
    standby: Option<Standby>,
    /// A standby that took the run over: when.
    took_over: Option<Handover>,
    /// This leader's term (0: a standby that has not taken over).
    term: u32,
    /// The step at which it stood down, having heard a higher term.
    stood_down_at: Option<u64>,
    /// A live leader's input (`cmd_vel`, `robot`; docs/model.md §18).
    steering: Option<Steering>,
}

impl LeaderMachine {
    /// The leader of `scenario`; it steps once [`LeaderMachine::start`] is called.
    pub fn new(scenario: &Scenario) -> Self {
        let g = &scenario.graph;
        let hearing: Vec<u32> = (0..g.len()).filter(|&i| g.hears_leader(i)).map(|i| g.id(i)).collect();
        let trajectory = scenario.leader();
        let state = trajectory.state(0.0);
        let batch_len = scenario.network.telemetry_batch.max(1) as usize;
        Self {
            steps: scenario.steps(),
            dt_s: scenario.dt_s,
            batch_len,
            lockstep: scenario.timing == Timing::Lockstep,
            reached: vec![None; hearing.len()],
            heard_from: vec![0; hearing.len()],
            hearing,
            trajectory,
            state,
            phase: Phase::Waiting,
            epoch: Now::ZERO,
            period: Duration::ZERO,
            timer: None,
            published: 0,
            wait: None,
            recent: Kept::new(gate::LEADER_KEPT),
            done: BTreeSet::new(),
            counters: Counters::default(),
            states: Vec::with_capacity(batch_len),
            first_k: 0,
            last_now: Now::ZERO,
            transmit: VecDeque::new(),
            telemetry: VecDeque::new(),
            say: VecDeque::new(),
            latest: None,
            standby: None,
            took_over: None,
            term: FIRST_TERM,
            stood_down_at: None,
            steering: Steering::of(scenario.leader_profile, Duration::from_secs_f64(scenario.leader_timeout_s))
                .map(|s| s.within(scenario.source.safety.as_ref().and_then(|s| s.arena))),
        }
    }

    /// A live leader (`leader.source = "cmd_vel"`): a velocity command
    /// heard at `now`, taken within the leader's limits for the steps to come.
    pub fn handle_command(&mut self, command: Velocity, now: Now) {
        if let Some(line) = self.steering.as_mut().and_then(|s| s.command(command, now)) {
            self.say.push_back(line);
        }
    }

    /// A live leader (`leader.source = "robot"`): the leader robot's
    /// odometry (its pose in the world, its twist) heard at `now`.
    pub fn handle_leader_odometry(&mut self, pose: Pose, twist: Velocity, now: Now) {
        if let Some(s) = self.steering.as_mut() {
            s.odometry(pose, twist, now);
        }
    }

    /// A live leader (`leader.source = "path"`): a planner's route (its
    /// points in the world), driven from the next step on.
    pub fn handle_path(&mut self, points: Vec<[f64; 2]>) {
        if let Some(line) = self.steering.as_mut().and_then(|s| s.route(points)) {
            self.say.push_back(line);
        }
    }

    /// What a live leader's source sent so far (None: a scripted leader).
    pub fn steering(&self) -> Option<&Steering> {
        self.steering.as_ref()
    }

    /// A standby leader of `scenario` (docs/model.md §14): it publishes
    /// nothing until the leader of the run has been silent for `after`
    /// ([`LeaderMachine::handle_start`], [`LeaderMachine::handle_leader`]); then it takes
    /// the run over at the step due, with the leader's own trajectory.
    pub fn standby(scenario: &Scenario, after: Duration) -> Self {
        let mut l = Self::new(scenario);
        l.standby = Some(Standby { after, start: None, heard: None, heard_at: Now::ZERO, term: 0 });
        l.term = 0;
        l
    }

    /// A standby heard the run's start at `now`: from then on the leader's
    /// silence counts.
    pub fn handle_start(&mut self, start: &Start, now: Now) {
        if let Some(s) = self.standby.as_mut().filter(|s| s.start.is_none()) {
            s.start = Some(start.clone());
            s.heard_at = s.heard_at.max(now);
        }
    }

    /// A message on the leader's key from another process, at `now`. A
    /// standby: the leader is alive, and has published that step (a step of
    /// the run), in that term. A leader: one of a higher term took the run
    /// over while this one was cut off (or thought the leader gone): this
    /// one stands down (docs/model.md §14).
    pub fn handle_leader(&mut self, bytes: &[u8], now: Now) {
        let Ok(m) = wire::decode(bytes) else { return };
        if m.header.sender != wire::LEADER_ID || m.header.step > self.steps {
            return;
        }
        let Some(s) = self.standby.as_mut() else {
            if m.term > self.term {
                let k = m.header.step;
                self.stand_down(format!(
                    "leader (term {}): a leader of term {} is heard on the run's key (its step {k}): this one \
                     stands down and ends",
                    self.term, m.term
                ));
            }
            return;
        };
        if m.term < s.term {
            return;
        }
        let k = match m.term > s.term {
            true => m.header.step,
            false => s.heard.map_or(m.header.step, |h| h.max(m.header.step)),
        };
        (s.heard, s.heard_at, s.term, self.published) = (Some(k), now, m.term, k);
    }

    /// This leader's term (0: a standby that has not taken over).
    pub fn term(&self) -> u32 {
        self.term
    }

    /// The step at which this standby took the run over, once it has.
    pub fn took_over(&self) -> Option<u64> {
        self.took_over.map(|h| h.at_k)
    }

    /// A standby that leads the run from its start, the leader having gone
    /// before it began: said in every telemetry batch as a handover at step
    /// 0 with nothing heard (no gap: no leader message was due).
    pub fn led_by_a_standby_from_the_start(&mut self) {
        self.took_over = Some(Handover { heard: None, at_k: 0 });
        self.term = FIRST_TERM + 1;
    }

    /// Another process leads in a higher term (or the same term, and it
    /// outranks this one): this one ends, saying `why`; its last batch to
    /// the monitor says at which step it stood down. Once only, and not
    /// after the run's end.
    pub fn stand_down(&mut self, why: String) {
        let k = match self.phase {
            Phase::Stepping(k) => k,
            Phase::Waiting => 0,
            Phase::Lingering(_) | Phase::Done(_) => return,
        };
        self.say.push_back(why);
        self.stood_down_at = Some(k);
        if self.standby.is_none() {
            self.batch(k, false);
        }
        self.phase = Phase::Done(Ok(()));
    }

    /// The followers that hear the leader, ascending.
    pub fn hearing(&self) -> &[u32] {
        &self.hearing
    }

    /// The run begins: `start` as announced, at `now`. Publishes step 0.
    pub fn start(&mut self, start: &Start, now: Now) {
        self.last_now = now;
        self.pace(start);
        self.publish(0, now);
        self.phase = Phase::Stepping(0);
    }

    /// A standby: when the leader's silence will have lasted its wait. In
    /// real time the silence counts from the epoch at the earliest (the
    /// leader publishes step 0 at the start, step 1 at the epoch).
    fn standby_wake(&self) -> Option<Now> {
        let s = self.standby.as_ref()?;
        let start = s.start.as_ref()?;
        let epoch = Duration::from_nanos(start.epoch_unix_ns);
        let since = if self.lockstep { s.heard_at } else { s.heard_at.max(epoch) };
        Some(since + s.after)
    }

    /// Real time: the run's epoch and step period on the timebase.
    fn pace(&mut self, start: &Start) {
        if !self.lockstep {
            self.epoch = Duration::from_nanos(start.epoch_unix_ns);
            self.period = Duration::from_secs_f64(self.dt_s / start.scale());
            self.timer = Some(LoopTimer::new(self.period.as_secs_f64()));
        }
    }

    /// A standby whose leader has been silent long enough: the run is over
    /// (nothing to take over), or this machine takes it over.
    fn standby_timeout(&mut self, now: Now) {
        let Some(s) = self.standby.as_ref() else { return };
        let Some(wake) = self.standby_wake() else { return };
        let Some(start) = s.start.clone().filter(|_| now >= wake) else { return };
        let (heard, silent, heard_term) = (s.heard, now - s.heard_at, s.term);
        self.standby = None;
        self.term = heard_term.max(FIRST_TERM) + 1;
        self.pace(&start);
        let k = match self.lockstep {
            true => heard.unwrap_or(0),
            false if now < self.epoch => 0,
            false => self.steps.min(((now - self.epoch).as_nanos() / self.period.as_nanos().max(1)) as u64 + 1),
        };
        let heard_s = heard.map_or("nothing heard from it".to_string(), |h| format!("the newest heard: step {h}"));
        if heard == Some(self.steps) || (!self.lockstep && now >= self.due(self.steps)) {
            self.say.push_back(format!(
                "leader (standby): the run ended with its leader ({heard_s}); nothing to take over"
            ));
            self.phase = Phase::Done(Ok(()));
            return;
        }
        self.say.push_back(format!(
            "leader (standby): the leader silent for {:.3} s ({heard_s}): taking the run over at step {k} (t = {} s) \
             in term {}",
            silent.as_secs_f64(),
            k as f64 * self.dt_s,
            self.term
        ));
        let back = (RECORD_BACK.as_secs_f64() / self.dt_s).round() as u64 + 2 * self.batch_len as u64;
        self.took_over = Some(Handover { heard, at_k: k });
        self.take_over(k, heard.map_or(0, |h| h.saturating_sub(back)), now);
    }

    /// Takes the run over at step k: the trajectory replayed from step 0
    /// (the state the leader that is gone had at k, bit for bit), step k
    /// published, the states from `record_from` on queued for the monitor
    /// and, in lock-step, the messages before k kept for repeats.
    fn take_over(&mut self, k: u64, record_from: u64, now: Now) {
        self.first_k = record_from;
        for j in 0..k {
            if j >= record_from {
                self.states.push(self.state);
                if self.states.len() >= self.batch_len {
                    self.batch(j + 1, false);
                }
            }
            if self.lockstep && j + gate::LEADER_KEPT as u64 >= k {
                self.publish(j, now);
                self.transmit.clear();
            }
            self.trajectory.advance(&self.state, self.dt_s);
            self.state = self.trajectory.state((j + 1) as f64 * self.dt_s);
        }
        self.counters = Counters::default();
        self.publish(k, now);
        self.last_now = now;
        self.phase = Phase::Stepping(k);
    }

    /// A message on the estimate key of follower `key_id`: how far it has
    /// reached, counted by [`note_reached`]. Whether the step the machine
    /// waits for may now go (wake the loop).
    pub fn handle_estimate(&mut self, key_id: Option<u32>, bytes: &[u8]) -> bool {
        let Some(slot) = key_id.and_then(|id| self.hearing.iter().position(|&h| h == id)) else { return false };
        let Ok(m) = wire::decode(bytes) else { return false };
        if !note_reached(&mut self.reached, slot, key_id, &m.header, self.published) {
            return false;
        }
        self.heard_from[slot] += 1;
        self.may_step()
    }

    /// Hearing follower `id` reported its final step (lock-step).
    pub fn handle_done(&mut self, id: u32) {
        if self.hearing.contains(&id) {
            self.done.insert(id);
        }
    }

    /// Hearing follower `id` left the run (lock-step: its last telemetry
    /// said so): the window no longer waits for it, nor does the end.
    pub fn handle_gone(&mut self, id: u32) {
        let Some(slot) = self.hearing.iter().position(|&h| h == id) else { return };
        self.reached[slot] = Some(u64::MAX);
        self.done.insert(id);
    }

    /// Does what is due at `now`: at most one step, or a wait's repeat,
    /// warning or end.
    pub fn handle_timeout(&mut self, now: Now) {
        self.last_now = now;
        match self.phase {
            Phase::Waiting => self.standby_timeout(now),
            Phase::Done(_) => {}
            Phase::Stepping(k) => self.step_if_due(k, now),
            Phase::Lingering(_) => self.linger(now),
        }
    }

    /// When the machine next wants [`LeaderMachine::handle_timeout`]: None before
    /// the start and after the end; `Now::ZERO` (at once) when a lock-step
    /// step may go.
    pub fn poll_timeout(&self) -> Option<Now> {
        match &self.phase {
            Phase::Waiting => self.standby_wake(),
            Phase::Done(_) => None,
            Phase::Stepping(k) if !self.lockstep => Some(self.due(*k)),
            Phase::Stepping(_) if self.may_step() => Some(Now::ZERO),
            Phase::Stepping(_) => Some(self.wait.as_ref().map_or(Now::ZERO, gate::Wait::next_wake)),
            Phase::Lingering(w) => Some(w.next_wake().min(self.last_now + gate::LINGER_LOOK_EVERY)),
        }
    }

    /// The next estimate message to publish (encoded, stamped).
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.transmit.pop_front()
    }

    /// The next telemetry batch for the monitor.
    pub fn poll_telemetry(&mut self) -> Option<LeaderBatch> {
        self.telemetry.pop_front()
    }

    /// The next line for the operator (stderr).
    pub fn poll_say(&mut self) -> Option<String> {
        self.say.pop_front()
    }

    /// The step and state of the last step done, once (for a node that
    /// publishes each step as it happens, such as its ROS 2 topics).
    pub fn take_state(&mut self) -> Option<(u64, LeaderState)> {
        self.latest.take()
    }

    /// The end of the run: None while it runs; Err says why it failed.
    pub fn outcome(&self) -> Option<&Result<(), String>> {
        self.phase.outcome()
    }

    /// The step the machine does next (or waits for).
    pub fn step(&self) -> Option<u64> {
        self.phase.step()
    }

    /// What the leader sent and repeated so far.
    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// Real time: when step k is due on the timebase.
    fn due(&self, k: u64) -> Now {
        gate::due(self.epoch, self.period, k)
    }

    /// Lock-step: whether the current step may publish its successor (the
    /// window rule, [`gate::leader_needs`]); the last step always may.
    fn may_step(&self) -> bool {
        match self.phase {
            Phase::Stepping(k) if k < self.steps => {
                gate::leader_needs(k + 1).is_none_or(|need| gate::window_open(&self.reached, need))
            }
            Phase::Stepping(_) => true,
            _ => false,
        }
    }

    fn step_if_due(&mut self, k: u64, now: Now) {
        if self.lockstep {
            if !self.may_step() {
                return self.wait_for_window(k, now);
            }
            self.wait = None;
        } else {
            let due = self.due(k);
            if now < due {
                return;
            }
            // Lateness against the step's own due time.
            if let Some(t) = self.timer.as_mut() {
                t.push(k, k as f64 * self.period.as_secs_f64() + (now - due).as_secs_f64());
            }
        }
        let last = k == self.steps;
        self.states.push(self.state);
        self.latest = Some((k, self.state));
        if !last {
            let t = (k + 1) as f64 * self.dt_s;
            if let Some(s) = self.steering.as_mut() {
                let (input, said) = s.input(now, t);
                self.trajectory.steer(input);
                self.say.extend(said);
            }
            self.trajectory.advance(&self.state, self.dt_s);
            self.state = self.trajectory.state(t);
            self.publish(k + 1, now);
        } else if let Some(s) = &self.steering {
            self.say.push_back(s.summary());
        }
        if self.states.len() >= self.batch_len || last {
            self.batch(k + 1, last);
        }
        self.phase = match last {
            false => Phase::Stepping(k + 1),
            true if self.lockstep => Phase::Lingering(gate::Wait::new(now, gate::LINGER_REPEAT_EVERY, LINGER)),
            true => Phase::Done(Ok(())),
        };
    }

    /// Step k's message (the current state), stamped `now`, to publish; kept
    /// for repeats in lock-step.
    fn publish(&mut self, k: u64, now: Now) {
        let bytes = wire::encode(&EstimateMsg {
            header: Header {
                version: FORMAT_VERSION,
                sender: wire::LEADER_ID,
                step: k,
                time_s: k as f64 * self.dt_s,
                sent_ns: i64::try_from(now.as_nanos()).unwrap_or(i64::MAX),
            },
            state: self.state,
            fresh: true,
            term: self.term,
        });
        self.published = k;
        self.counters.sent += 1;
        if self.lockstep {
            self.recent.push(k, bytes.clone());
        }
        self.transmit.push_back(bytes);
    }

    /// The states since the last batch, up to `end_k`, for the monitor.
    fn batch(&mut self, end_k: u64, last: bool) {
        self.telemetry.push_back(LeaderBatch {
            first_k: self.first_k,
            end_k,
            states: std::mem::take(&mut self.states),
            counters: self.counters,
            done: last,
            loop_stats: if last { self.timer.as_ref().map(LoopTimer::stats) } else { None },
            handover: self.took_over,
            term: Term { number: self.term, stood_down_at: self.stood_down_at },
        });
        self.first_k = end_k;
    }

    /// Lock-step: the window is shut; repeat what the slowest hearing
    /// follower may lack, warn once, or give up after [`gate::LEADER_STALL`].
    fn wait_for_window(&mut self, k: u64, now: Now) {
        let need = gate::leader_needs(k + 1).unwrap_or(0);
        // The followers that hold the window up, alive while they speak.
        let signs: u64 = (self.reached.iter().zip(&self.heard_from))
            .filter(|(r, _)| !r.is_some_and(|s| s >= need))
            .map(|(_, n)| n)
            .sum();
        let wait = self.wait.get_or_insert_with(|| gate::Wait::new(now, gate::LEADER_REPEAT_EVERY, gate::LEADER_STALL));
        wait.alive(now, signs);
        let waited = wait.waited(now);
        let gate::WaitStep::Wait { repeat, warn } = wait.poll(now) else {
            let why =
                format!("followers stopped before step {need} (no progress for {} s)", gate::LEADER_STALL.as_secs());
            self.phase = Phase::Done(Err(why));
            return;
        };
        let slowest = gate::slowest_step(&self.reached);
        if warn {
            self.say.push_back(format!(
                "leader: waiting {:.0} s at step {} for the followers that hear it (slowest at step {slowest}, \
                 {WINDOW} steps behind allowed); repeating steps {} on",
                waited.as_secs_f64(),
                k + 1,
                gate::leader_from_step(slowest)
            ));
        }
        if repeat {
            let n = self.repeat(slowest);
            self.counters.republished += n;
        }
    }

    /// Lock-step, after the last step: a follower may still wait for one of
    /// the last messages (lost?): repeat what the slowest may have missed
    /// until every hearing follower is done, for at most [`LINGER`].
    fn linger(&mut self, now: Now) {
        let Phase::Lingering(wait) = &mut self.phase else { return };
        let step = wait.poll(now);
        match step {
            _ if self.done.len() >= self.hearing.len() => self.phase = Phase::Done(Ok(())),
            gate::WaitStep::Over => self.phase = Phase::Done(Ok(())),
            gate::WaitStep::Wait { repeat, .. } => {
                if repeat {
                    self.repeat(gate::slowest_step(&self.reached));
                }
            }
        }
    }

    /// Repeats the kept messages the slowest hearing follower may lack; how many.
    fn repeat(&mut self, slowest: u64) -> u64 {
        let before = self.transmit.len();
        self.transmit.extend(self.recent.leader_repeats(slowest).cloned());
        let n = (self.transmit.len() - before) as u64;
        self.counters.sent += n;
        n
    }
}

/// Lock-step: files a hearing follower's message (`slot`, received on the
/// key of `key_id`) in how far each has reached. Counted only from the
/// follower itself and for a step it can have reached: at most one past the
/// leader's newest (`published`). Whether it was counted.
pub fn note_reached(reached: &mut [Option<u64>], slot: usize, key_id: Option<u32>, h: &Header, published: u64) -> bool {
    if key_id != Some(h.sender) || h.step > published.saturating_add(1) || slot >= reached.len() {
        return false;
    }
    reached[slot] = Some(reached[slot].map_or(h.step, |x| x.max(h.step)));
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn header(sender: u32, step: u64) -> Header {
        Header { version: FORMAT_VERSION, sender, step, time_s: 0.0, sent_ns: 0 }
    }

    fn paper(sets: &[&str]) -> Scenario {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        Scenario::load(&path, &sets).expect("the paper scenario")
    }

    fn start0() -> Start {
        Start { fingerprint: 0, epoch_unix_ns: 1_000_000_000_000, time_scale: 1.0, sent_ns: 0, absent: Vec::new() }
    }

    /// A follower's message for `step`.
    fn from(id: u32, step: u64) -> Vec<u8> {
        wire::encode(&EstimateMsg { header: header(id, step), state: LeaderState::default(), fresh: true, term: 0 })
    }

    /// Hands the machine `now` as long as something is due at once.
    fn run_while_due(l: &mut LeaderMachine, now: Now) {
        for _ in 0..100_000 {
            l.handle_timeout(now);
            if l.poll_timeout() != Some(Now::ZERO) {
                return;
            }
        }
    }

    /// Every message the leader publishes, by step.
    fn steps_sent(l: &mut LeaderMachine) -> Vec<u64> {
        std::iter::from_fn(|| l.poll_transmit())
            .map(|b| wire::decode(&b).expect("the leader's own").header.step)
            .collect()
    }

    #[test]
    fn a_follower_counts_only_on_its_own_key_and_never_beyond_the_leader() {
        let mut r = vec![None, None];
        assert!(note_reached(&mut r, 0, Some(1), &header(1, 5), 10));
        assert!(!note_reached(&mut r, 0, Some(2), &header(1, 7), 10), "forged: on another follower's key");
        assert!(!note_reached(&mut r, 0, None, &header(1, 7), 10), "a key that is no id");
        assert!(!note_reached(&mut r, 0, Some(1), &header(1, 12), 10), "beyond the leader's newest + 1");
        assert!(note_reached(&mut r, 0, Some(1), &header(1, 11), 10), "one past the leader's newest");
        assert!(note_reached(&mut r, 0, Some(1), &header(1, 3), 10), "an old repeat");
        assert_eq!(r, [Some(11), None], "the furthest step counts");
        assert!(!note_reached(&mut r, 5, Some(1), &header(1, 3), 10), "a slot out of range");
    }

    /// The window rule in the machine, to the step: with its hearing
    /// follower silent the leader publishes steps 0..WINDOW and no more;
    /// each step the follower publishes lets exactly one more go. Moving
    /// the rule by one step either way fails here.
    #[test]
    fn in_lockstep_the_leader_runs_exactly_its_window_ahead_of_the_slowest() {
        let mut l = LeaderMachine::new(&paper(&["duration=2", "timing=lockstep"]));
        assert_eq!(l.hearing(), [1], "in the paper's graph only follower 1 hears the leader");
        let t0 = Duration::from_secs(1);
        l.start(&start0(), t0);
        run_while_due(&mut l, t0);
        let sent = steps_sent(&mut l);
        assert_eq!(sent.last(), Some(&(WINDOW - 1)), "published without a word from follower 1: {} steps", sent.len());
        assert_eq!(l.step(), Some(WINDOW - 1), "waits to publish step {WINDOW}");
        assert_ne!(l.poll_timeout(), Some(Now::ZERO), "nothing is due");
        // Follower 1's step 0 lets step WINDOW go, its step 1 step WINDOW + 1.
        for k in 0..2 {
            assert!(l.handle_estimate(Some(1), &from(1, k)), "the step the leader waits for wakes it");
            run_while_due(&mut l, t0);
            assert_eq!(steps_sent(&mut l), [WINDOW + k], "after follower 1's step {k}");
        }
        // A forged claim (on follower 2's key, or beyond the leader) opens nothing.
        assert!(!l.handle_estimate(Some(2), &from(1, 50)), "follower 2 does not hear the leader");
        assert!(!l.handle_estimate(Some(1), &from(1, 10_000)), "beyond the leader's newest + 1");
        run_while_due(&mut l, t0);
        assert_eq!(steps_sent(&mut l), Vec::<u64>::new());
    }

    /// While the window is shut the leader repeats what the slowest may
    /// lack every 200 ms, warns once after 5 s and gives up after 60 s,
    /// naming the step.
    #[test]
    fn a_shut_window_repeats_warns_and_gives_up() {
        let mut l = LeaderMachine::new(&paper(&["duration=2", "timing=lockstep"]));
        let t0 = Duration::from_secs(1);
        l.start(&start0(), t0);
        l.handle_estimate(Some(1), &from(1, 0));
        run_while_due(&mut l, t0);
        assert_eq!(steps_sent(&mut l).last(), Some(&WINDOW));
        let mut t = t0;
        while l.outcome().is_none() && t < t0 + Duration::from_secs(120) {
            t = l.poll_timeout().expect("waiting").max(t);
            l.handle_timeout(t);
        }
        let c = l.counters();
        // Every 200 ms for 60 s, every kept step from slowest − 2 on (0..=WINDOW).
        let each = WINDOW + 1;
        assert!((299 * each..=301 * each).contains(&c.republished), "repeats over 60 s: {}", c.republished);
        let said: Vec<String> = std::iter::from_fn(|| l.poll_say()).collect();
        assert_eq!(said.len(), 1, "one warning: {said:?}");
        let why = l.outcome().cloned().expect("done").expect_err("a stall fails");
        assert!(why.contains("before step 1 (") && (t - t0).as_secs() == 60, "{why} after {:?}", t - t0);
    }

    /// Real time: a step is done when due on the timebase, not before;
    /// every message is stamped with the time it was published.
    #[test]
    fn in_real_time_a_step_goes_when_due_and_is_stamped_then() {
        let mut l = LeaderMachine::new(&paper(&["duration=1", "timing=realtime"]));
        let epoch = Duration::from_nanos(start0().epoch_unix_ns);
        l.start(&start0(), epoch - Duration::from_millis(500));
        assert_eq!(steps_sent(&mut l), [0], "step 0's message goes at the start");
        assert_eq!(l.poll_timeout(), Some(epoch));
        l.handle_timeout(epoch - Duration::from_micros(1));
        assert_eq!(l.poll_transmit(), None, "not due yet");
        let at = epoch + Duration::from_micros(300);
        l.handle_timeout(at);
        let m = wire::decode(&l.poll_transmit().expect("step 1")).expect("decodes");
        assert_eq!((m.header.step, m.header.sent_ns), (1, at.as_nanos() as i64));
        assert_eq!(l.poll_timeout(), Some(epoch + Duration::from_millis(1)), "step 1 is due 1 ms later");
        let mut t = at;
        while l.outcome().is_none() {
            t = l.poll_timeout().expect("running").max(t);
            l.handle_timeout(t);
        }
        let batches: Vec<LeaderBatch> = std::iter::from_fn(|| l.poll_telemetry()).collect();
        let states: usize = batches.iter().map(|b| b.states.len()).sum();
        assert_eq!(states as u64, 1_001, "every step's state reaches the monitor");
        assert!(batches.last().is_some_and(|b| b.done && b.loop_stats.is_some()));
    }

    /// A cmd_vel leader (docs/model.md §18) stands until the first command,
    /// drives each clipped to its limits, and stops at the first step
    /// computed more than its time-out after the newest: every state it
    /// sends is the unicycle integrated from what it took.
    #[test]
    fn a_commanded_leader_drives_what_it_hears_and_stops_on_silence() {
        let sets = ["duration=3", "timing=realtime", "leader.source=cmd_vel", "leader.speed=0.5", "leader.timeout=0.2"];
        let mut l = LeaderMachine::new(&paper(&sets));
        let epoch = Duration::from_nanos(start0().epoch_unix_ns);
        l.start(&start0(), epoch);
        let ms = Duration::from_millis;
        // 20 Hz from 0.5 s to 1.5 s, each beyond the speed limit: (1.0, 0.3) is taken as (0.5, 0.3).
        let commands: Vec<Now> = (0..=20).map(|i| epoch + ms(500 + 50 * i)).collect();
        let (mut t, mut next, mut states) = (epoch, 0, Vec::new());
        while l.outcome().is_none() {
            while next < commands.len() && commands[next] <= t {
                l.handle_command(Velocity::new(1.0, 0.3), commands[next]);
                next += 1;
            }
            l.handle_timeout(t);
            states.extend(std::iter::from_fn(|| l.poll_telemetry()).flat_map(|b| b.states));
            t = l.poll_timeout().map_or(t, |n| n.max(t)).min(commands.get(next).copied().unwrap_or(Now::MAX));
        }
        assert_eq!(states.len(), 3001);
        let moving: Vec<usize> = (0..states.len()).filter(|&k| states[k].v != 0.0).collect();
        let (first, last) = (moving[0], *moving.last().expect("it moved"));
        // Step k + 1's state is computed when step k is due (k ms after the epoch).
        assert_eq!(first, 501, "the first command (at 500 ms) drives step 501");
        assert_eq!(last, 1701, "the newest (at 1500 ms) goes stale 200 ms later");
        assert_eq!(moving.len(), last - first + 1, "no gap while commands come every 50 ms");
        assert!(moving.iter().all(|&k| (states[k].v, states[k].w) == (0.5, 0.3)), "clipped to 0.5 m/s");
        let mut model = formation_leader::Leader::new(
            formation_leader::Profile {
                trajectory: formation_leader::Trajectory::Line { speed_mps: 0.0 },
                ramp_s: 0.0,
            },
            paper(&[]).leader_pose,
        );
        for (k, s) in states.iter().enumerate() {
            assert_eq!(s.pose, model.pose, "step {k}: the pose is eq. 6 integrated from what it took");
            model.advance(s, 0.001);
        }
        let said: Vec<String> = std::iter::from_fn(|| l.poll_say()).collect();
        assert!(said.iter().any(|l| l.contains("beyond the leader's limits")), "{said:?}");
        assert!(said.iter().any(|l| l.contains("silent for 0.2 s at t = 1.70 s")), "{said:?}");
        assert!(said.last().is_some_and(|l| l.contains("21 commands taken") && l.contains("21 clipped")), "{said:?}");
    }

    /// The states of every message in `sent`, by step.
    fn states_of(sent: &[Vec<u8>]) -> Vec<(u64, LeaderState)> {
        sent.iter().map(|b| wire::decode(b).expect("the leader's own")).map(|m| (m.header.step, m.state)).collect()
    }

    /// Runs a real-time leader machine from `t` until `until` (or its end),
    /// feeding `standby` what it publishes; every message and batch.
    fn run_rt(
        l: &mut LeaderMachine,
        mut t: Now,
        until: Now,
        mut standby: Option<&mut LeaderMachine>,
    ) -> (Vec<Vec<u8>>, Now) {
        let mut sent = Vec::new();
        while l.outcome().is_none() && t <= until {
            l.handle_timeout(t);
            for b in std::iter::from_fn(|| l.poll_transmit()) {
                if let Some(s) = standby.as_deref_mut() {
                    s.handle_leader(&b, t);
                }
                sent.push(b);
            }
            t = l.poll_timeout().map_or(t, |n| n.max(t));
            if let Some(s) = standby.as_deref_mut() {
                s.handle_timeout(t);
            }
        }
        (sent, t)
    }

    /// A standby takes a real-time run over when the leader has been silent
    /// for its wait, at the step then due, and continues the leader's
    /// trajectory bit for bit: every message and every state it sends the
    /// monitor equals what the leader itself would have sent (a leader run
    /// without fault is the reference). It sends the monitor the states from
    /// 1 s and two batches before the newest step it heard.
    #[test]
    fn a_standby_takes_a_real_time_run_over_with_the_leaders_own_trajectory() {
        let s = paper(&["duration=3", "timing=realtime"]);
        let epoch = Duration::from_nanos(start0().epoch_unix_ns);
        let mut whole = LeaderMachine::new(&s);
        whole.start(&start0(), epoch);
        let (reference, _) = run_rt(&mut whole, epoch, epoch + Duration::from_secs(10), None);
        let reference_states: Vec<LeaderState> =
            std::iter::from_fn(|| whole.poll_telemetry()).flat_map(|b| b.states).collect();

        let after = Duration::from_millis(200);
        let mut standby = LeaderMachine::standby(&s, after);
        let mut leader = LeaderMachine::new(&s);
        leader.start(&start0(), epoch);
        standby.handle_start(&start0(), epoch);
        assert_eq!(standby.poll_timeout(), Some(epoch + after), "the leader's silence counts from the start");
        // The leader dies during step 1,500 (t = 1.5 s).
        let (_, died) = run_rt(&mut leader, epoch, epoch + Duration::from_millis(1500), Some(&mut standby));
        assert!(standby.took_over().is_none() && steps_sent(&mut standby).is_empty(), "silent while the leader runs");
        let wake = standby.poll_timeout().expect("watching");
        assert_eq!(wake, died + after - Duration::from_millis(1), "the last message was heard 1 ms before");
        let (sent, _) = run_rt(&mut standby, wake, epoch + Duration::from_secs(10), None);
        let k = standby.took_over().expect("took over");
        // Step 1,500 done at 1.5 s published step 1,501, the newest heard;
        // at 1.7 s step 1,700 is done and step 1,701 published.
        assert_eq!(k, 1_701, "the message due 200 ms after the newest heard (1,501)");
        let said: Vec<String> = std::iter::from_fn(|| standby.poll_say()).collect();
        assert!(said[0].contains("taking the run over at step 1701") && said[0].contains("step 1501"), "{said:?}");
        let ours = states_of(&sent);
        assert_eq!(ours.first().map(|m| m.0), Some(k));
        assert_eq!(ours.last().map(|m| m.0), Some(s.steps()));
        let theirs = states_of(&reference);
        for (step, state) in &ours {
            assert_eq!(Some(state), theirs.iter().find(|m| m.0 == *step).map(|m| &m.1), "step {step}");
        }
        let batches: Vec<LeaderBatch> = std::iter::from_fn(|| standby.poll_telemetry()).collect();
        let from = batches[0].first_k;
        assert_eq!(from, 1_501 - 1_000 - 2 * s.network.telemetry_batch.max(1) as u64);
        let states: Vec<LeaderState> = batches.into_iter().flat_map(|b| b.states).collect();
        assert_eq!(&states[..], &reference_states[from as usize..], "the states sent the monitor");
    }

    /// One leader (docs/model.md §14): a leader cut off from its standby
    /// for 1 s goes on stepping; the standby takes the run over in term 2;
    /// when the cut ends, the leader hears term 2 on its key and stands
    /// down at once (one line, a last batch that says at which step), and
    /// the standby, hearing term 1, does not. Whatever the steps say: the
    /// old leader's are ahead of the standby's here (its clock ran 0.5 s
    /// ahead while cut off), and it still stands down.
    #[test]
    fn a_leader_cut_off_and_back_stands_down_for_the_standbys_higher_term() {
        let s = paper(&["duration=4", "timing=realtime"]);
        let epoch = Duration::from_nanos(start0().epoch_unix_ns);
        let mut standby = LeaderMachine::standby(&s, Duration::from_millis(500));
        let mut leader = LeaderMachine::new(&s);
        assert_eq!((leader.term(), standby.term()), (FIRST_TERM, 0));
        leader.start(&start0(), epoch);
        standby.handle_start(&start0(), epoch);
        let (_, cut) = run_rt(&mut leader, epoch, epoch + Duration::from_millis(1000), Some(&mut standby));
        // Cut off: the leader steps on, unheard, with its clock 0.5 s ahead.
        let ahead = Duration::from_millis(500);
        let (unheard, _) = run_rt(&mut leader, cut + ahead, cut + ahead + Duration::from_millis(1000), None);
        let wake = standby.poll_timeout().expect("watching");
        let (sent, back) = run_rt(&mut standby, wake, cut + Duration::from_millis(1000), None);
        assert_eq!(standby.term(), FIRST_TERM + 1, "the standby leads the next term");
        let first = wire::decode(&sent[0]).expect("the standby's");
        assert_eq!(first.term, 2);
        let said: Vec<String> = std::iter::from_fn(|| standby.poll_say()).collect();
        assert!(said[0].contains("in term 2"), "{said:?}");
        // Back: each hears the other's messages.
        let old = wire::decode(unheard.last().expect("sent")).expect("the leader's");
        assert!(old.header.step > first.header.step + 500 && old.term == 1, "{:?} / {:?}", old.header, first.header);
        standby.handle_leader(unheard.last().expect("sent"), back);
        assert!(standby.outcome().is_none(), "the standby does not stand down for term 1");
        leader.handle_leader(sent.last().expect("sent"), back);
        assert_eq!(leader.outcome(), Some(&Ok(())), "the leader stands down");
        let said: Vec<String> = std::iter::from_fn(|| leader.poll_say()).collect();
        assert_eq!(said.len(), 1, "{said:?}");
        assert!(said[0].contains("leader (term 1): a leader of term 2") && said[0].contains("stands down"), "{said:?}");
        let last = std::iter::from_fn(|| leader.poll_telemetry()).last().expect("a last batch");
        let at = last.term.stood_down_at.expect("says where it stood down");
        assert_eq!((last.term.number, last.end_k), (1, at), "{:?}", last.term);
        leader.stand_down("twice".into());
        assert_eq!(leader.poll_say(), None, "once only");
        // A leader's own term, or a lower one, changes nothing.
        let mut other = LeaderMachine::new(&s);
        other.start(&start0(), epoch);
        other.handle_leader(unheard.last().expect("sent"), epoch);
        assert!(other.outcome().is_none(), "term 1 beside term 1 (the claims' nonce decides)");
    }

    /// A standby whose leader ends the run does not take it over; one whose
    /// leader is silent before the start waits for the start.
    #[test]
    fn a_standby_does_not_take_over_a_run_that_ended_or_has_not_started() {
        let s = paper(&["duration=0.5", "timing=realtime"]);
        let epoch = Duration::from_nanos(start0().epoch_unix_ns);
        let mut standby = LeaderMachine::standby(&s, Duration::from_millis(200));
        assert_eq!(standby.poll_timeout(), None, "no start heard: nothing to watch");
        standby.handle_timeout(epoch + Duration::from_secs(100));
        assert!(standby.took_over().is_none() && standby.outcome().is_none());
        let mut leader = LeaderMachine::new(&s);
        leader.start(&start0(), epoch);
        // Heard 0.5 s before the epoch (the leader's step 0 then, its step 1
        // at the epoch): the silence counts from the epoch.
        standby.handle_start(&start0(), epoch - Duration::from_millis(500));
        assert_eq!(standby.poll_timeout(), Some(epoch + Duration::from_millis(200)));
        standby.handle_timeout(epoch - Duration::from_millis(1));
        assert!(standby.took_over().is_none(), "no takeover before the epoch");
        let (_, t) = run_rt(&mut leader, epoch, epoch + Duration::from_secs(10), Some(&mut standby));
        assert_eq!(leader.outcome(), Some(&Ok(())));
        standby.handle_timeout(t + Duration::from_secs(1));
        assert_eq!((standby.took_over(), standby.outcome()), (None, Some(&Ok(()))));
        assert!(steps_sent(&mut standby).is_empty());
        let said = standby.poll_say().expect("a line");
        assert!(said.contains("the run ended with its leader"), "{said}");
    }

    /// Lock-step: a standby takes over at the newest step it heard, keeps
    /// the window's messages for repeats, and from there obeys the window
    /// rule like the leader.
    #[test]
    fn in_lockstep_a_standby_takes_over_at_the_newest_step_heard_and_keeps_the_window() {
        let s = paper(&["duration=2", "timing=lockstep"]);
        let t0 = Duration::from_secs(1);
        let mut leader = LeaderMachine::new(&s);
        let mut standby = LeaderMachine::standby(&s, Duration::from_millis(500));
        leader.start(&start0(), t0);
        standby.handle_start(&start0(), t0);
        // Follower 1 reaches step 99; the standby hears both.
        let mut sent: Vec<Vec<u8>> = Vec::new();
        for k in 0..=100 {
            run_while_due(&mut leader, t0);
            for b in std::iter::from_fn(|| leader.poll_transmit()) {
                standby.handle_leader(&b, t0);
                sent.push(b);
            }
            if k < 100 {
                leader.handle_estimate(Some(1), &from(1, k));
                standby.handle_estimate(Some(1), &from(1, k));
            }
        }
        let newest = states_of(&sent).last().expect("sent").0;
        assert_eq!(newest, 100 + WINDOW - 1, "the leader ran its window ahead of follower 1's step 99");
        standby.handle_timeout(t0 + Duration::from_millis(499));
        assert!(standby.took_over().is_none(), "not before its wait");
        standby.handle_timeout(t0 + Duration::from_millis(500));
        assert_eq!(standby.took_over(), Some(newest));
        let t1 = t0 + Duration::from_millis(500);
        run_while_due(&mut standby, t1);
        let ours = states_of(&std::iter::from_fn(|| standby.poll_transmit()).collect::<Vec<_>>());
        assert_eq!(ours.iter().map(|m| m.0).collect::<Vec<_>>(), [newest], "the window is shut: step {newest} again");
        assert_eq!(ours[0].1, states_of(&sent).last().expect("sent").1, "the leader's own state");
        // Follower 1's next step opens the window by one, as for the leader.
        standby.handle_estimate(Some(1), &from(1, 100));
        run_while_due(&mut standby, t1);
        assert_eq!(steps_sent(&mut standby), [newest + 1]);
        // While shut, it repeats what the slowest may lack: the kept messages.
        standby.handle_timeout(t1 + Duration::from_millis(250));
        let repeated = steps_sent(&mut standby);
        assert_eq!(repeated.first(), Some(&98), "from the slowest's step (100) − 2 on: {repeated:?}");
    }

    /// Lock-step: after the last step the leader lingers until every
    /// hearing follower is done, then ends.
    #[test]
    fn in_lockstep_the_leader_lingers_until_its_followers_are_done() {
        let s = paper(&["duration=0.01", "timing=lockstep"]);
        let mut l = LeaderMachine::new(&s);
        let t0 = Duration::from_secs(1);
        l.start(&start0(), t0);
        for _ in 0..=s.steps() {
            l.handle_timeout(t0);
        }
        assert!(l.outcome().is_none() && l.step().is_none(), "lingers after the last step");
        l.handle_timeout(t0 + Duration::from_millis(300));
        assert!(l.counters().sent > s.steps() + 1, "repeats while lingering");
        l.handle_done(1);
        l.handle_timeout(t0 + Duration::from_millis(310));
        assert_eq!(l.outcome(), Some(&Ok(())));
    }
}
