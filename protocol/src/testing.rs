//! The formation's own machines on virtual time, for tests (quinn's
//! `tests/util.rs` `Pair` is the model): the real leader
//! ([`crate::leader::LeaderMachine`]) and one real follower machine
//! ([`crate::follower::FollowerMachine`]) per follower of a scenario, with the
//! simulator's bodies, over a network of queues that can lose packets,
//! close a node's links or delay them. No sockets, no threads, no clock.
//!
//! [`World::step`] moves virtual time to the next moment something is due
//! (a machine's wake-up or a packet's arrival) and lets every machine do
//! it; [`World::drive`] steps until every machine is done. [`World::tick`]
//! moves by a fixed amount instead, for a test that watches the run as it
//! goes.

use std::collections::BTreeMap;
use std::ops::Range;
use std::time::Duration;

use crate::wire::{self, LEADER_ID};
use formation_record::FollowerSample;
use formation_scenario::Scenario;
use formation_sim::SimFollower;

use crate::barrier::Start;
use crate::counters::Counters;
use crate::follower::{FollowerMachine, Options};
use crate::leader::LeaderMachine;
use crate::telemetry::{Delivery, NetEvent, Telemetry};
use crate::Now;

/// The run's epoch on the virtual timebase.
pub const EPOCH: Now = Duration::from_secs(1_000);

/// A deterministic packet-loss draw (xorshift), so a failure replays.
struct Draws(u64);

impl Draws {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// What the network does to the packets of one node's links (0: the leader).
#[derive(Clone, Default)]
pub struct Faults {
    /// Physical loss on every link of `node` while the virtual time is in range.
    pub loss: Option<(u32, f64, Range<Now>)>,
    /// Links of `node` closed (their queues dropped) while in range.
    pub closed: Option<(u32, Range<Now>)>,
    /// Every packet takes this long.
    pub latency: Duration,
    /// The leader's stamps jump by this much from the given time on (its
    /// clock steps; what it decides is unchanged).
    pub leader_clock_step: Option<(Now, Duration)>,
}

/// Packets in flight, by (from, to), with their arrival time.
type Queues = BTreeMap<(u32, u32), Vec<(Now, Vec<u8>)>>;

/// The network: what is in flight, and what it does to it.
struct Network {
    queues: Queues,
    draws: Draws,
    faults: Faults,
}

impl Network {
    fn touches(node: u32, from: u32, to: u32) -> bool {
        from == node || to == node
    }

    fn send(&mut self, now: Now, from: u32, to: u32, bytes: &[u8]) {
        if let Some((node, p, r)) = &self.faults.loss {
            if Self::touches(*node, from, to) && r.contains(&now) && self.draws.next() < *p {
                return;
            }
        }
        if let Some((node, r)) = &self.faults.closed {
            if Self::touches(*node, from, to) && r.contains(&now) {
                return;
            }
        }
        self.queues.entry((from, to)).or_default().push((now + self.faults.latency, bytes.to_vec()));
    }

    /// What reaches `to` by `now`; a closed link drops what it held.
    fn deliver(&mut self, to: u32, now: Now) -> Vec<(u32, Vec<u8>)> {
        if let Some((node, r)) = &self.faults.closed {
            if r.contains(&now) {
                let node = *node;
                self.queues.retain(|&(a, b), _| !Self::touches(node, a, b));
            }
        }
        let mut out = Vec::new();
        for (&(from, dest), q) in self.queues.iter_mut() {
            if dest == to {
                let due = q.iter().take_while(|(at, _)| *at <= now).count();
                out.extend(q.drain(..due).map(|(_, b)| (from, b)));
            }
        }
        out
    }

    /// The earliest arrival still in flight.
    fn next_arrival(&self) -> Option<Now> {
        self.queues.values().filter_map(|q| q.first().map(|(at, _)| *at)).min()
    }

    /// The leader's message as its stepped clock stamps it.
    fn stamp(&self, now: Now, bytes: Vec<u8>) -> Vec<u8> {
        match self.faults.leader_clock_step {
            Some((at, by)) if now >= at => match wire::decode(&bytes) {
                Ok(mut m) => {
                    m.header.sent_ns += by.as_nanos() as i64;
                    wire::encode(&m)
                }
                Err(_) => bytes,
            },
            _ => bytes,
        }
    }
}

/// A scenario's leader and followers and the network, on virtual time.
pub struct World {
    pub scenario: Scenario,
    pub followers: Vec<FollowerMachine>,
    pub leader: LeaderMachine,
    net: Network,
    pub now: Now,
    pub start: Start,
    /// Every follower's telemetry so far, by index.
    pub telemetry: Vec<Vec<Telemetry>>,
    /// The leader's telemetry so far.
    pub leader_telemetry: Vec<Telemetry>,
    /// Followers killed ([`World::kill`]), by index: no longer driven.
    dead: Vec<bool>,
}

/// The leader's start of a complete run at [`EPOCH`], time scale 1.
pub fn start_at_epoch() -> Start {
    Start { fingerprint: 0, epoch_unix_ns: EPOCH.as_nanos() as u64, time_scale: 1.0, sent_ns: 0, absent: Vec::new() }
}

impl World {
    /// The scenario's machines at [`EPOCH`], not started.
    pub fn new(scenario: Scenario, faults: Faults) -> Self {
        let opts = Options { stall_timeout: Duration::from_secs(60), physical_node_faults: false };
        let followers = (0..scenario.followers.len())
            .map(|i| FollowerMachine::new(&scenario, i, Box::new(SimFollower::new(&scenario, i)), &opts))
            .collect();
        let start = start_at_epoch();
        Self {
            leader: LeaderMachine::new(&scenario),
            net: Network { queues: BTreeMap::new(), draws: Draws(0x9e37_79b9_7f4a_7c15), faults },
            now: EPOCH,
            start,
            followers,
            telemetry: vec![Vec::new(); scenario.followers.len()],
            leader_telemetry: Vec::new(),
            dead: vec![false; scenario.followers.len()],
            scenario,
        }
    }

    /// Every machine hears the start now.
    pub fn start_all(&mut self) {
        let now = self.now;
        self.leader.start(&self.start, now);
        for f in &mut self.followers {
            f.start(&self.start, None, now);
        }
        self.flush();
    }

    /// Follower `i`'s id.
    pub fn id(&self, i: usize) -> u32 {
        self.scenario.graph.id(i)
    }

    /// Who hears node `from` (0: the leader): the followers whose sources
    /// it is, and the leader for a follower that hears it (the lock-step window).
    pub fn listeners(&self, from: u32) -> Vec<u32> {
        let mut to: Vec<u32> = (0..self.followers.len())
            .filter(|&i| !self.dead[i] && self.followers[i].source_ids().contains(&from))
            .map(|i| self.id(i))
            .collect();
        if from != LEADER_ID && self.leader.hearing().contains(&from) {
            to.push(LEADER_ID);
        }
        to
    }

    /// Every machine's answers onto the network and into the telemetry.
    fn flush(&mut self) {
        let now = self.now;
        let to = self.listeners(LEADER_ID);
        while let Some(bytes) = self.leader.poll_transmit() {
            let bytes = self.net.stamp(now, bytes);
            for &t in &to {
                self.net.send(now, LEADER_ID, t, &bytes);
            }
        }
        while let Some(b) = self.leader.poll_telemetry() {
            self.leader_telemetry.push(b.into_telemetry(Delivery::default(), (0, 0)));
        }
        while self.leader.poll_say().is_some() {}
        for i in 0..self.followers.len() {
            if self.dead[i] {
                continue;
            }
            let from = self.id(i);
            let to = self.listeners(from);
            while let Some(bytes) = self.followers[i].poll_transmit() {
                for &t in &to {
                    self.net.send(now, from, t, &bytes);
                }
            }
            while let Some(b) = self.followers[i].poll_telemetry() {
                self.telemetry[i].push(b.into_telemetry(Delivery::default(), None));
            }
            while self.followers[i].poll_say().is_some() {}
        }
    }

    /// Everything due at `now`: the leader first (what it publishes at a
    /// step's due time is on the way before the followers' step), then each
    /// follower, each machine until it waits; then who is done. Whether a
    /// machine did anything.
    fn run_due(&mut self) -> bool {
        let now = self.now;
        let mut busy = false;
        for (from, bytes) in self.net.deliver(LEADER_ID, now) {
            self.leader.handle_estimate(Some(from), &bytes);
            busy = true;
        }
        for _ in 0..100_000 {
            match self.leader.poll_timeout() {
                Some(at) if at <= now => self.leader.handle_timeout(now),
                _ => break,
            }
            busy = true;
            self.flush();
        }
        for i in 0..self.followers.len() {
            if self.dead[i] {
                continue;
            }
            let id = self.id(i);
            for (from, bytes) in self.net.deliver(id, now) {
                self.followers[i].handle_estimate(Some(from), &bytes, Some(now));
                busy = true;
            }
            for _ in 0..10_000 {
                match self.followers[i].poll_timeout() {
                    Some(at) if at <= now => self.followers[i].handle_timeout(now),
                    _ => break,
                }
                busy = true;
                self.flush();
            }
        }
        // Lock-step: tell every machine which followers reported their final step.
        let steps = self.scenario.steps();
        let finished: Vec<u32> = (0..self.followers.len())
            .filter(|&i| self.telemetry[i].iter().any(|t| t.reports_final_step(self.id(i), steps)))
            .map(|i| self.id(i))
            .collect();
        for &id in &finished {
            self.leader.handle_done(id);
            for f in &mut self.followers {
                f.handle_done(id);
            }
        }
        self.flush();
        busy
    }

    /// The next moment something is due: a machine's wake-up or an arrival.
    fn next_due(&mut self) -> Option<Now> {
        let dead = &self.dead;
        let wakes =
            self.followers.iter_mut().enumerate().filter(|(i, _)| !dead[*i]).filter_map(|(_, f)| f.poll_timeout());
        let leader = self.leader.poll_timeout();
        wakes.chain(leader).chain(self.net.next_arrival()).min()
    }

    /// Does what is due now, or else moves virtual time to the next moment
    /// something is and does it. False once nothing is left to do.
    pub fn step(&mut self) -> bool {
        if self.run_due() {
            return true;
        }
        match self.next_due() {
            Some(at) => {
                self.now = self.now.max(at);
                self.run_due();
                true
            }
            None => false,
        }
    }

    /// Steps until every machine is done, nothing is left to do, or `limit`
    /// of virtual time has passed.
    pub fn drive(&mut self, limit: Duration) {
        let end = self.now + limit;
        // (Bounded: a machine that is always due would hold virtual time still.)
        for _ in 0..100_000_000u64 {
            if self.now >= end || self.all_done() || !self.step() {
                return;
            }
        }
    }

    /// One tick of `tick` virtual time: everything due by then.
    pub fn tick(&mut self, tick: Duration) {
        self.now += tick;
        while self.run_due() {}
    }

    /// Ticks until every machine is done or `limit` of virtual time passed.
    pub fn run(&mut self, tick: Duration, limit: Duration) {
        let end = self.now + limit;
        while self.now < end && !self.all_done() {
            self.tick(tick);
        }
    }

    fn all_done(&self) -> bool {
        self.leader.outcome().is_some() && self.living().all(|f| f.outcome().is_some())
    }

    /// The followers not killed.
    fn living(&self) -> impl Iterator<Item = &FollowerMachine> {
        self.followers.iter().zip(&self.dead).filter(|(_, d)| !**d).map(|(f, _)| f)
    }

    /// Follower `id`'s process killed now, its last messages on the way
    /// to `reached` only (a peer's fan-out cut mid-way: each link has its
    /// own queue): the rest of what it sent is lost, and it is no longer
    /// driven.
    pub fn kill(&mut self, id: u32, reached: &[u32]) {
        let i = (0..self.followers.len()).find(|&i| self.id(i) == id).expect("a follower of the scenario");
        self.dead[i] = true;
        self.net.queues.retain(|&(from, to), _| to != id && (from != id || reached.contains(&to)));
    }

    /// The monitor's part of a death (`formation_protocol::died`): what
    /// every follower still running holds of `id`, the step named from it
    /// with its last messages, applied by each of them and the leader.
    pub fn name_death(&mut self, id: u32) -> crate::died::Died {
        let holdings: Vec<crate::died::Holding> = self.living().map(|f| f.holding_of(id, 0)).collect();
        let died = crate::died::Died::named(0, id, &holdings);
        for (f, _) in self.followers.iter_mut().zip(&self.dead).filter(|(_, d)| !**d) {
            f.handle_died(&died);
        }
        self.leader.handle_gone(id);
        self.flush();
        died
    }

    /// Every follower's outcome, by index (None: still running).
    pub fn outcomes(&self) -> Vec<Option<Result<(), String>>> {
        self.followers.iter().map(|f| f.outcome().cloned()).collect()
    }

    /// Whether the leader and every follower not killed completed.
    pub fn all_ok(&self) -> bool {
        matches!(self.leader.outcome(), Some(Ok(()))) && self.living().all(|f| matches!(f.outcome(), Some(Ok(()))))
    }

    /// Follower `i`'s samples, in step order.
    pub fn samples(&self, i: usize) -> Vec<FollowerSample> {
        self.telemetry[i]
            .iter()
            .flat_map(|t| match t {
                Telemetry::Follower { samples, .. } => samples.clone(),
                _ => Vec::new(),
            })
            .collect()
    }

    /// Follower `i`'s network events.
    pub fn events(&self, i: usize) -> Vec<NetEvent> {
        self.telemetry[i]
            .iter()
            .flat_map(|t| match t {
                Telemetry::Follower { events, .. } => events.clone(),
                _ => Vec::new(),
            })
            .collect()
    }

    /// Follower `i`'s counters as its last telemetry says.
    pub fn counters(&self, i: usize) -> Counters {
        match self.telemetry[i].last() {
            Some(Telemetry::Follower { counters, .. }) => *counters,
            _ => Counters::default(),
        }
    }
}
