//! `rosbag2/`: a run folder's samples as a ROS 2 bag (rosbag2's folder:
//! `metadata.yaml` and an MCAP file with `ros2msg` schemas and CDR
//! messages), so that `ros2 bag info`, `ros2 bag play` and Foxglove take a
//! run as a ROS 2 recording (docs/ros2.md).
//!
//! Written from the folder's CSVs when the folder is finished, as
//! `run.mcap` is: one message per CSV row and topic, the topics the live
//! nodes publish with `[ros2]` on, stamped with run time (t = 0 at step 0,
//! so a bag played with `--clock` drives `use_sim_time` nodes from 0).
//!
//! | topic | type | from |
//! | --- | --- | --- |
//! | `/clock` | `rosgraph_msgs/msg/Clock` | `leader.csv`'s t |
//! | `/leader/odom` | `nav_msgs/msg/Odometry` | `leader.csv` |
//! | `/follower_<id>/odom` | `nav_msgs/msg/Odometry` | x, y, θ, v, ω |
//! | `/follower_<id>/cmd_vel` | `geometry_msgs/msg/Twist` | v_c, ω_c |
//! | `/follower_<id>/leader_estimate` | `geometry_msgs/msg/PoseStamped` | x_ir, y_ir, θ_ir |
//! | `/tf` | `tf2_msgs/msg/TFMessage` | every robot's pose |

use std::path::Path;

use formation_ros2::bag::BagWriter;
use formation_ros2::msgs::{Clock, Message, Odometry, PoseStamped, TFMessage, Time, Twist};
use formation_ros2::planar::{self, Frames};
use formation_ros2::rmw_keys::Qos;

/// The bag's folder name in a run folder.
pub const DIR: &str = "rosbag2";

fn err(e: impl std::fmt::Display) -> std::io::Error {
    std::io::Error::other(format!("{DIR}: {e}"))
}

/// A CSV's columns `names`, or None when the file is absent.
fn read(path: &Path, names: &[&str]) -> std::io::Result<Option<Vec<Vec<f64>>>> {
    if !path.exists() {
        return Ok(None);
    }
    crate::columns::read_columns(path, names).map(Some).map_err(err)
}

fn ns(t: f64) -> i64 {
    (t.max(0.0) * 1e9).round() as i64
}

/// Writes `dir/rosbag2/` from the CSVs in `dir` for the followers `ids`.
#[allow(clippy::needless_range_loop)] // one row read across several columns
pub fn write(dir: &Path, ids: &[u32]) -> std::io::Result<()> {
    let mut bag = BagWriter::create(&dir.join(DIR))?;
    let qos = Qos::default();
    let clock = bag.add_topic::<Clock>("/clock", Qos::best_effort(1))?;
    let tf = bag.add_topic::<TFMessage>("/tf", qos)?;
    let put = |bag: &mut BagWriter, topic, t: f64, payload: Vec<u8>| bag.write(topic, ns(t) as u64, &payload);

    let names = ["t", "x", "y", "theta", "v", "w"];
    if let Some(c) = read(&dir.join("leader.csv"), &names)? {
        let frames = Frames::of("/leader");
        let odom = bag.add_topic::<Odometry>("/leader/odom", qos)?;
        for r in 0..c[0].len() {
            let (t, pose) = (c[0][r], (c[1][r], c[2][r], c[3][r]));
            put(&mut bag, clock, t, Clock { clock: Time::from_nanos(ns(t)) }.encode())?;
            put(&mut bag, odom, t, planar::odometry(&frames, ns(t), pose, (c[4][r], c[5][r])).encode())?;
            put(&mut bag, tf, t, planar::transforms(&frames, ns(t), pose).encode())?;
        }
    }
    let names = ["t", "x", "y", "theta", "v", "w", "v_c", "w_c", "x_ir", "y_ir", "theta_ir"];
    for id in ids {
        let Some(c) = read(&dir.join(format!("follower_{id}.csv")), &names)? else { continue };
        let namespace = format!("/follower_{id}");
        let frames = Frames::of(&namespace);
        let odom = bag.add_topic::<Odometry>(&format!("{namespace}/odom"), qos)?;
        let cmd = bag.add_topic::<Twist>(&format!("{namespace}/cmd_vel"), qos)?;
        let est = bag.add_topic::<PoseStamped>(&format!("{namespace}/leader_estimate"), qos)?;
        for r in 0..c[0].len() {
            let (t, pose) = (c[0][r], (c[1][r], c[2][r], c[3][r]));
            put(&mut bag, odom, t, planar::odometry(&frames, ns(t), pose, (c[4][r], c[5][r])).encode())?;
            put(&mut bag, cmd, t, planar::twist(c[6][r], c[7][r]).encode())?;
            put(&mut bag, est, t, planar::pose_stamped(ns(t), (c[8][r], c[9][r], c[10][r])).encode())?;
            put(&mut bag, tf, t, planar::transforms(&frames, ns(t), pose).encode())?;
        }
    }
    bag.finish().map(|_| ())
}
