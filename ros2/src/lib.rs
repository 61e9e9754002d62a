//! ROS 2 on the formation's terms: what a process needs to publish and
//! subscribe on rmw_zenoh's wire (ROS 2 over Zenoh) and to write rosbag2
//! folders, with no zenoh, no runtime and no clock here. `formation-net`
//! puts the keys, tokens, payloads and attachments made here on its own
//! zenoh session; `formation-record` can write bags.
//!
//! | module | what | rmw_zenoh / ROS source |
//! | --- | --- | --- |
//! | [`cdr`] | little-endian XCDR1 writer and reader, header `00 01 00 00` | `type_support.cpp`, `cdr.cpp` (Fast-CDR, `DDS_CDR`) |
//! | [`msgs`] | Time, Header, the geometry_msgs, Odometry, TFMessage, Clock; [`Message`] with type name, RIHS01 hash and `.msg` definition | Jazzy `.msg` files; hashes by REP 2011 |
//! | `type_hash` (tests) | every hash recomputed from its definition | rosidl `calculate_type_hash` |
//! | [`keys`] | data keys, liveliness tokens, the QoS string, ROS name rules | `liveliness_utils.cpp`, `qos.cpp` |
//! | [`attachment`] | the 33-byte attachment (sequence, source time, GID) | `attachment_helpers.cpp` (zenoh-ext serialization) |
//! | [`bag`] | rosbag2 folder: `metadata.yaml` v9 + one MCAP file | rosbag2 / rosbags writer formats |
//!
//! Each module names the rmw_zenoh sources (and the commits they were read
//! at, for issue 32) that its facts come from. In short: a sample of
//! topic `/follower_1/odom` is put on
//! `0/follower_1/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_…` with the
//! CDR payload (header included) and the 33-byte attachment; a publisher
//! is visible to ROS tools while its liveliness token
//! `@ros2_lv/0/<zid>/<node>/<entity>/MP/%/<ns>/<node>/<topic>/<type>/<hash>/<qos>`
//! is declared. Jazzy or later: Humble has no type hashes.
//!
//! The tests check these facts twice: against golden bytes and strings
//! worked out for issue 32, and (in `tests/python_cross_check.rs`) against
//! rosbags and mcap-ros2-support, independent Python implementations.
//!
//! # Examples
//!
//! A velocity command as rmw_zenoh carries it: CDR with its encapsulation
//! header, read back to the same value, and a truncated payload refused.
//!
//! ```
//! use formation_ros2::msgs::{Twist, Vector3};
//! use formation_ros2::Message;
//!
//! let cmd = Twist { linear: Vector3 { x: 0.2, ..Default::default() }, angular: Vector3 { z: -0.5, ..Default::default() } };
//! let bytes = cmd.encode();
//! assert_eq!(Twist::TYPE, "geometry_msgs/msg/Twist");
//! assert_eq!(&bytes[..4], [0, 1, 0, 0], "CDR little-endian");
//! assert_eq!(Twist::decode(&bytes), Ok(cmd));
//! assert!(Twist::decode(&bytes[..bytes.len() - 8]).is_err());
//! ```

pub mod attachment;
pub mod bag;
pub mod cdr;
pub mod msgs;
pub mod planar;
pub mod rmw_keys;
#[cfg(test)]
mod type_hash;

pub use cdr::DecodeError;
pub use msgs::Message;
