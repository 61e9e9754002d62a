//! One follower's brain: estimator, kinematic and dynamic controller and
//! velocity filter, stepped in docs/model.md §9's order. The plant is not in here:
//! the follower sees only its measured pose and the velocity measurement,
//! so a real robot driver can take the simulated robot's place. With a
//! velocity-commanded robot (docs/model.md §15) the brain stops at the
//! kinematic command: the robot's own loop follows it.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::deadlock::DeadlockState;
use crate::dynamic::{self, DynamicGains, DynamicKind, DynamicState};
use crate::estimator::{self, EstimatorGains};
use crate::filter::{FilterParams, VelocityFilter};
use crate::guard::{self, Guard, GuardStep, Nearby};
use crate::kinematic::{self, BodyError, KinematicGains, KinematicKind};
use crate::links::{self, Message, RejoinPolicy, RejoinRule};
use crate::slot::{self, Frame, Slots};
use formation_leader::LeaderState;
use formation_plant::{Drive, Pose, RobotParams, Torque, Velocity};

/// The filter-model fault of section IV: from `time_s` on, the filter's model
/// uses m_f = mass_factor · m and I_f = inertia_factor · I. The robot itself
/// does not change.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fault {
    pub time_s: f64,
    pub mass_factor: f64,
    pub inertia_factor: f64,
}

/// The control law, filter and step that every follower of a scenario
/// shares, validated. Followers hold it behind an `Arc`: one copy however
/// many followers run.
#[derive(Clone, Debug, PartialEq)]
pub struct ControlParams {
    pub estimator: EstimatorGains,
    pub kinematic: KinematicKind,
    pub kinematic_gains: KinematicGains,
    pub dynamic: DynamicKind,
    pub dynamic_gains: DynamicGains,
    pub filter: FilterParams,
    /// The nominal model the controller's torque mapping and the filter use.
    pub model: RobotParams,
    pub fault: Option<Fault>,
    /// What a follower does when it hears a source again after isolation (docs/model.md §14).
    pub rejoin: RejoinRule,
    pub dt_s: f64,
    /// How the robot is driven: torques from the dynamic controller, or the
    /// kinematic command itself (docs/model.md §15; the lag is the robot's,
    /// the brain does not use it).
    pub drive: Drive,
    /// The base's limits and the safety filter between the kinematic
    /// command and the robot (docs/model.md §16; off in the paper's scenario).
    pub guard: Guard,
    /// The frame the followers' offsets are written in (docs/model.md §17).
    pub frame: Frame,
}

/// One follower's place in the formation and the shared control parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct FollowerConfig {
    pub id: u32,
    /// Formation offset (Δx_i, Δy_i), m, in `control.frame`, over the run
    /// (one, or one per shape; docs/model.md §17).
    pub slots: Slots,
    /// a_i0: does this follower hear the leader?
    pub hears_leader: bool,
    pub control: Arc<ControlParams>,
}

impl ControlParams {
    /// The first step at which the fault is in force: the first k with
    /// k Δt ≥ t_fault, decided on step indices so that a t_fault on the grid
    /// is not missed by one step through rounding of k Δt.
    pub fn fault_step(&self) -> Option<u64> {
        self.fault.map(|f| crate::math::step_at(f.time_s, self.dt_s))
    }

    /// The model the filter uses at step k (nominal, or faulty from t_fault).
    pub fn filter_model_at(&self, k: u64) -> RobotParams {
        match (self.fault, self.fault_step()) {
            (Some(f), Some(from)) if k >= from => RobotParams {
                mass_kg: self.model.mass_kg * f.mass_factor,
                inertia_kgm2: self.model.inertia_kgm2 * f.inertia_factor,
                ..self.model
            },
            _ => self.model,
        }
    }
}

/// What one step produced.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepOutput {
    /// The step these outputs belong to.
    pub k: u64,
    /// The estimate (P_ir, v_ir, ω_ir) at k that the outputs were computed from.
    pub estimate: LeaderState,
    /// (x̂, ŷ, θ̂).
    pub body_error: BodyError,
    /// (v_c, ω_c), as the robot gets it: after the limits and the safety
    /// filter (docs/model.md §16) when the scenario has them.
    pub command: Velocity,
    /// What the limits and the filter did to the controller's command
    /// (None: the scenario has neither).
    pub guard: Option<GuardStep>,
    /// (v̇_c, ω̇_c), backward differences.
    pub command_rate: Velocity,
    /// (v̂, ω̂), the filter's estimate at k (with a velocity-commanded
    /// robot, the measurement z(k)).
    pub velocity_estimate: Velocity,
    /// τ(k) (zero with a velocity-commanded robot).
    pub torque: Torque,
    /// How many sources (leader + neighbours) entered the estimator at k.
    pub sources: u32,
    /// Step k ended an isolation of at least `rejoin.after_steps` steps
    /// (and, under `adopt`, the estimate was replaced before the outputs).
    pub rejoined: bool,
    /// The message to publish for step k+1: P_ir(k+1), v_ir(k+1), ω_ir(k+1)
    /// and the Ṗ_ir computed at k, with its freshness (docs/model.md §14).
    pub next_message: Message,
}

/// A state that stopped being finite: which quantity.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NonFinite(pub &'static str);

/// One follower's brain.
#[derive(Clone, Debug)]
pub struct Follower {
    pub config: FollowerConfig,
    /// (P_ir, Ṗ_ir of the last step, v_ir, ω_ir): also this follower's message.
    estimate: LeaderState,
    /// V_s of the bioinspired backstepping.
    v_s: f64,
    dynamic: DynamicState,
    filter: VelocityFilter,
    last_command: Option<Velocity>,
    /// τ(k−1) and k−1, for the filter's prediction at the next step.
    last_torque: Torque,
    last_k: u64,
    next_k: u64,
    /// Consecutive steps, up to k − 1, at which no source was heard.
    silent_steps: u64,
    /// Adopt at the next step that hears a source, whatever the policy (a
    /// restarted agent has no estimate to keep).
    adopt_pending: bool,
    /// The estimate has been held through an isolation (or is a restart's
    /// placeholder) and has not since been taken from a fresh source: its
    /// message is not fresh (docs/model.md §14), and under `adopt` it is replaced as
    /// soon as the leader or a fresh neighbour is heard.
    stale: bool,
    /// Steps held by the safety filter, or the sidestep under way (eq. G6).
    deadlock: DeadlockState,
}

impl Follower {
    /// A follower at step 0 with its initial leader estimate and the robot's
    /// initial velocity ξ(0) (ζ̂(0) = ξ(0), docs/model.md §8). Ṗ_ir starts at zero.
    pub fn new(config: FollowerConfig, initial_estimate: LeaderState, initial_velocity: Velocity) -> Self {
        let filter = VelocityFilter::new(&config.control.filter, initial_velocity);
        let estimate = LeaderState { pose_rate: Pose::default(), ..initial_estimate };
        Self {
            config,
            estimate,
            v_s: 0.0,
            dynamic: DynamicState::default(),
            filter,
            last_command: None,
            last_torque: Torque::default(),
            last_k: 0,
            next_k: 0,
            silent_steps: 0,
            adopt_pending: false,
            stale: false,
            deadlock: DeadlockState::default(),
        }
    }

    pub fn id(&self) -> u32 {
        self.config.id
    }

    /// The step the next call to [`Follower::step`] computes.
    pub fn next_step(&self) -> u64 {
        self.next_k
    }

    /// docs/model.md §13's message for the coming step: P_ir(k), Ṗ_ir(k−1), v_ir(k), ω_ir(k).
    pub fn message(&self) -> LeaderState {
        self.estimate
    }

    /// The message with its freshness (docs/model.md §14), as neighbours receive it.
    pub fn tagged_message(&self) -> Message {
        Message { state: self.estimate, fresh: !self.stale }
    }

    /// Takes the estimate from the first step that hears a source, as
    /// `adopt` does, whatever `network.rejoin` says (docs/model.md §14's restarted agent).
    pub fn adopt_on_next_source(&mut self) {
        self.adopt_pending = true;
        self.stale = true;
    }

    /// A restarted agent (docs/model.md §14): the follower as new (fresh filter with
    /// ζ̂ = 0, P = R, fresh controller with the first-step rules of section
    /// 7) at step `k`, taking its estimate from the first step that hears a
    /// source, as `adopt` does.
    pub fn resume_at(&mut self, k: u64) {
        self.filter = VelocityFilter::new(&self.config.control.filter, Velocity::default());
        self.next_k = k;
        self.last_k = k.saturating_sub(1);
        self.adopt_pending = true;
        self.v_s = 0.0;
        self.dynamic = DynamicState::default();
        self.last_command = None;
        self.last_torque = Torque::default();
        self.silent_steps = 0;
        self.stale = true;
        self.deadlock = DeadlockState::default();
    }

    /// Still waiting for a source to take its estimate from (see
    /// [`Follower::adopt_on_next_source`]).
    pub fn adopting(&self) -> bool {
        self.adopt_pending
    }

    /// Consecutive steps, up to the last one computed, at which no source was
    /// heard (isolation when at least `rejoin.after_steps`).
    pub fn silent_steps(&self) -> u64 {
        self.silent_steps
    }

    /// The filter's current estimate ζ̂ (and its gains, for telemetry).
    pub fn filter(&self) -> &VelocityFilter {
        &self.filter
    }

    /// One step k (docs/model.md §9).
    ///
    /// `pose` is the robot's pose at k and `z` the velocity measurement z(k)
    /// (ignored at k = 0, where ζ̂(0) = ξ(0)); `leader` is the leader's state
    /// at k if this follower hears it (and has it); `neighbours` yields the
    /// neighbours' messages for k in ascending id.
    ///
    /// In order: the outputs are computed from the states at k; the
    /// filter folds in z(k) (predict with τ(k−1) and the model valid at
    /// t_(k−1), update with z(k)) before the dynamic controller reads it;
    /// the estimator's rates; then every state advances to k+1.
    ///
    /// With [`Drive::Velocity`] (docs/model.md §15) the step ends at the
    /// kinematic command: no filter and no dynamic controller run, the
    /// velocity estimate is z(k) (even at k = 0) and the torque is zero.
    /// `pose` and `z` are then the robot's odometry.
    ///
    /// docs/model.md §14: the sources not heard at k are simply not passed. After at
    /// least `rejoin.after_steps` steps without any source, the first step
    /// that hears one is a rejoin, and the estimate is stale; under `adopt`
    /// it is replaced by [`links::adopted`] at the first step that hears the
    /// leader or a fresh neighbour (until then the law runs on what is heard).
    pub fn step<'a, I>(&mut self, pose: &Pose, z: Velocity, leader: Option<&LeaderState>, neighbours: I) -> StepOutput
    where
        I: IntoIterator<Item = &'a Message>,
        I::IntoIter: Clone,
    {
        self.step_near(pose, pose.theta.sin_cos(), z, leader, neighbours, Nearby::NONE)
    }

    /// [`Follower::step`] with the other robots' poses the safety filter
    /// keeps this robot away from (docs/model.md §16; ignored when the
    /// scenario has no filter), and `heading = pose.theta.sin_cos()` already
    /// computed (a simulated robot advancing from the same pose needs it
    /// too): the same numbers, one sin/cos fewer.
    pub fn step_near<'a, I>(
        &mut self,
        pose: &Pose,
        heading: (f64, f64),
        z: Velocity,
        leader: Option<&LeaderState>,
        neighbours: I,
        nearby: Nearby<'_>,
    ) -> StepOutput
    where
        I: IntoIterator<Item = &'a Message>,
        I::IntoIter: Clone,
    {
        let neighbours = neighbours.into_iter();
        let cfg = &*self.config.control;
        let dt = cfg.dt_s;
        let k = self.next_k;
        let leader = if self.config.hears_leader { leader } else { None };
        let isolated = self.silent_steps >= cfg.rejoin.after_steps;
        let mut rejoined = false;
        if (self.stale && cfg.rejoin.policy == RejoinPolicy::Adopt) || self.adopt_pending {
            if let Some(adopted) = links::adopted(leader, neighbours.clone()) {
                self.estimate = adopted;
                self.adopt_pending = false;
                self.stale = false;
                rejoined = true;
            }
        }
        let estimate = self.estimate;
        // docs/model.md §14, `adopt`: a fresh estimate leaves stale ones out of its sums.
        let only_fresh = cfg.rejoin.policy == RejoinPolicy::Adopt && !self.stale;
        let neighbours = neighbours.filter(move |m| m.fresh || !only_fresh);

        // Kinematic controller (eq. 29, 35–36) on the slot (docs/model.md §17).
        let (body_error, v_ir, w_ir, slot_rate) = tracked(cfg.frame, &estimate, self.config.slots.at(k), pose, heading);
        let requested = kinematic::command(cfg.kinematic, &cfg.kinematic_gains, self.v_s, &body_error, v_ir, w_ir);
        // Limits and safety filter (docs/model.md §16): what the robot gets.
        let (command, guard) = match cfg.guard.is_off() {
            true => (requested, None),
            false => {
                let (c, g) = guarded(&cfg.guard, &mut self.deadlock, requested, pose, (&body_error, slot_rate), nearby);
                (c, Some(g))
            }
        };
        let command_rate = match self.last_command {
            Some(prev) => Velocity::new((command.v - prev.v) / dt, (command.w - prev.w) / dt),
            None => Velocity::default(),
        };

        let (velocity_estimate, torque) = match cfg.drive {
            Drive::Torque => {
                let last = (self.last_k, self.last_torque);
                torque_step(cfg, &mut self.filter, &mut self.dynamic, k, last, z, command, command_rate)
            }
            // docs/model.md §15: the robot follows (v_c, ω_c) itself.
            Drive::Velocity { .. } => (z, Torque::default()),
        };

        // Estimator (eq. 11–15).
        let rates = estimator::rates(&cfg.estimator, &estimate, leader, neighbours.map(|m| &m.state));
        rejoined |= isolated && rates.sources > 0;
        self.silent_steps = if rates.sources == 0 { self.silent_steps.saturating_add(1) } else { 0 };
        if self.silent_steps >= cfg.rejoin.after_steps {
            self.stale = true;
        } else if rates.sources > 0 && cfg.rejoin.policy == RejoinPolicy::Consensus && !self.adopt_pending {
            // `consensus` rejoins by the law itself: heard again, fresh again.
            self.stale = false;
        }

        // Advance every state to k+1.
        if cfg.kinematic == KinematicKind::Bio {
            self.v_s = cfg.kinematic_gains.shunting.advance(self.v_s, body_error.x, dt);
        }
        estimator::advance(&mut self.estimate, &rates, dt);
        self.last_command = Some(command);
        self.last_torque = torque;
        self.last_k = k;
        self.next_k = k + 1;

        StepOutput {
            k,
            estimate,
            body_error,
            command,
            guard,
            command_rate,
            velocity_estimate,
            torque,
            sources: rates.sources,
            rejoined,
            next_message: self.tagged_message(),
        }
    }

    /// The first state that is not finite, if any.
    pub fn check_finite(&self) -> Result<(), NonFinite> {
        let checks: [(&'static str, bool); 5] = [
            ("leader estimate", self.estimate.is_finite()),
            ("backstepping shunting state V_s", self.v_s.is_finite()),
            ("sliding-mode state", self.dynamic.is_finite()),
            ("filtered velocity", self.filter.estimate.iter().chain(&self.filter.p).all(|x| x.is_finite())),
            ("torque", self.last_torque.is_finite()),
        ];
        match checks.iter().find(|(_, ok)| !ok) {
            Some((what, _)) => Err(NonFinite(what)),
            None => Ok(()),
        }
    }
}

/// The guard's command and what it did (docs/model.md §16), with the
/// deadlock rule (eq. G6) around it where the scenario has one: during a
/// sidestep the wish is the point stepping right of the others, and each
/// step says whether it was held.
#[inline]
fn guarded(
    guard: &Guard,
    deadlock: &mut DeadlockState,
    requested: Velocity,
    pose: &Pose,
    (body_error, slot_rate): (&BodyError, [f64; 2]),
    nearby: Nearby<'_>,
) -> (Velocity, GuardStep) {
    let Some((rule, s)) = guard.safety.and_then(|s| s.deadlock.map(|r| (r, s))) else {
        return guard::apply(guard, requested, pose, nearby);
    };
    let clip = |c: Velocity| guard.limits.map_or(c, |l| l.clip(c));
    // What the filter is asked for (G1a applied, as `apply` applies it).
    let mut asked = clip(requested);
    let mut wish = requested;
    let mut sidestep = false;
    if deadlock.sidestepping() {
        let want = guard::point_velocity(&s, pose, asked);
        if let Some(u) = deadlock.wish(&rule, want, guard::crowd(&s, pose, nearby)) {
            // Into the limits with its direction kept (clipped channel by
            // channel, a sideways step, ω = u / l, would lose its way).
            let c = guard::from_point_velocity(&s, pose, u);
            wish = guard.limits.map_or(c, |l| l.scale(c));
            asked = clip(wish);
            sidestep = true;
        }
    }
    let (command, mut step) = guard::apply(guard, wish, pose, nearby);
    step.sidestep = sidestep;
    // Held against the slot, which moves (the leader's Ṗ_r): side by side
    // and level with it, two robots kept from crossing are held too.
    let asked_u = guard::point_velocity(&s, pose, asked);
    let cut = step.change / (asked_u[0] - slot_rate[0]).hypot(asked_u[1] - slot_rate[1]);
    let to_slot = body_error.x.hypot(body_error.y);
    step.deadlock = deadlock.after(&rule, to_slot, s.distance, cut, step.infeasible || step.blind);
    (command, step)
}

/// A torque-driven robot's step k (section III-E, eq. 37–43): the filter
/// folds in z(k) (at k = 0 without a filter the estimate is z itself), the
/// dynamic controller turns the command's error on the filtered velocity
/// into torques, and its state advances to k + 1. The filtered velocity and
/// the torques. (`last`: the previous step and its torques.)
#[inline]
#[allow(clippy::too_many_arguments)]
fn torque_step(
    cfg: &ControlParams,
    filter: &mut VelocityFilter,
    dynamic: &mut DynamicState,
    k: u64,
    (last_k, last_torque): (u64, Torque),
    z: Velocity,
    command: Velocity,
    command_rate: Velocity,
) -> (Velocity, Torque) {
    let dt = cfg.dt_s;
    if k > 0 {
        let model = cfg.filter_model_at(last_k);
        filter.update(&cfg.filter, &model, last_torque, dt, z);
    } else if cfg.filter.kind == crate::filter::FilterKind::None {
        filter.estimate = [z.v, z.w];
    }
    let velocity_estimate = filter.estimate();
    let e_eta = [command.v - velocity_estimate.v, command.w - velocity_estimate.w];
    let [a_v, a_w] =
        dynamic::accelerations(cfg.dynamic, &cfg.dynamic_gains, dynamic, e_eta, [command_rate.v, command_rate.w]);
    dynamic::advance(cfg.dynamic, &cfg.dynamic_gains, dynamic, e_eta, dt);
    (velocity_estimate, cfg.model.acceleration_to_torque(a_v, a_w))
}

/// What the kinematic controller tracks at a step: the body-frame error to
/// the slot at `offset` from the estimate, the slot's speed and turn rate,
/// and its velocity in the world (docs/model.md §17, eq. 17.1–17.3). In the
/// world frame these are the estimate's own, as eq. 28 has them.
#[inline]
fn tracked(
    frame: Frame,
    estimate: &LeaderState,
    offset: [f64; 2],
    pose: &Pose,
    heading: (f64, f64),
) -> (BodyError, f64, f64, [f64; 2]) {
    match frame {
        Frame::World => {
            let e = kinematic::body_error_with(&estimate.pose, offset, pose, heading);
            (e, estimate.v, estimate.w, [estimate.pose_rate.x, estimate.pose_rate.y])
        }
        Frame::Leader => {
            let r = slot::reference(Frame::Leader, estimate, offset);
            (kinematic::body_error_to(&r.pose, pose, heading), r.v, r.w, r.rate)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::links::{RejoinPolicy, RejoinRule};
    use crate::{FilterKind, Shunting};

    fn config(fault_time_s: f64, dt_s: f64) -> ControlParams {
        let shunting = Shunting { a: 4.0, b: 2.0, d: 2.0 };
        ControlParams {
            estimator: EstimatorGains { k: [1.0; 3], ka: [20.0; 2], kb: [5.0; 2] },
            kinematic: KinematicKind::Bio,
            kinematic_gains: KinematicGains { c1: 3.0, c2: 2.0, c3: 1.0, shunting },
            dynamic: DynamicKind::Bio,
            dynamic_gains: DynamicGains {
                ca: 3.0,
                cb: 3.0,
                shunting_v: shunting,
                shunting_w: shunting,
                k1: 3.0,
                k2: 3.0,
            },
            filter: FilterParams { kind: FilterKind::Asif, q: [1e-4; 2], r: [1e-4; 2], rho_max: [0.08; 2] },
            model: RobotParams { mass_kg: 10.0, inertia_kgm2: 5.0, wheel_radius_m: 0.05, half_axle_m: 0.2 },
            fault: Some(Fault { time_s: fault_time_s, mass_factor: 0.01, inertia_factor: 0.1 }),
            rejoin: RejoinRule::default(),
            dt_s,
            drive: Drive::Torque,
            guard: Guard::default(),
            frame: Frame::World,
        }
    }

    fn follower(policy: RejoinPolicy, after_steps: u64) -> Follower {
        let mut c = config(100.0, 1e-3);
        c.rejoin = RejoinRule { policy, after_steps };
        let cfg = FollowerConfig { id: 3, slots: Slots::fixed([7.0, -7.0]), hears_leader: false, control: Arc::new(c) };
        let start = LeaderState { pose: Pose::new(0.0, 3.0, 0.0), pose_rate: Pose::default(), v: 1.0, w: 0.0 };
        Follower::new(cfg, start, Velocity::default())
    }

    fn neighbour(x: f64) -> Message {
        Message::fresh(LeaderState {
            pose: Pose::new(x, 3.0, 0.0),
            pose_rate: Pose::new(1.0, 0.0, 0.0),
            v: 1.0,
            w: 0.0,
        })
    }

    /// Runs `silent` isolated steps, then one step hearing a neighbour at x = 5.
    fn isolate_then_hear(f: &mut Follower, silent: u64) -> (StepOutput, LeaderState) {
        let pose = Pose::new(7.0, -4.0, 0.0);
        for _ in 0..silent {
            let out = f.step(&pose, Velocity::default(), None, []);
            assert_eq!(out.sources, 0);
        }
        let before = f.message();
        let n = neighbour(5.0);
        (f.step(&pose, Velocity::default(), None, [&n]), before)
    }

    #[test]
    fn isolation_holds_the_rates_and_dead_reckons() {
        let mut f = follower(RejoinPolicy::Consensus, 100);
        let n = neighbour(1.0);
        f.step(&Pose::default(), Velocity::default(), None, [&n]);
        let rate = f.message().pose_rate;
        let (v, w) = (f.message().v, f.message().w);
        let x0 = f.message().pose.x;
        for _ in 0..50 {
            f.step(&Pose::default(), Velocity::default(), None, []);
        }
        let m = f.message();
        assert_eq!((m.pose_rate, m.v, m.w), (rate, v, w), "isolated: Ṗ_ir, v_ir, ω_ir held");
        assert!((m.pose.x - (x0 + 50.0 * 1e-3 * rate.x)).abs() < 1e-12, "dead reckoning: x = {}", m.pose.x);
    }

    #[test]
    fn consensus_rejoins_without_a_jump() {
        let mut f = follower(RejoinPolicy::Consensus, 100);
        let (out, before) = isolate_then_hear(&mut f, 200);
        assert!(out.rejoined, "200 silent steps ≥ 100: the step that hears again is a rejoin");
        // The outputs use the held estimate; the estimate moves by one Euler step only.
        assert_eq!(out.estimate, before);
        let moved = (f.message().pose.x - before.pose.x).abs();
        assert!(moved < 0.01, "consensus moved the estimate {moved} m in one step");
    }

    #[test]
    fn adopt_takes_the_heard_state_before_the_outputs() {
        let mut f = follower(RejoinPolicy::Adopt, 100);
        let (out, before) = isolate_then_hear(&mut f, 200);
        assert!(out.rejoined);
        assert_eq!(out.estimate, neighbour(5.0).state, "adopt: the outputs use the neighbour's state");
        assert!((before.pose.x - 5.0).abs() > 1.0, "the held estimate was elsewhere ({})", before.pose.x);
        // A short silence (below rejoin_after) is not a rejoin: consensus as usual.
        let mut g = follower(RejoinPolicy::Adopt, 100);
        let (out, before) = isolate_then_hear(&mut g, 99);
        assert!(!out.rejoined);
        assert_eq!(out.estimate, before);
    }

    #[test]
    fn a_resumed_follower_starts_fresh_at_its_step_and_adopts() {
        let mut f = follower(RejoinPolicy::Consensus, 100);
        for _ in 0..50 {
            f.step(&Pose::default(), Velocity::new(0.5, 0.1), None, [&neighbour(1.0)]);
        }
        f.resume_at(7000);
        assert!(f.adopting());
        assert_eq!(f.next_step(), 7000);
        assert_eq!(f.filter().estimate, [0.0, 0.0], "fresh filter: ζ̂ = 0");
        let out = f.step(&Pose::default(), Velocity::default(), None, [&neighbour(5.0)]);
        assert_eq!(out.k, 7000);
        assert!(out.rejoined && !f.adopting());
        assert_eq!(out.estimate, neighbour(5.0).state, "the estimate is the first heard message");
        assert_eq!(out.command_rate, Velocity::default(), "first-step rule: no command rate");
    }

    #[test]
    fn a_restarted_follower_adopts_whatever_the_policy() {
        let mut f = follower(RejoinPolicy::Consensus, 100);
        f.adopt_on_next_source();
        let (out, _) = isolate_then_hear(&mut f, 3);
        assert_eq!(out.estimate, neighbour(5.0).state);
    }

    #[test]
    fn adopt_waits_for_a_fresh_source_and_its_message_says_when_it_is_stale() {
        let mut f = follower(RejoinPolicy::Adopt, 100);
        let pose = Pose::new(7.0, -4.0, 0.0);
        assert!(f.tagged_message().fresh);
        for _ in 0..100 {
            f.step(&pose, Velocity::default(), None, []);
        }
        assert!(!f.tagged_message().fresh, "100 silent steps: the estimate is held through an isolation");
        // A neighbour that was cut off too (a router restart): not adopted.
        let stale = Message { fresh: false, ..neighbour(5.0) };
        let held = f.message();
        let out = f.step(&pose, Velocity::default(), None, [&stale]);
        assert_eq!(out.estimate, held, "a stale neighbour's estimate is not taken");
        assert!(!f.tagged_message().fresh, "still stale after hearing only a stale neighbour");
        // The first fresh one is.
        let out = f.step(&pose, Velocity::default(), None, [&stale, &neighbour(9.0)]);
        assert_eq!(out.estimate, neighbour(9.0).state, "adopted from the fresh neighbour alone");
        assert!(out.rejoined && f.tagged_message().fresh);
    }

    #[test]
    fn consensus_is_fresh_again_when_it_hears_anyone() {
        let mut f = follower(RejoinPolicy::Consensus, 100);
        isolate_then_hear(&mut f, 100);
        assert!(f.tagged_message().fresh);
        let mut g = follower(RejoinPolicy::Consensus, 100);
        g.resume_at(50);
        assert!(!g.tagged_message().fresh, "a restart's placeholder estimate is stale");
    }

    #[test]
    fn a_velocity_driven_brain_stops_at_the_kinematic_command() {
        // The same inputs to a torque brain and a velocity brain: the same
        // kinematic command and estimate; the velocity brain's estimate is
        // z(k) (at k = 0 too), its torque zero, its filter untouched.
        let torque = follower(RejoinPolicy::Consensus, 100);
        let mut c = (*torque.config.control).clone();
        c.drive = Drive::Velocity { lag_s: 0.1 };
        let config = FollowerConfig { control: Arc::new(c), ..torque.config.clone() };
        let mut velocity = Follower::new(config, torque.message(), Velocity::default());
        let mut torque = torque;
        for k in 0..20 {
            let pose = Pose::new(6.0 + 0.01 * k as f64, -4.0, 0.02 * k as f64);
            let z = Velocity::new(0.1 * k as f64, -0.05);
            let n = neighbour(1.0 + 0.01 * k as f64);
            let (a, b) = (torque.step(&pose, z, None, [&n]), velocity.step(&pose, z, None, [&n]));
            assert_eq!(
                (a.command, a.command_rate, a.body_error, a.estimate),
                (b.command, b.command_rate, b.body_error, b.estimate)
            );
            assert_eq!(b.velocity_estimate, z);
            assert_eq!(b.torque, Torque::default());
            // (At k = 0 the torque brain's shunting states and command rate are zero too.)
            assert!(k == 0 || a.torque != Torque::default(), "k = {k}: the torque brain computed no torque");
            assert_eq!(velocity.message(), torque.message(), "the estimator does not depend on the drive");
        }
        assert_eq!(velocity.filter().estimate, [0.0, 0.0], "no filter runs");
        assert!(velocity.check_finite().is_ok());
    }

    #[test]
    fn the_fault_starts_at_the_first_step_at_or_after_t_fault() {
        // 10 s at 1 ms is step 10000 exactly; 0.3 s at 0.1 s is step 3 even
        // though 3 × 0.1 = 0.30000000000000004 > 0.3 and 0.3 / 0.1 = 2.9999999999999996.
        assert_eq!(config(10.0, 1e-3).fault_step(), Some(10_000));
        assert_eq!(config(0.3, 0.1).fault_step(), Some(3));
        assert_eq!(config(0.25, 0.1).fault_step(), Some(3));
        let c = config(0.3, 0.1);
        assert_eq!(c.filter_model_at(2), c.model);
        assert_eq!(c.filter_model_at(3).mass_kg, 0.1);
        assert_eq!(c.filter_model_at(3).inertia_kgm2, 0.5);
    }
}
