//! The formation on ROS 2's wire: rmw_zenoh's keys, CDR payloads,
//! attachments and liveliness tokens on the node's own zenoh session, so
//! that ROS 2 tools see the formation's robots and ROS 2 robots can be
//! driven by it (docs/ros2.md). No bridge process: the keys and bytes are
//! the ones rmw_zenoh_cpp reads and writes ([`formation_ros2`] holds
//! them, without zenoh).
//!
//! - [`wire`]: a ROS 2 node, its publishers and subscriptions on a session.
//! - [`topics`]: what a follower's agent and the leader publish each step.
//! - [`driven`]: a robot the agent drives through `cmd_vel` and `odom`
//!   instead of simulating it (the [`crate::agent::Body`] of such a follower).
//! - [`robot`]: `formation robot`, the stand-in robot that speaks ROS 2.
//! - [`steer`]: a live leader's input (`/leader/cmd_vel`, `/leader/path`, `/leader/odom`).

pub mod driven;
pub mod rmw_node;
pub mod robot;
pub mod steer;
pub mod topics;

/// The namespace of follower `id`'s topics (`/follower_<id>`).
pub fn follower_namespace(id: u32) -> String {
    format!("/follower_{id}")
}

/// The leader's namespace.
pub const LEADER_NAMESPACE: &str = "/leader";
