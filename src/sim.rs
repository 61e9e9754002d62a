//! The in-process simulator: the leader, every follower's brain and robot,
//! stepped in lock-step in SPEC §9's order. Deterministic: the same scenario
//! gives the same numbers, bit for bit.

use formation_agent::{Follower, Hearing, LeaderState, LinkLoss, Message};
use formation_leader::Leader;
use formation_plant::{NoiseSource, Pose, Robot, Velocity};
use formation_topology::Scenario;

use crate::record::{FollowerMetrics, FollowerSample, MetricsAccumulator, Row};

/// A run stopped because a state stopped being finite.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("follower {follower}: {quantity} is not finite at step {step} (t = {t_s} s); the run diverged")]
pub struct Diverged {
    pub follower: u32,
    pub step: u64,
    pub t_s: f64,
    pub quantity: &'static str,
}

/// One follower as the simulator holds it: the brain and its own robot and
/// noise generator.
pub struct SimFollower {
    pub brain: Follower,
    pub robot: Robot,
    pub noise: NoiseSource,
    /// z(k), the velocity measurement the brain folds in at step k.
    pub measurement: Velocity,
    pub metrics: MetricsAccumulator,
}

impl SimFollower {
    /// The follower at `index` of the scenario, at step 0. Its noise stream
    /// is seeded from (scenario seed, follower id), as in its own process.
    pub fn new(scenario: &Scenario, index: usize) -> Self {
        let spec = &scenario.followers[index];
        let brain = Follower::new(scenario.follower_config(index), scenario.initial_estimate(), spec.velocity);
        let robot = Robot::new(scenario.robot, scenario.disturbance, spec.pose, spec.velocity);
        Self {
            brain,
            robot,
            noise: NoiseSource::new(scenario.covariance, scenario.noise, scenario.seed, spec.id),
            // z(0) = ξ(0): the filter starts from ξ(0) and only `none` reads z(0).
            measurement: spec.velocity,
            metrics: MetricsAccumulator::for_scenario(scenario),
        }
    }

    /// A restarted agent's follower (SPEC §14): at step `k`, its robot
    /// stopped (v = ω = 0) at `pose`, a fresh brain that adopts its estimate
    /// from the first source it hears.
    pub fn resume(&mut self, k: u64, pose: Pose) {
        self.brain.resume_at(k);
        self.robot.pose = pose;
        self.robot.velocity = Velocity::default();
        self.measurement = Velocity::default();
    }

    /// One step of brain and robot with the leader's state (if heard) and the
    /// neighbours' messages; returns the sample of step k. The robot advances
    /// unless `last` (the final sample only computes outputs).
    pub fn step<'a, I>(
        &mut self,
        t_s: f64,
        dt_s: f64,
        leader: Option<&LeaderState>,
        neighbours: I,
        last: bool,
    ) -> (FollowerSample, Message)
    where
        I: IntoIterator<Item = &'a Message>,
        I::IntoIter: Clone,
    {
        let out = self.brain.step(&self.robot.pose, self.measurement, leader, neighbours);
        let sample = FollowerSample::new(&out, self.robot.pose, self.robot.velocity);
        if !last {
            let draw = self.noise.draw();
            self.measurement = self.robot.advance(out.torque, t_s, dt_s, draw);
        }
        (sample, out.next_message)
    }

    /// The first non-finite quantity of brain or robot.
    pub fn check_finite(&self) -> Result<(), &'static str> {
        self.brain.check_finite().map_err(|e| e.0)?;
        if !self.robot.pose.is_finite() {
            return Err("robot pose");
        }
        if !self.robot.velocity.is_finite() {
            return Err("robot velocity");
        }
        Ok(())
    }
}

/// SPEC §14 on the receiving side of one follower: the fault table's loss
/// decisions for each incoming link and what it holds from each source.
/// Slots are the neighbours in ascending id, then the leader if heard.
pub struct Reception {
    pub links: Vec<LinkLoss>,
    pub hearing: Hearing,
}

impl Reception {
    /// The follower at `index`'s reception, or `None` when no fault of the
    /// table touches its incoming links (then it hears every step-k message).
    pub fn new(scenario: &Scenario, index: usize) -> Option<Self> {
        let id = scenario.graph.id(index);
        let links: Vec<LinkLoss> = scenario.sources_of(index).iter().map(|&src| scenario.link_loss(src, id)).collect();
        if links.iter().all(LinkLoss::is_empty) {
            return None;
        }
        let hearing = Hearing::new(links.len(), scenario.silence_steps());
        Some(Self { links, hearing })
    }

    /// Step k's message of `slot` was sent: delivered unless the table removes it.
    pub fn offer(&mut self, slot: usize, k: u64, msg: &Message) {
        if !self.links[slot].lost(k) {
            self.hearing.deliver(slot, k, *msg);
        }
    }
}

/// Receives every sample of a run (recording, plotting, …).
pub trait Observer {
    fn leader(&mut self, _k: u64, _state: &LeaderState) -> std::io::Result<()> {
        Ok(())
    }
    fn follower(&mut self, _index: usize, _k: u64, _row: &Row, _last: bool) -> std::io::Result<()> {
        Ok(())
    }
}

/// Observes nothing (benchmarks, metrics only).
pub struct NoRecord;
impl Observer for NoRecord {}

/// Why a simulation stopped early.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Diverged(#[from] Diverged),
    #[error("writing the run folder: {0}")]
    Io(#[from] std::io::Error),
}

/// The whole formation in one process.
pub struct Simulation<'s> {
    scenario: &'s Scenario,
    leader: Leader,
    followers: Vec<SimFollower>,
    /// Every follower's message for the current step, by index.
    messages: Vec<Message>,
    next_messages: Vec<Message>,
    /// With `network.delay_steps` d > 0: the messages and the leader's
    /// state of the last d + 1 steps, step j at j mod (d + 1).
    past: Vec<(Vec<Message>, LeaderState)>,
    /// Per follower, `Some` where the fault table touches its incoming links.
    receptions: Vec<Option<Reception>>,
    /// The samples of the current step, by index (the parallel step's output).
    samples: Vec<FollowerSample>,
    /// Step the followers of a step on rayon's threads (see [`Simulation::set_parallel`]).
    parallel: bool,
    k: u64,
}

/// Slots of [`Simulation::past`]: d + 1 with a delay of d steps, else none.
fn delay_slots(s: &Scenario) -> usize {
    match s.network.delay_steps {
        0 => 0,
        d => d as usize + 1,
    }
}

/// Follower `i`'s step k: its inputs (through its reception when the fault
/// table touches it), brain and robot; its sample and its next message.
#[allow(clippy::too_many_arguments)]
fn step_follower(
    s: &Scenario,
    i: usize,
    f: &mut SimFollower,
    rx: &mut Option<Reception>,
    messages: &[Message],
    leader: &LeaderState,
    k: u64,
    sent_k: u64,
    last: bool,
) -> (FollowerSample, Message) {
    let (t, dt) = (k as f64 * s.dt_s, s.dt_s);
    match rx {
        None => {
            let heard = s.graph.hears_leader(i).then_some(leader);
            let neighbours = s.graph.neighbours(i).iter().map(|&j| &messages[j]);
            f.step(t, dt, heard, neighbours, last)
        }
        Some(rx) => {
            // SPEC §14: deliver what the table lets through, then
            // hear each source's newest message within the timeout.
            let ns = s.graph.neighbours(i);
            // (`sent_k`: the step the inputs were sent at, k − delay.)
            for (slot, &j) in ns.iter().enumerate() {
                rx.offer(slot, sent_k, &messages[j]);
            }
            let heard = if s.graph.hears_leader(i) {
                rx.offer(ns.len(), sent_k, &Message::fresh(*leader));
                rx.hearing.heard(ns.len(), sent_k).map(|m| &m.state)
            } else {
                None
            };
            let hearing = &rx.hearing;
            let neighbours = (0..ns.len()).filter_map(|slot| hearing.heard(slot, sent_k));
            f.step(t, dt, heard, neighbours, last)
        }
    }
}

impl<'s> Simulation<'s> {
    pub fn new(scenario: &'s Scenario) -> Self {
        let followers: Vec<SimFollower> =
            (0..scenario.followers.len()).map(|i| SimFollower::new(scenario, i)).collect();
        let messages: Vec<Message> = followers.iter().map(|f| f.brain.tagged_message()).collect();
        let receptions = (0..followers.len()).map(|i| Reception::new(scenario, i)).collect();
        Self {
            scenario,
            leader: scenario.leader(),
            next_messages: messages.clone(),
            past: vec![(messages.clone(), LeaderState::default()); delay_slots(scenario)],
            messages,
            followers,
            receptions,
            samples: vec![FollowerSample::default(); scenario.followers.len()],
            parallel: false,
            k: 0,
        }
    }

    /// Steps the followers of each step on rayon's threads (the current
    /// pool: `ThreadPool::install` chooses how many). The followers of a step
    /// are independent once the step's messages are known, and each one's
    /// arithmetic is the same, so the results are bit for bit the
    /// single-thread run's; samples still reach the observer in index order.
    /// (The parallel step allocates in rayon's scheduler; the sequential one
    /// allocates nothing.)
    pub fn set_parallel(&mut self, on: bool) {
        self.parallel = on;
    }

    /// Steps done so far.
    pub fn step_index(&self) -> u64 {
        self.k
    }

    pub fn followers(&self) -> &[SimFollower] {
        &self.followers
    }

    /// Every follower's metrics around each fault window, by id.
    pub fn outages(&self) -> std::collections::BTreeMap<u32, Vec<crate::outage::OutageMetrics>> {
        self.followers.iter().map(|f| (f.brain.id(), f.metrics.outages())).collect()
    }

    /// Runs to t = T, calling `progress(k)` every 1000 steps.
    pub fn run(
        &mut self,
        observer: &mut impl Observer,
        mut progress: impl FnMut(u64),
    ) -> Result<Vec<FollowerMetrics>, SimError> {
        let steps = self.scenario.steps();
        while self.k <= steps {
            self.step(observer)?;
            if self.k % 1000 == 0 {
                progress(self.k);
            }
        }
        Ok(self.followers.iter().map(|f| f.metrics.finish()).collect())
    }

    /// One step k of SPEC §9 for the whole formation.
    pub fn step(&mut self, observer: &mut impl Observer) -> Result<(), SimError> {
        let s = self.scenario;
        let (k, dt) = (self.k, s.dt_s);
        let t = k as f64 * dt;
        let last = k == s.steps();
        let leader = self.leader.state(t);
        observer.leader(k, &leader)?;
        // The inputs: step k's messages and leader state, or with a delay
        // of d steps those of step k − d (step 0's before step d).
        let (inputs, heard_leader, sent_k) = if self.past.is_empty() {
            (&self.messages, &leader, k)
        } else {
            let slots = self.past.len() as u64;
            let now = &mut self.past[(k % slots) as usize];
            now.0.copy_from_slice(&self.messages);
            now.1 = leader;
            let sent_k = k.saturating_sub(slots - 1);
            let then = &self.past[(sent_k % slots) as usize];
            (&then.0, &then.1, sent_k)
        };
        if self.parallel {
            use rayon::prelude::*;
            let messages = inputs;
            let leader_ref = heard_leader;
            self.followers
                .par_iter_mut()
                .zip(self.receptions.par_iter_mut())
                .zip(self.next_messages.par_iter_mut())
                .zip(self.samples.par_iter_mut())
                .enumerate()
                .for_each(|(i, (((f, rx), next), sample))| {
                    (*sample, *next) = step_follower(s, i, f, rx, messages, leader_ref, k, sent_k, last);
                });
        } else {
            for (i, f) in self.followers.iter_mut().enumerate() {
                let (sample, next) =
                    step_follower(s, i, f, &mut self.receptions[i], inputs, heard_leader, k, sent_k, last);
                self.samples[i] = sample;
                self.next_messages[i] = next;
            }
        }
        // In index order, as a sequential run: metrics, the observer, and
        // the first follower that diverged.
        for (i, f) in self.followers.iter_mut().enumerate() {
            let row = Row::new(&self.samples[i], &leader, s.followers[i].offset, dt);
            f.metrics.push(k, &row);
            observer.follower(i, k, &row, last)?;
            f.check_finite().map_err(|quantity| Diverged { follower: s.followers[i].id, step: k, t_s: t, quantity })?;
        }
        std::mem::swap(&mut self.messages, &mut self.next_messages);
        self.leader.advance(&leader, dt);
        self.k += 1;
        Ok(())
    }
}
