//! Independent implementations read what this crate writes: rosbags
//! decodes every payload, hashes every type and parses every definition
//! (`tests/python/check_cdr.py`); rosbags' rosbag2 reader and
//! mcap-ros2-support read a bag folder (`tests/python/check_bag.py`).
//!
//! The interpreter is `$FORMATION_PYTHON` (default `python3`); it needs
//! rosbags, mcap-ros2-support and ruamel.yaml. Without them the tests print
//! "skipped: …" and pass, unless `FORMATION_ROS2_REQUIRED=1`, when they
//! fail naming what is missing. Locally:
//! `FORMATION_PYTHON=/work/ros2-venv/bin/python FORMATION_ROS2_REQUIRED=1 cargo test -p formation-ros2`.

use formation_ros2::bag::BagWriter;
use formation_ros2::msgs::*;
use formation_ros2::rmw_keys::Qos;
use formation_ros2::Message;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;

fn python() -> String {
    std::env::var("FORMATION_PYTHON").unwrap_or_else(|_| "python3".to_string())
}

/// Whether the Python side can run; if not, the reason.
fn probe() -> Result<(), String> {
    let imports = "import rosbags.typesys, rosbags.rosbag2, mcap.reader, mcap_ros2.reader, ruamel.yaml";
    let out =
        Command::new(python()).args(["-c", imports]).output().map_err(|e| format!("cannot run {}: {e}", python()))?;
    if out.status.success() {
        return Ok(());
    }
    let stderr = String::from_utf8_lossy(&out.stderr);
    Err(format!("{}: {}", python(), stderr.lines().last().unwrap_or("import failed")))
}

/// True when the checks can run. Fails the test instead of skipping when
/// `FORMATION_ROS2_REQUIRED=1`.
fn python_ready() -> bool {
    match probe() {
        Ok(()) => true,
        Err(why) if std::env::var("FORMATION_ROS2_REQUIRED").as_deref() == Ok("1") => {
            panic!("FORMATION_ROS2_REQUIRED=1 but the Python cross-check cannot run: {why}")
        }
        Err(why) => {
            eprintln!("skipped: {why} (set FORMATION_PYTHON to an interpreter with rosbags and mcap-ros2-support)");
            false
        }
    }
}

/// Runs `tests/python/<script> <dir>` and fails with its output if it fails.
fn run_script(script: &str, dir: &Path) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python").join(script);
    // No __pycache__ left in the source tree.
    let mut command = Command::new(python());
    command.env("PYTHONDONTWRITEBYTECODE", "1").arg(&path).arg(dir);
    let out = command.output().expect("running the Python check");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{script} failed (its input is kept in {}):\n{text}", dir.display());
    eprintln!("{text}");
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("formation-ros2-py-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch folder");
    dir
}

/// The fields a decoder should find, by ROS field name.
trait Expected {
    fn expected(&self) -> Value;
}

impl Expected for Time {
    fn expected(&self) -> Value {
        json!({"sec": self.sec, "nanosec": self.nanosec})
    }
}
impl Expected for Header {
    fn expected(&self) -> Value {
        json!({"stamp": self.stamp.expected(), "frame_id": self.frame_id})
    }
}
impl Expected for Vector3 {
    fn expected(&self) -> Value {
        json!({"x": self.x, "y": self.y, "z": self.z})
    }
}
impl Expected for Point {
    fn expected(&self) -> Value {
        json!({"x": self.x, "y": self.y, "z": self.z})
    }
}
impl Expected for Quaternion {
    fn expected(&self) -> Value {
        json!({"x": self.x, "y": self.y, "z": self.z, "w": self.w})
    }
}
impl Expected for Pose {
    fn expected(&self) -> Value {
        json!({"position": self.position.expected(), "orientation": self.orientation.expected()})
    }
}
impl Expected for Twist {
    fn expected(&self) -> Value {
        json!({"linear": self.linear.expected(), "angular": self.angular.expected()})
    }
}
impl Expected for PoseWithCovariance {
    fn expected(&self) -> Value {
        json!({"pose": self.pose.expected(), "covariance": self.covariance.to_vec()})
    }
}
impl Expected for TwistWithCovariance {
    fn expected(&self) -> Value {
        json!({"twist": self.twist.expected(), "covariance": self.covariance.to_vec()})
    }
}
impl Expected for PoseStamped {
    fn expected(&self) -> Value {
        json!({"header": self.header.expected(), "pose": self.pose.expected()})
    }
}
impl Expected for Transform {
    fn expected(&self) -> Value {
        json!({"translation": self.translation.expected(), "rotation": self.rotation.expected()})
    }
}
impl Expected for TransformStamped {
    fn expected(&self) -> Value {
        json!({"header": self.header.expected(), "child_frame_id": self.child_frame_id, "transform": self.transform.expected()})
    }
}
impl Expected for Odometry {
    fn expected(&self) -> Value {
        json!({
            "header": self.header.expected(),
            "child_frame_id": self.child_frame_id,
            "pose": self.pose.expected(),
            "twist": self.twist.expected(),
        })
    }
}
impl Expected for TFMessage {
    fn expected(&self) -> Value {
        json!({"transforms": self.transforms.iter().map(Expected::expected).collect::<Vec<_>>()})
    }
}
impl Expected for Clock {
    fn expected(&self) -> Value {
        json!({"clock": self.clock.expected()})
    }
}

/// Samples whose every value differs, so a swapped or misplaced field shows.
fn header(k: f64, frame: &str) -> Header {
    Header {
        stamp: Time { sec: 1_700_000_000 + k as i32, nanosec: 123_456_789 + k as u32 },
        frame_id: frame.to_string(),
    }
}

fn odometry(k: f64, frame: &str, child: &str) -> Odometry {
    Odometry {
        header: header(k, frame),
        child_frame_id: child.to_string(),
        pose: PoseWithCovariance {
            pose: Pose {
                position: Point { x: k + 0.1, y: k + 0.2, z: k + 0.3 },
                orientation: Quaternion::from_yaw(k * 0.1),
            },
            covariance: core::array::from_fn(|i| k + i as f64 / 64.0),
        },
        twist: TwistWithCovariance {
            twist: Twist {
                linear: Vector3 { x: k + 0.4, y: k + 0.5, z: k + 0.6 },
                angular: Vector3 { x: -k, y: 1e-300, z: k * 1e10 },
            },
            covariance: core::array::from_fn(|i| -k - i as f64 / 128.0),
        },
    }
}

fn pose_stamped(k: f64) -> PoseStamped {
    PoseStamped {
        header: header(k, "world"),
        pose: Pose { position: Point { x: k, y: -k, z: 0.0 }, orientation: Quaternion::from_yaw(-k) },
    }
}

fn transform(k: f64, child: &str) -> TransformStamped {
    TransformStamped {
        header: header(k, "world"),
        child_frame_id: child.to_string(),
        transform: Transform { translation: Vector3 { x: k, y: k * 2.0, z: 0.0 }, rotation: Quaternion::from_yaw(k) },
    }
}

fn tf(k: f64) -> TFMessage {
    TFMessage {
        transforms: vec![transform(k, "leader"), transform(k + 1.0, "follower_1"), transform(k + 2.0, "fölløwer_2")],
    }
}

fn twist(k: f64) -> Twist {
    Twist { linear: Vector3 { x: k, y: k + 0.25, z: -k }, angular: Vector3 { x: 0.0, y: -0.0, z: k / 3.0 } }
}

fn clock(k: f64) -> Clock {
    Clock { clock: header(k, "").stamp }
}

/// One manifest entry for check_cdr.py, with the payload written to `dir`.
fn sample<M: Message + Expected>(dir: &Path, m: &M) -> Value {
    let file = format!("{}_{}.cdr", M::TYPE.replace('/', "_"), std::fs::read_dir(dir).expect("scratch").count());
    std::fs::write(dir.join(&file), m.encode()).expect("writing a payload");
    json!({"file": file, "type": M::TYPE, "hash": M::HASH, "definition": M::DEFINITION, "expected": m.expected()})
}

#[test]
fn rosbags_decodes_every_payload_and_agrees_on_hashes_and_definitions() {
    if !python_ready() {
        return;
    }
    let dir = scratch("cdr");
    let samples = vec![
        sample(&dir, &Time { sec: -7, nanosec: 999_999_999 }),
        sample(&dir, &header(3.0, "base_link")),
        sample(&dir, &Vector3 { x: 1.5, y: -2.5, z: f64::MAX }),
        sample(&dir, &Point { x: 0.1, y: 0.2, z: 0.3 }),
        sample(&dir, &Quaternion::from_yaw(2.5)),
        sample(&dir, &odometry(4.0, "a", "b").pose.pose),
        sample(&dir, &twist(0.7)),
        sample(&dir, &odometry(5.0, "", "").pose),
        sample(&dir, &odometry(6.0, "", "").twist),
        sample(&dir, &pose_stamped(1.25)),
        sample(&dir, &transform(2.0, "x").transform),
        sample(&dir, &transform(2.0, "follower_3")),
        sample(&dir, &odometry(1.0, "world", "follower_1")),
        sample(&dir, &odometry(2.0, "", "")),
        sample(&dir, &odometry(3.0, "odom", "follower_1/base_link")),
        sample(&dir, &tf(0.5)),
        sample(&dir, &TFMessage::default()),
        sample(&dir, &clock(9.0)),
    ];
    std::fs::write(dir.join("manifest.json"), serde_json::to_string_pretty(&samples).unwrap()).unwrap();
    run_script("check_cdr.py", &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

/// What check_bag.py expects of one topic.
fn topic(type_: &str, hash: &str, count: usize, qos: Qos) -> Value {
    json!({
        "type": type_, "hash": hash, "count": count, "depth": qos.depth,
        "reliability": if qos.reliable { "reliable" } else { "best_effort" },
        "durability": if qos.transient_local { "transient_local" } else { "volatile" },
    })
}

#[test]
fn rosbags_and_mcap_ros2_read_a_bag_folder() {
    if !python_ready() {
        return;
    }
    let dir = scratch("bag");
    let bag_dir = dir.join("formation_bag");
    let mut bag = BagWriter::create(&bag_dir).expect("creating the bag");
    let (odom_qos, clock_qos) = (Qos::default(), Qos::best_effort(1));
    let odom = bag.add_topic::<Odometry>("/follower_1/odom", odom_qos).unwrap();
    let cmd = bag.add_topic::<Twist>("/follower_1/cmd_vel", Qos::default()).unwrap();
    let est = bag.add_topic::<PoseStamped>("/follower_1/leader_estimate", Qos::default()).unwrap();
    let tf_id = bag.add_topic::<TFMessage>("/tf", Qos { reliable: true, transient_local: false, depth: 100 }).unwrap();
    let clk = bag.add_topic::<Clock>("/clock", clock_qos).unwrap();
    let mut messages = Vec::new();
    let t0 = 1_700_000_000_000_000_000u64;
    for step in 0..5u64 {
        let k = step as f64;
        let mut put = |id, offset: u64, topic: &str, cdr: Vec<u8>, expected: Value| {
            let t = t0 + step * 10_000_000 + offset;
            bag.write(id, t, &cdr).expect("writing a message");
            messages.push(json!({"topic": topic, "log_time": t, "expected": expected}));
        };
        let o = odometry(k, "world", "follower_1");
        put(clk, 0, "/clock", clock(k).encode(), clock(k).expected());
        put(odom, 1, "/follower_1/odom", o.encode(), o.expected());
        put(cmd, 2, "/follower_1/cmd_vel", twist(k).encode(), twist(k).expected());
        put(est, 3, "/follower_1/leader_estimate", pose_stamped(k).encode(), pose_stamped(k).expected());
        if step % 2 == 0 {
            put(tf_id, 4, "/tf", tf(k).encode(), tf(k).expected());
        }
    }
    let summary = bag.finish().expect("finishing the bag");
    assert_eq!(summary.message_count, messages.len() as u64);
    let expected = json!({
        "bag": bag_dir,
        "topics": {
            "/follower_1/odom": topic(Odometry::TYPE, Odometry::HASH, 5, odom_qos),
            "/follower_1/cmd_vel": topic(Twist::TYPE, Twist::HASH, 5, Qos::default()),
            "/follower_1/leader_estimate": topic(PoseStamped::TYPE, PoseStamped::HASH, 5, Qos::default()),
            "/tf": topic(TFMessage::TYPE, TFMessage::HASH, 3, Qos { reliable: true, transient_local: false, depth: 100 }),
            "/clock": topic(Clock::TYPE, Clock::HASH, 5, clock_qos),
        },
        "messages": messages,
    });
    std::fs::write(dir.join("expected.json"), serde_json::to_string_pretty(&expected).unwrap()).unwrap();
    run_script("check_bag.py", &dir);
    let _ = std::fs::remove_dir_all(&dir);
}
