//! The formation's conventions for planar robots in ROS 2 messages, shared
//! by the live nodes and the rosbag2 writer: REP 105's frames per robot
//! (`<robot>/odom` → `<robot>/base_link`, each odometry frame fixed in
//! [`WORLD`]), a pose (x, y, θ) as a position and a yaw quaternion, a body
//! velocity (v, ω) as `linear.x` and `angular.z`.

use crate::msgs::{
    Header, Odometry, Point, Pose, PoseStamped, Quaternion, TFMessage, Time, Transform, TransformStamped, Twist,
    Vector3,
};

/// The frame every robot's odometry frame is fixed in (the scenario's frame; rviz2's fixed frame).
pub const WORLD: &str = "world";

/// A robot's frame names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Frames {
    /// `<robot>/odom`.
    pub odom: String,
    /// `<robot>/base_link`.
    pub base_link: String,
}

impl Frames {
    /// The frames of the robot whose namespace is `namespace` (`/follower_1` → `follower_1/odom`, …).
    pub fn of(namespace: &str) -> Self {
        let robot = namespace.trim_matches('/');
        Self { odom: format!("{robot}/odom"), base_link: format!("{robot}/base_link") }
    }
}

/// A planar pose (x, y, θ): position (x, y, 0), orientation [`Quaternion::from_yaw`].
pub fn pose(x: f64, y: f64, theta: f64) -> Pose {
    Pose { position: Point { x, y, z: 0.0 }, orientation: Quaternion::from_yaw(theta) }
}

/// A body velocity (v, ω): `linear.x` and `angular.z`.
pub fn twist(v: f64, w: f64) -> Twist {
    Twist { linear: Vector3 { x: v, y: 0.0, z: 0.0 }, angular: Vector3 { x: 0.0, y: 0.0, z: w } }
}

fn header(frame: &str, stamp_ns: i64) -> Header {
    Header { stamp: Time::from_nanos(stamp_ns), frame_id: frame.to_string() }
}

/// Odometry: the pose in `frames.odom`, the body twist in `frames.base_link`.
pub fn odometry(frames: &Frames, stamp_ns: i64, (x, y, theta): (f64, f64, f64), (v, w): (f64, f64)) -> Odometry {
    let mut m = Odometry {
        header: header(&frames.odom, stamp_ns),
        child_frame_id: frames.base_link.clone(),
        ..Default::default()
    };
    m.pose.pose = pose(x, y, theta);
    m.twist.twist = twist(v, w);
    m
}

/// A pose stamped in [`WORLD`].
pub fn pose_stamped(stamp_ns: i64, (x, y, theta): (f64, f64, f64)) -> PoseStamped {
    PoseStamped { header: header(WORLD, stamp_ns), pose: pose(x, y, theta) }
}

/// The robot's transforms: [`WORLD`] → odom (identity) and odom → base_link (the pose).
pub fn transforms(frames: &Frames, stamp_ns: i64, (x, y, theta): (f64, f64, f64)) -> TFMessage {
    transforms_from(frames, stamp_ns, (0.0, 0.0, 0.0), (x, y, theta))
}

/// The world → odom transform alone, with the odometry frame's origin in the world.
pub fn odom_in_world(frames: &Frames, stamp_ns: i64, (x, y, theta): (f64, f64, f64)) -> TransformStamped {
    TransformStamped {
        header: header(WORLD, stamp_ns),
        child_frame_id: frames.odom.clone(),
        transform: Transform { translation: Vector3 { x, y, z: 0.0 }, rotation: Quaternion::from_yaw(theta) },
    }
}

/// [`transforms`] of a robot whose odometry frame sits at `origin` in the
/// world: world → odom at `origin`, odom → base_link at the odometry pose.
pub fn transforms_from(
    frames: &Frames,
    stamp_ns: i64,
    origin: (f64, f64, f64),
    (x, y, theta): (f64, f64, f64),
) -> TFMessage {
    let fixed = odom_in_world(frames, stamp_ns, origin);
    let moving = TransformStamped {
        header: header(&frames.odom, stamp_ns),
        child_frame_id: frames.base_link.clone(),
        transform: Transform { translation: Vector3 { x, y, z: 0.0 }, rotation: Quaternion::from_yaw(theta) },
    };
    TFMessage { transforms: vec![fixed, moving] }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_planar_pose_reads_back_as_it_was_written() {
        let f = Frames::of("/follower_3");
        assert_eq!((f.odom.as_str(), f.base_link.as_str()), ("follower_3/odom", "follower_3/base_link"));
        let m = odometry(&f, 1_500_000_000, (1.25, -2.5, 0.75), (0.5, -0.125));
        assert_eq!((m.header.stamp.sec, m.header.stamp.nanosec), (1, 500_000_000));
        let p = &m.pose.pose;
        assert_eq!((p.position.x, p.position.y, p.position.z), (1.25, -2.5, 0.0));
        assert!((p.orientation.yaw() - 0.75).abs() < 1e-15, "yaw {}", p.orientation.yaw());
        assert_eq!((m.twist.twist.linear.x, m.twist.twist.angular.z), (0.5, -0.125));
        let tf = transforms(&f, 0, (1.0, 2.0, 0.0));
        assert_eq!(tf.transforms.len(), 2);
        assert_eq!(tf.transforms[0].header.frame_id, WORLD);
        assert_eq!(tf.transforms[1].child_frame_id, "follower_3/base_link");
    }

    #[test]
    fn a_robots_odometry_frame_sits_at_its_origin_in_the_world() {
        let f = Frames::of("/follower_2");
        let tf = transforms_from(&f, 0, (1.5, -0.5, 0.25), (0.0, 0.0, 0.0));
        let fixed = &tf.transforms[0];
        assert_eq!((fixed.header.frame_id.as_str(), fixed.child_frame_id.as_str()), (WORLD, "follower_2/odom"));
        let t = &fixed.transform.translation;
        assert_eq!((t.x, t.y), (1.5, -0.5));
        assert!((fixed.transform.rotation.yaw() - 0.25).abs() < 1e-15);
        let moving = &tf.transforms[1];
        assert_eq!(moving.child_frame_id, "follower_2/base_link");
        assert_eq!((moving.transform.translation.x, moving.transform.translation.y), (0.0, 0.0));
    }
}
