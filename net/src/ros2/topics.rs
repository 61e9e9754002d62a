//! What the formation publishes on ROS 2 each step (docs/ros2.md):
//!
//! - a follower's agent, in `/follower_<i>`: `odom` (nav_msgs/Odometry: its
//!   robot's pose and body twist; not when a driven robot publishes its
//!   own), `cmd_vel` (geometry_msgs/Twist: the command (v_c, ω_c), or zero
//!   for a driven robot whose odometry stopped), `leader_estimate`
//!   (geometry_msgs/PoseStamped: its estimate of the leader's pose), and
//!   its robot's transforms on `/tf`;
//! - the leader, in `/leader`: `odom`, its transforms on `/tf`, and in
//!   lock-step `/clock` (rosgraph_msgs/Clock) so ROS nodes can run on
//!   `use_sim_time`.
//!
//! Frames follow REP 105 per robot ([`formation_ros2::planar`]). Stamps are the step's time on the run's timebase: k Δt in
//! lock-step (the time `/clock` gives), the step's due time since the Unix
//! epoch on the leader's clock in real time.

use formation_leader::LeaderState;
use formation_plant::{Pose, Velocity};
use formation_record::FollowerSample;
use formation_ros2::msgs::{Clock, Message, Odometry, PoseStamped, TFMessage, Time, Twist};
use formation_ros2::planar::{self, Frames};
use formation_ros2::rmw_keys::Qos;
use formation_scenario::{Scenario, Timing};
use zenoh::qos::CongestionControl;

use super::rmw_node::{RosNode, RosPublisher};
use formation_exit::Error;

/// The QoS of the formation's topics: reliable, volatile, the last 10.
pub const QOS: Qos = Qos { reliable: true, transient_local: false, depth: 10 };
/// `/clock`'s usual QoS: best effort, the last one.
pub const CLOCK_QOS: Qos = Qos { reliable: false, transient_local: false, depth: 1 };

/// When each step happened, as ROS stamps it.
#[derive(Clone, Copy, Debug)]
pub struct Stamps {
    /// ns added to k · period: 0 in lock-step, the run's epoch in real time.
    origin_ns: i64,
    period_ns: f64,
}

impl Stamps {
    /// Lock-step: k Δt (simulated time). Real time: the epoch plus k
    /// periods of wall time (Δt / time scale).
    pub fn of(scenario: &Scenario, epoch_unix_ns: u64) -> Self {
        match scenario.timing {
            Timing::Lockstep => Self { origin_ns: 0, period_ns: scenario.dt_s * 1e9 },
            Timing::Realtime => Self {
                origin_ns: epoch_unix_ns as i64,
                period_ns: scenario.dt_s / formation_protocol::barrier::positive_scale(scenario.network.time_scale)
                    * 1e9,
            },
        }
    }

    /// Lock-step stamps of a step Δt (what [`Stamps::of`] gives a lock-step scenario).
    pub fn lockstep(dt_s: f64) -> Self {
        Self { origin_ns: 0, period_ns: dt_s * 1e9 }
    }

    /// Step k's stamp, ns.
    pub fn ns(&self, k: u64) -> i64 {
        self.origin_ns + (k as f64 * self.period_ns).round() as i64
    }

    /// The step whose stamp is `ns`, if it is one (lock-step odometry names its step so).
    pub fn step_of(&self, ns: i64) -> Option<u64> {
        let k = ((ns - self.origin_ns) as f64 / self.period_ns).round();
        (k >= 0.0 && self.ns(k as u64) == ns).then_some(k as u64)
    }
}

/// Odometry of a planar robot at `pose` moving with `twist`.
pub fn odometry(frames: &Frames, ns: i64, pose: Pose, twist: Velocity) -> Odometry {
    planar::odometry(frames, ns, (pose.x, pose.y, pose.theta), (twist.v, twist.w))
}

/// The robot's transforms at `pose`.
pub fn transforms(frames: &Frames, ns: i64, pose: Pose) -> TFMessage {
    planar::transforms(frames, ns, (pose.x, pose.y, pose.theta))
}

/// A follower's frames: its odometry frame as the scenario names it
/// (`ros2.odom_frame`), `follower_<id>/base_link`.
pub fn follower_frames(scenario: &Scenario, id: u32) -> Frames {
    Frames { odom: scenario.odom_frame_of(id), ..Frames::of(&super::follower_namespace(id)) }
}

/// Where a follower's robot is in its odometry frame, and that frame's
/// origin in the world (docs/ros2.md, "Odometry in the robot's frame").
#[derive(Clone, Copy, Debug, Default)]
pub struct OdomFrame {
    pub origin: Option<Pose>,
}

impl OdomFrame {
    pub fn of(scenario: &Scenario, index: usize) -> Self {
        Self { origin: scenario.followers[index].odom_origin }
    }

    /// A world pose as the robot's odometry reports it.
    pub fn local(&self, world: Pose) -> Pose {
        self.origin.map_or(world, |o| o.relative(&world))
    }

    /// A pose the odometry reports, in the world.
    pub fn world(&self, local: Pose) -> Pose {
        self.origin.map_or(local, |o| o.compose(&local))
    }

    /// The robot's transforms: world → odom at the origin, odom → base_link at its odometry pose.
    pub fn transforms(&self, frames: &Frames, ns: i64, world: Pose) -> TFMessage {
        let (o, l) = (self.origin.unwrap_or_default(), self.local(world));
        planar::transforms_from(frames, ns, (o.x, o.y, o.theta), (l.x, l.y, l.theta))
    }
}

fn twist_of(v: Velocity) -> Twist {
    planar::twist(v.v, v.w)
}

fn congestion(scenario: &Scenario) -> CongestionControl {
    crate::node::estimate_congestion(scenario)
}

/// A follower agent's ROS 2 publishers (its node is the agent's, held by it).
pub struct FollowerTopics {
    frames: Frames,
    stamps: Stamps,
    /// None when a driven robot publishes its own odometry and transforms.
    odom: Option<RosPublisher<Odometry>>,
    tf: Option<RosPublisher<TFMessage>>,
    /// An external robot's world → odom transform, which only the agent
    /// knows (a robot with `odom_origin`).
    odom_in_world: Option<RosPublisher<TFMessage>>,
    frame: OdomFrame,
    cmd_vel: RosPublisher<Twist>,
    estimate: RosPublisher<PoseStamped>,
    /// The last command sent (step, payload), for a lock-step robot that asks again.
    last_command: Option<(u64, Vec<u8>)>,
}

impl FollowerTopics {
    /// The topics of `node`, the agent's node `/follower_<id>/agent` (one
    /// node per agent: its odometry subscription and these publishers are
    /// the same node's, as `ros2 node info` shows them); `driven`: the
    /// robot publishes its own odometry.
    pub async fn declare(
        node: &RosNode,
        scenario: &Scenario,
        id: u32,
        driven: bool,
        epoch_unix_ns: u64,
    ) -> Result<Self, Error> {
        let c = congestion(scenario);
        let (odom, tf) = if driven {
            (None, None)
        } else {
            (Some(node.publisher("odom", QOS, c).await?), Some(node.publisher("/tf", QOS, c).await?))
        };
        let index = scenario.index_of(id).ok_or_else(|| Error::Input(format!("no follower {id}")))?;
        let frame = OdomFrame::of(scenario, index);
        let external = scenario.ros2.is_some_and(|r| r.robots == formation_scenario::RobotSource::External);
        let odom_in_world = match external && frame.origin.is_some() {
            true => Some(node.publisher("/tf", QOS, c).await?),
            false => None,
        };
        Ok(Self {
            cmd_vel: node.publisher("cmd_vel", QOS, c).await?,
            estimate: node.publisher("leader_estimate", QOS, c).await?,
            odom,
            tf,
            odom_in_world,
            frame,
            frames: follower_frames(scenario, id),
            stamps: Stamps::of(scenario, epoch_unix_ns),
            last_command: None,
        })
    }

    /// Step `s.k`'s messages.
    pub fn publish(&mut self, s: &FollowerSample) -> Result<(), Error> {
        let ns = self.stamps.ns(s.k);
        let command = twist_of(s.command).encode();
        self.cmd_vel.put_encoded(command.clone(), ns)?;
        self.last_command = Some((s.k, command));
        let e = s.estimate.pose;
        self.estimate.put(&planar::pose_stamped(ns, (e.x, e.y, e.theta)), ns)?;
        if let Some(p) = &mut self.odom {
            p.put(&odometry(&self.frames, ns, self.frame.local(s.pose), s.velocity), ns)?;
        }
        if let Some(p) = &mut self.tf {
            p.put(&self.frame.transforms(&self.frames, ns, s.pose), ns)?;
        }
        if let (Some(p), Some(o)) = (&mut self.odom_in_world, self.frame.origin) {
            let fixed = planar::odom_in_world(&self.frames, ns, (o.x, o.y, o.theta));
            p.put(&TFMessage { transforms: vec![fixed] }, ns)?;
        }
        Ok(())
    }

    /// Zero velocity on `cmd_vel`, stamped `now_ns` (the wall clock now):
    /// the agent is ending (docs/ros2.md, "A robot that stops").
    pub fn stop(&mut self, now_ns: i64) -> Result<(), Error> {
        self.last_command = None;
        self.cmd_vel.put(&Twist::default(), now_ns)
    }

    /// Sends step k's command again (a lock-step robot repeated its
    /// odometry of step k: the command may have been lost).
    pub fn repeat_command(&mut self, k: u64) -> Result<(), Error> {
        match &self.last_command {
            Some((last, bytes)) if *last == k => {
                let bytes = bytes.clone();
                self.cmd_vel.put_encoded(bytes, self.stamps.ns(k))
            }
            _ => Ok(()),
        }
    }

    pub fn stamps(&self) -> Stamps {
        self.stamps
    }
}

/// The leader's ROS 2 node and publishers.
pub struct LeaderTopics {
    _node: RosNode,
    frames: Frames,
    stamps: Stamps,
    odom: RosPublisher<Odometry>,
    tf: RosPublisher<TFMessage>,
    /// Lock-step only.
    clock: Option<RosPublisher<Clock>>,
}

impl LeaderTopics {
    /// Node `leader` in `/leader`.
    pub async fn declare(
        session: &zenoh::Session,
        scenario: &Scenario,
        domain: u32,
        epoch_unix_ns: u64,
    ) -> Result<Self, Error> {
        let node = RosNode::declare(session, domain, super::LEADER_NAMESPACE, "leader").await?;
        let c = congestion(scenario);
        let clock = match scenario.timing {
            Timing::Lockstep => Some(node.publisher("/clock", CLOCK_QOS, CongestionControl::Drop).await?),
            Timing::Realtime => None,
        };
        Ok(Self {
            odom: node.publisher("odom", QOS, c).await?,
            tf: node.publisher("/tf", QOS, c).await?,
            clock,
            frames: Frames::of(super::LEADER_NAMESPACE),
            stamps: Stamps::of(scenario, epoch_unix_ns),
            _node: node,
        })
    }

    /// Step k of the leader: `/clock` first, then its odometry and transforms.
    pub fn publish(&mut self, k: u64, s: &LeaderState) -> Result<(), Error> {
        let ns = self.stamps.ns(k);
        if let Some(c) = &mut self.clock {
            c.put(&Clock { clock: Time::from_nanos(ns) }, ns)?;
        }
        self.odom.put(&odometry(&self.frames, ns, s.pose, Velocity::new(s.v, s.w)), ns)?;
        self.tf.put(&transforms(&self.frames, ns, s.pose), ns)
    }
}
