//! A robot the agent drives through ROS 2 instead of simulating it: the
//! follower's brain steps on the pose and twist the robot's `odom` reports
//! and its command goes out on `cmd_vel` (the interface of TurtleBot,
//! Gazebo's diff-drive plugin and most mobile bases). Such a robot is
//! velocity-commanded (`robot.model = "velocity"`), so `formation sim`
//! predicts the run: the simulator feeds the brain the same odometry view
//! of its robot (docs/model.md).
//!
//! Lock-step: odometry names its step by its stamp (k Δt); step k waits
//! for the robot's odometry of step k ([`Body::robot_ready`]), and a robot
//! that repeats step k − 1's odometry is sent step k − 1's command again.
//! Real time: each step uses the newest odometry; a robot silent for
//! `ros2.odom_timeout` is sent zero velocity, and the run says so.
//!
//! Odometry in another frame than the scenario's `ros2.odom_frame`, from
//! the future, with a quantity that is not finite, or a jump of more than
//! [`JUMP_M`] from the last one taken is counted and refused. A robot whose
//! odometry frame has an origin (`robot.odom_origin`) reports its pose in
//! that frame; it is mapped into the world before the brain sees it.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use formation_control::{Follower, Message};
use formation_leader::LeaderState;
use formation_plant::{Pose, Velocity};
use formation_record::FollowerSample;
use formation_ros2::msgs::Odometry;
use formation_scenario::{Scenario, Timing};

use super::rmw_node::{RosNode, RosSubscription};
use super::topics::{OdomFrame, Stamps, QOS};
use crate::clock::{Clock, Timebase};
use formation_exit::Error;
use formation_protocol::follower::Body;

/// A move between two odometry messages longer than this (m) is a jump
/// (an odometry reset, or a message that is not this robot's): refused.
pub const JUMP_M: f64 = 1.0;

/// One odometry message, taken.
#[derive(Clone, Copy, Debug)]
struct Odom {
    /// Lock-step: the step its stamp names.
    step: Option<u64>,
    pose: Pose,
    twist: Velocity,
    /// When it arrived (this process's monotonic clock).
    arrived: Duration,
}

/// Lock-step: odometry stamped at most this many steps past the awaited
/// one is "from the future"; further is "off the run's steps".
const AHEAD_STEPS: u64 = 1000;

/// Odometry refused, by reason.
#[derive(Debug, Default)]
pub struct Refused {
    pub undecodable: AtomicU64,
    pub not_finite: AtomicU64,
    pub future: AtomicU64,
    /// Lock-step: stamped at no step of the run (k Δt from its start), or
    /// more than [`AHEAD_STEPS`] past the awaited one.
    pub off_steps: AtomicU64,
    pub jump: AtomicU64,
    pub wrong_frame: AtomicU64,
    /// The last frame_id refused, and the one expected.
    pub frames: Mutex<Option<(String, String)>>,
}

impl Refused {
    /// "3 from the future, 1 not finite", or None when nothing was refused.
    pub fn summary(&self) -> Option<String> {
        let wrong = self.wrong_frame.load(Ordering::Relaxed);
        let frames = self.frames.lock().unwrap_or_else(|p| p.into_inner()).clone();
        let wrong = frames
            .filter(|_| wrong > 0)
            .map(|(got, want)| format!("{wrong} in frame `{got}` (expected `{want}`: ros2.odom_frame)"));
        let parts: Vec<String> = wrong
            .into_iter()
            .chain(
                [
                    (&self.future, "from the future"),
                    (&self.off_steps, "stamped off the run's steps"),
                    (&self.not_finite, "not finite"),
                    (&self.jump, "jumps"),
                    (&self.undecodable, "undecodable"),
                ]
                .iter()
                .filter_map(|(n, what)| {
                    let n = n.load(Ordering::Relaxed);
                    (n > 0).then(|| format!("{n} {what}"))
                }),
            )
            .collect();
        (!parts.is_empty()).then(|| parts.join(", "))
    }
}

/// What the odometry subscription and the body share.
#[derive(Default)]
pub struct OdomInbox {
    latest: Mutex<Option<Odom>>,
    /// Lock-step: the step the body waits for next.
    awaited: AtomicU64,
    pub refused: Refused,
    /// The follower whose robot this is.
    id: u32,
    /// The frame_id the odometry must carry, and where that frame sits.
    frame_id: String,
    frame: OdomFrame,
    /// The node's clock: when each odometry message arrived.
    clock: Clock,
}

impl OdomInbox {
    /// The inbox of follower `index`'s robot, on the node's clock.
    pub fn for_robot(scenario: &Scenario, index: usize, clock: &Clock) -> Self {
        Self {
            id: scenario.graph.id(index),
            frame_id: scenario.odom_frame_of(scenario.graph.id(index)),
            frame: OdomFrame::of(scenario, index),
            clock: clock.clone(),
            ..Self::default()
        }
    }

    fn latest(&self) -> Option<Odom> {
        *self.latest.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Checks one message and keeps it if it passes; answers the step it
    /// names (lock-step) when it was taken.
    fn offer(
        &self,
        m: &Odometry,
        stamps: &Stamps,
        lockstep: bool,
        now_ns: Option<i64>,
        future_ns: i64,
    ) -> Result<Option<u64>, ()> {
        if m.header.frame_id != self.frame_id {
            // Said at the first one, not only at the run's end: a robot whose
            // every message is refused gets commands and never moves.
            if self.refused.wrong_frame.fetch_add(1, Ordering::Relaxed) == 0 {
                crate::node::say(&format!(
                    "follower {}: its robot's odometry in frame `{}` is refused (expected `{}`: ros2.odom_frame); \
                     every such message is dropped and counted",
                    self.id, m.header.frame_id, self.frame_id
                ));
            }
            *self.refused.frames.lock().unwrap_or_else(|p| p.into_inner()) =
                Some((m.header.frame_id.clone(), self.frame_id.clone()));
            return Err(());
        }
        let p = &m.pose.pose;
        let pose = self.frame.world(Pose::new(p.position.x, p.position.y, p.orientation.yaw()));
        let twist = Velocity::new(m.twist.twist.linear.x, m.twist.twist.angular.z);
        if !(pose.is_finite() && twist.is_finite()) {
            self.refused.not_finite.fetch_add(1, Ordering::Relaxed);
            return Err(());
        }
        let stamp = m.header.stamp.as_nanos();
        let step = if lockstep {
            // Only the step awaited or one before (a repeat) can exist yet;
            // a stamp off the run's steps is not this run's.
            let awaited = self.awaited.load(Ordering::Relaxed);
            match stamps.step_of(stamp) {
                Some(k) if k <= awaited => Some(k),
                // A robot a few steps ahead of its commands; further off,
                // a clock of its own that fell on a step by chance.
                Some(k) if k - awaited <= AHEAD_STEPS => {
                    self.refused.future.fetch_add(1, Ordering::Relaxed);
                    return Err(());
                }
                Some(_) | None => {
                    self.refused.off_steps.fetch_add(1, Ordering::Relaxed);
                    return Err(());
                }
            }
        } else {
            if now_ns.is_some_and(|now| stamp > now + future_ns) {
                self.refused.future.fetch_add(1, Ordering::Relaxed);
                return Err(());
            }
            None
        };
        let mut latest = self.latest.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(last) = *latest {
            if (pose.x - last.pose.x).hypot(pose.y - last.pose.y) > JUMP_M {
                self.refused.jump.fetch_add(1, Ordering::Relaxed);
                return Err(());
            }
        }
        *latest = Some(Odom { step, pose, twist, arrived: self.clock.mono() });
        Ok(step)
    }
}

/// Subscribes a driven robot's `odom`: each message checked into `inbox`;
/// `wake` when a lock-step step's odometry is in; `repeat(k)` when a
/// lock-step robot says step k again while step k + 1 is awaited.
pub async fn subscribe_odometry(
    node: &RosNode,
    scenario: &Scenario,
    inbox: Arc<OdomInbox>,
    stamps: Stamps,
    timebase: Timebase,
    wake: Arc<dyn Fn() + Send + Sync>,
    repeat: Arc<dyn Fn(u64) + Send + Sync>,
) -> Result<RosSubscription, Error> {
    let lockstep = scenario.timing == Timing::Lockstep;
    let future_ns = (scenario.ros2.map_or(0.5, |r| r.odom_timeout_s) * 1e9) as i64;
    node.subscribe::<Odometry, _>("odom", QOS, move |m, _attachment| {
        let Ok(m) = m else {
            inbox.refused.undecodable.fetch_add(1, Ordering::Relaxed);
            return;
        };
        match inbox.offer(&m, &stamps, lockstep, timebase.now_ns(), future_ns) {
            Ok(Some(k)) if k == inbox.awaited.load(Ordering::Relaxed) => wake(),
            Ok(Some(k)) => repeat(k),
            _ => {}
        }
    })
    .await
}

/// The follower's body when its robot is driven through ROS 2.
pub struct DrivenRobot {
    brain: Follower,
    inbox: Arc<OdomInbox>,
    lockstep: bool,
    timeout: Duration,
    /// The topic, for what the run says.
    topic: String,
    /// What a lock-step step waits for, for what the run says.
    waiting_for: String,
    /// The pose before any odometry arrived (the scenario's initial pose).
    initial: Pose,
    /// Sending zero velocity since (monotonic), while the odometry is stale.
    stopped_since: Option<Duration>,
    id: u32,
}

impl DrivenRobot {
    /// Follower `index`'s brain driving the robot whose odometry arrives in `inbox`.
    pub fn new(scenario: &Scenario, index: usize, inbox: Arc<OdomInbox>) -> Self {
        let spec = &scenario.followers[index];
        let brain = Follower::new(scenario.follower_config(index), scenario.initial_estimate(), spec.velocity);
        let id = spec.id;
        Self {
            brain,
            inbox,
            lockstep: scenario.timing == Timing::Lockstep,
            timeout: Duration::from_secs_f64(scenario.ros2.map_or(0.5, |r| r.odom_timeout_s)),
            topic: format!("{}/odom", super::follower_namespace(id)),
            waiting_for: format!("the robot's odometry on {}/odom", super::follower_namespace(id)),
            initial: spec.pose,
            stopped_since: None,
            id,
        }
    }

    /// Real time: the newest odometry, or None when it is older than the
    /// timeout (or never came); says when that starts and ends.
    fn fresh_odometry(&mut self) -> (Option<Odom>, Option<Odom>) {
        let latest = self.inbox.latest();
        let now = self.inbox.clock.mono();
        let fresh = latest.filter(|o| now.saturating_sub(o.arrived) <= self.timeout);
        match (fresh.is_some(), self.stopped_since) {
            (false, None) => {
                self.stopped_since = Some(now);
                let why = if latest.is_some() {
                    format!("no odometry on {} for {:.1} s", self.topic, self.timeout.as_secs_f64())
                } else {
                    format!("no odometry on {} yet", self.topic)
                };
                crate::node::say(&format!("follower {}: {why}: sending zero velocity", self.id));
            }
            (true, Some(since)) => {
                self.stopped_since = None;
                crate::node::say(&format!(
                    "follower {}: odometry on {} again after {:.1} s: driving",
                    self.id,
                    self.topic,
                    now.saturating_sub(since).as_secs_f64()
                ));
            }
            _ => {}
        }
        (fresh, latest)
    }
}

impl Body for DrivenRobot {
    fn step(
        &mut self,
        t_s: f64,
        dt_s: f64,
        leader: Option<&LeaderState>,
        neighbours: &[Message],
        nearby: formation_control::Nearby<'_>,
        last: bool,
    ) -> (FollowerSample, Message) {
        let k = (t_s / dt_s).round() as u64;
        let (odom, stop) = if self.lockstep {
            // robot_ready made sure it is step k's.
            (self.inbox.latest(), false)
        } else {
            let (fresh, latest) = self.fresh_odometry();
            (fresh.or(latest), fresh.is_none())
        };
        let (pose, z) = odom.map_or((self.initial, Velocity::default()), |o| (o.pose, o.twist));
        // The simulator's own call for a robot seen through its odometry.
        let (mut sample, out) = formation_sim::step_on_odometry(&mut self.brain, (pose, z), leader, neighbours, nearby);
        if stop {
            sample.command = Velocity::default();
        }
        if !last {
            self.inbox.awaited.store(k + 1, Ordering::Relaxed);
        }
        (sample, out.next_message)
    }
    fn initial_message(&self) -> Message {
        self.brain.tagged_message()
    }
    fn check_finite(&self) -> Result<(), &'static str> {
        self.brain.check_finite().map_err(|e| e.0)
    }
    fn silent_steps(&self) -> u64 {
        self.brain.silent_steps()
    }
    fn resume(&mut self, k: u64, _pose: Pose) {
        // The robot is where its odometry says; only the brain starts again.
        self.brain.resume_at(k);
        self.inbox.awaited.store(k, Ordering::Relaxed);
    }
    fn adopting(&self) -> bool {
        self.brain.adopting()
    }
    fn robot_ready(&self, k: u64) -> bool {
        self.inbox.latest().is_some_and(|o| o.step == Some(k))
    }
    fn robot_name(&self) -> std::borrow::Cow<'_, str> {
        let off = self.inbox.refused.off_steps.load(Ordering::Relaxed);
        if self.lockstep && off > 0 {
            // A robot on its own clock: say so while the run waits, not at its end.
            format!(
                "{} ({off} received, refused: stamped off the run's steps; in lock-step step k's odometry is \
                 stamped k Δt, the time /clock gives, and a robot on its own clock needs timing = \"realtime\")",
                self.waiting_for
            )
            .into()
        } else {
            self.waiting_for.as_str().into()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_ros2::planar::{self, Frames};

    fn odom(stamp_ns: i64, x: f64, y: f64) -> Odometry {
        planar::odometry(&Frames::of("/follower_1"), stamp_ns, (x, y, 0.25), (0.5, 0.1))
    }

    /// Follower 1's inbox, its odometry frame at `origin` (None: the world).
    fn inbox(origin: Option<Pose>) -> OdomInbox {
        OdomInbox { frame_id: "follower_1/odom".into(), frame: OdomFrame { origin }, ..OdomInbox::default() }
    }

    fn counts(r: &Refused) -> [u64; 5] {
        [&r.future, &r.not_finite, &r.jump, &r.undecodable, &r.off_steps].map(|n| n.load(Ordering::Relaxed))
    }

    #[test]
    fn lock_step_odometry_is_taken_for_the_awaited_step_or_a_repeat_and_refused_from_the_future() {
        let stamps = Stamps::lockstep(0.01);
        let inbox = inbox(None);
        inbox.awaited.store(3, Ordering::Relaxed);
        assert_eq!(inbox.offer(&odom(stamps.ns(3), 1.0, 2.0), &stamps, true, None, 0), Ok(Some(3)));
        let o = inbox.latest().expect("taken");
        assert_eq!((o.step, o.pose.x, o.pose.y, o.twist), (Some(3), 1.0, 2.0, Velocity::new(0.5, 0.1)));
        assert_eq!(inbox.offer(&odom(stamps.ns(2), 1.0, 2.0), &stamps, true, None, 0), Ok(Some(2)), "a repeat");
        assert_eq!(
            inbox.offer(&odom(stamps.ns(4), 1.0, 2.0), &stamps, true, None, 0),
            Err(()),
            "step 4 before its command"
        );
        assert_eq!(inbox.offer(&odom(stamps.ns(3) + 1, 1.0, 2.0), &stamps, true, None, 0), Err(()), "off the steps");
        // A robot on the wall clock (a TurtleBot's, Gazebo's without /clock).
        let wall = 1_764_200_000_000_000_000;
        for at in [wall, wall + 123_456] {
            assert_eq!(inbox.offer(&odom(at, 1.0, 2.0), &stamps, true, None, 0), Err(()), "the wall clock: {at}");
        }
        assert_eq!(counts(&inbox.refused), [1, 0, 0, 0, 3]);
        assert_eq!(inbox.refused.summary().as_deref(), Some("1 from the future, 3 stamped off the run's steps"));
    }

    #[test]
    fn odometry_that_is_not_finite_jumps_or_comes_from_the_future_is_counted_and_refused() {
        let stamps = Stamps::lockstep(0.01);
        let inbox = inbox(None);
        let now = 1_000_000_000_000;
        let timeout = 500_000_000;
        assert_eq!(inbox.offer(&odom(now, 0.0, 0.0), &stamps, false, Some(now), timeout), Ok(None));
        assert_eq!(inbox.offer(&odom(now, f64::NAN, 0.0), &stamps, false, Some(now), timeout), Err(()));
        let mut inf = odom(now, 0.0, 0.0);
        inf.twist.twist.angular.z = f64::INFINITY;
        assert_eq!(inbox.offer(&inf, &stamps, false, Some(now), timeout), Err(()));
        assert_eq!(inbox.offer(&odom(now, 1.5, 0.0), &stamps, false, Some(now), timeout), Err(()), "1.5 m at once");
        assert_eq!(inbox.offer(&odom(now + 2 * timeout, 0.1, 0.0), &stamps, false, Some(now), timeout), Err(()));
        assert_eq!(inbox.offer(&odom(now + timeout / 2, 0.5, 0.0), &stamps, false, Some(now), timeout), Ok(None));
        assert_eq!(inbox.latest().map(|o| o.pose.x), Some(0.5));
        assert_eq!(counts(&inbox.refused), [1, 2, 1, 0, 0]);
        assert_eq!(inbox.refused.summary().as_deref(), Some("1 from the future, 2 not finite, 1 jumps"));
    }

    /// docs/ros2.md: odometry in another frame is refused, named; a robot
    /// whose odometry starts at (0, 0, 0) at its origin is placed in the world.
    #[test]
    fn odometry_in_another_frame_is_refused_and_a_frame_with_an_origin_is_mapped_into_the_world() {
        let stamps = Stamps::lockstep(0.01);
        let origin = Pose::new(2.0, 1.0, std::f64::consts::FRAC_PI_2);
        let inbox = inbox(Some(origin));
        let mut bare = odom(0, 0.0, 0.0);
        bare.header.frame_id = "odom".into();
        assert_eq!(inbox.offer(&bare, &stamps, false, Some(0), 1), Err(()));
        assert_eq!(
            inbox.refused.summary().as_deref(),
            Some("1 in frame `odom` (expected `follower_1/odom`: ros2.odom_frame)")
        );
        assert_eq!(inbox.offer(&odom(0, 0.0, 0.0), &stamps, false, Some(0), 1), Ok(None));
        let p = inbox.latest().expect("taken").pose;
        assert!((p.x - 2.0).abs() < 1e-15 && (p.y - 1.0).abs() < 1e-15, "(0, 0) in the odometry frame is {p:?}");
        assert!((p.theta - (std::f64::consts::FRAC_PI_2 + 0.25)).abs() < 1e-15, "heading {}", p.theta);
        inbox.offer(&odom(0, 0.5, 0.0), &stamps, false, Some(0), 1).unwrap();
        let p = inbox.latest().expect("taken").pose;
        assert!((p.x - 2.0).abs() < 1e-15 && (p.y - 1.5).abs() < 1e-15, "0.5 m ahead of a robot facing +y: {p:?}");
    }
}
