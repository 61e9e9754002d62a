//! A live leader's input on ROS 2's wire (docs/model.md §18): with
//! `leader.source = "cmd_vel"` the leader node subscribes
//! `/leader/cmd_vel` (geometry_msgs/Twist, as `teleop_twist_keyboard` and
//! `joy`'s teleop publish it); with `"robot"`, `/leader/odom`
//! (nav_msgs/Odometry of the leader robot, in `ros2.odom_frame`'s leader
//! frame, mapped into the world from `robot.odom_origin`); with `"path"`,
//! `/leader/path` (nav_msgs/Path in frame `world`, as a planner sends its
//! plan: each pose's position a point of the route). Each message
//! goes to the leader machine with the time it arrived; the machine
//! clips, counts and times out ([`formation_protocol::steering`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use formation_leader::Trajectory;
use formation_plant::{Pose, Velocity};
use formation_protocol::leader::LeaderMachine as Machine;
use formation_ros2::msgs::{Odometry, Path, Twist};
use formation_scenario::Scenario;

use super::rmw_node::{RosNode, RosSubscription};
use super::topics::{OdomFrame, QOS};
use crate::clock::Timebase;
use crate::node::Shared;
use formation_exit::Error;

/// The frame a route on `/leader/path` must be in: the scenario's own.
pub const WORLD_FRAME: &str = formation_ros2::planar::WORLD;

/// The leader's subscription to its source, and what it could not read.
pub struct Steered {
    _node: RosNode,
    _subscription: RosSubscription,
    /// Messages that did not decode, or came in another frame.
    pub refused: Arc<AtomicU64>,
}

/// Subscribes the source of a live leader (None for a scripted one), on
/// `ros2.domain_id` (0 without a `[ros2]` table).
pub async fn subscribe(
    session: &zenoh::Session,
    scenario: &Scenario,
    shared: &Arc<Shared<Machine>>,
    timebase: &Timebase,
) -> Result<Option<Steered>, Error> {
    if !scenario.leader_profile.is_live() {
        return Ok(None);
    }
    let domain = scenario.ros2.map_or(0, |r| r.domain_id);
    let refused = Arc::new(AtomicU64::new(0));
    let (sh, tb, bad) = (shared.clone(), timebase.clone(), refused.clone());
    let node = RosNode::declare(session, domain, super::LEADER_NAMESPACE, "leader_input").await?;
    let subscription = match scenario.leader_profile.trajectory {
        Trajectory::Commanded { .. } => {
            node.subscribe::<Twist, _>("cmd_vel", QOS, move |m, _| match m {
                Ok(t) => sh.lock().handle_command(Velocity::new(t.linear.x, t.angular.z), tb.now()),
                Err(_) => drop(bad.fetch_add(1, Ordering::Relaxed)),
            })
            .await?
        }
        Trajectory::Routed { .. } => {
            let said = std::sync::Once::new();
            node.subscribe::<Path, _>("path", QOS, move |m, _| match m {
                Ok(m) if m.header.frame_id == WORLD_FRAME => {
                    let points = m.poses.iter().map(|p| [p.pose.position.x, p.pose.position.y]).collect();
                    sh.lock().handle_path(points);
                }
                Ok(m) => refuse(&bad, &said, || {
                    format!(
                        "leader: a route on /leader/path in frame `{}` is refused (expected `{WORLD_FRAME}`, the \
                         scenario's frame); every such route is dropped and counted",
                        m.header.frame_id
                    )
                }),
                Err(_) => drop(bad.fetch_add(1, Ordering::Relaxed)),
            })
            .await?
        }
        Trajectory::External => {
            let (frame_id, origin) =
                (scenario.leader_odom_frame(), OdomFrame { origin: scenario.leader_odom_origin() });
            let said = std::sync::Once::new();
            node.subscribe::<Odometry, _>("odom", QOS, move |m, _| match m {
                Ok(m) if m.header.frame_id == frame_id => {
                    let p = &m.pose.pose;
                    let pose = origin.world(Pose::new(p.position.x, p.position.y, p.orientation.yaw()));
                    let twist = Velocity::new(m.twist.twist.linear.x, m.twist.twist.angular.z);
                    sh.lock().handle_leader_odometry(pose, twist, tb.now());
                }
                Ok(m) => refuse(&bad, &said, || {
                    format!(
                        "leader: the leader robot's odometry in frame `{}` is refused (expected `{frame_id}`: \
                         ros2.odom_frame); every such message is dropped and counted",
                        m.header.frame_id
                    )
                }),
                Err(_) => drop(bad.fetch_add(1, Ordering::Relaxed)),
            })
            .await?
        }
        _ => return Ok(None),
    };
    Ok(Some(Steered { _node: node, _subscription: subscription, refused }))
}

/// A message in another frame: counted, and the first one said.
fn refuse(count: &AtomicU64, said: &std::sync::Once, line: impl FnOnce() -> String) {
    count.fetch_add(1, Ordering::Relaxed);
    said.call_once(|| crate::node::say(&line()));
}
