//! The formation on ROS 2's wire, lock-step: stand-in robots driven
//! through `cmd_vel` and `odom` give `formation sim`'s run byte for byte,
//! and the run's rosbag2 folder is read back by two readers that are not
//! this project's (rosbags, mcap-ros2-support). The real-time checks (a
//! foreign subscriber, an external Python robot) are in tests/realtime/ros2.rs.

use std::process::Command;

use crate::common::{self, Group, LIMIT, VELOCITY_SCENARIO};

/// A short lock-step run of the paper's formation on velocity-commanded robots.
const SETS: [&str; 1] = ["duration=1.5"];

#[test]
fn stand_in_robots_in_lock_step_equal_formation_sim_and_record_a_readable_bag() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("run");
    let o = out.display().to_string();
    let mut args = vec!["launch", VELOCITY_SCENARIO, "-q", "--out", &o, "--robots", "stand-in", "--rosbag2"];
    for s in SETS {
        args.extend(["--set", s]);
    }
    let mut run = Group::spawn(&args);
    let status = run.wait(LIMIT * 2);
    assert!(status.success(), "launch --robots stand-in: {status}");
    run.assert_group_empty();

    // The same numbers as the simulator's velocity-commanded robots.
    let sim = dir.path().join("sim");
    let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
    c.args(["sim", VELOCITY_SCENARIO, "-q", "--out"]).arg(&sim);
    for s in SETS {
        c.args(["--set", s]);
    }
    common::run_ok(&mut c);
    for f in ["leader.csv", "follower_1.csv", "follower_2.csv", "follower_3.csv", "follower_4.csv"] {
        let got = std::fs::read(out.join(f)).expect("run file");
        let want = std::fs::read(sim.join(f)).expect("sim file");
        let first = got.iter().zip(&want).position(|(a, b)| a != b);
        assert!(
            got == want,
            "{f} through stand-in robots differs from formation sim's (first differing byte {first:?}, {} vs {} bytes)",
            got.len(),
            want.len()
        );
    }

    // The bag, read by rosbags and mcap-ros2-support.
    let Some(python) = common::ros2_python() else { return };
    let seen = dir.path().join("bag.json");
    common::run_ok(
        Command::new(&python).arg(common::ros2_script("read_bag.py")).arg(out.join("rosbag2")).arg("--out").arg(&seen),
    );
    let topics = common::json(dir.path(), "bag.json");
    let rows = std::fs::read_to_string(out.join("follower_1.csv")).expect("csv").lines().count() as u64 - 1;
    let mut names: Vec<&String> = topics.as_object().expect("topics").keys().collect();
    names.sort();
    let mut want = vec!["/clock".to_string(), "/leader/odom".into(), "/tf".into()];
    for i in 1..=4 {
        want.extend([
            format!("/follower_{i}/cmd_vel"),
            format!("/follower_{i}/leader_estimate"),
            format!("/follower_{i}/odom"),
        ]);
    }
    want.sort();
    assert_eq!(names, want.iter().collect::<Vec<_>>(), "the bag's topics");
    for (topic, t) in topics.as_object().expect("topics") {
        let per_row = if topic == "/tf" { 5 } else { 1 };
        let n = |k: &str| t[k].as_u64().unwrap_or(0);
        assert_eq!(
            (n("counted"), n("rosbags"), n("mcap_ros2")),
            (rows * per_row, rows * per_row, rows * per_row),
            "{topic}: messages in metadata, decoded by rosbags, decoded by mcap-ros2-support ({rows} rows)"
        );
    }
    // The odometry as the CSV has it (last row of follower 1).
    let last = std::fs::read_to_string(out.join("follower_1.csv")).expect("csv");
    let cols: Vec<f64> =
        last.lines().last().expect("a row").split(',').take(4).map(|v| v.parse().expect("number")).collect();
    let pose = &topics["/follower_1/odom"]["last_pose"];
    let (x, y, th) = (pose[1].as_f64().unwrap(), pose[2].as_f64().unwrap(), pose[3].as_f64().unwrap());
    assert_eq!((x, y), (cols[1], cols[2]), "follower 1's last odometry position in the bag vs its CSV row");
    let d = (th - cols[3]).rem_euclid(std::f64::consts::TAU);
    assert!(d.min(std::f64::consts::TAU - d) < 1e-12, "heading {th} in the bag vs {} in the CSV", cols[3]);
}

/// docs/ros2.md, "Odometry in the robot's frame": stand-in robots whose
/// odometry starts at (0, 0, 0) at their scenario poses, driven with
/// `robot.odom_origin = "start"`, end where world-frame robots do: the
/// formation errors of `formation sim` to 1e-9 m (the frame change rounds).
#[test]
fn stand_in_robots_with_odometry_from_their_start_end_as_world_frame_robots() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("run");
    let o = out.display().to_string();
    let sets = ["duration=3", "robot.odom_origin=\"start\""];
    let mut args = vec!["launch", VELOCITY_SCENARIO, "-q", "--out", &o, "--robots", "stand-in"];
    for s in &sets {
        args.extend(["--set", s]);
    }
    let mut run = Group::spawn(&args);
    let status = run.wait(LIMIT * 2);
    assert!(status.success(), "launch --robots stand-in with odom_origin = start: {status}");
    run.assert_group_empty();
    let sim = dir.path().join("sim");
    let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
    c.args(["sim", VELOCITY_SCENARIO, "-q", "--out"]).arg(&sim);
    for s in &sets {
        c.args(["--set", s]);
    }
    common::run_ok(&mut c);
    let (got, want) = (common::json(&out, "summary.json"), common::json(&sim, "summary.json"));
    for id in ["1", "2", "3", "4"] {
        for m in ["formation_final", "formation_rms_last10", "heading_final", "estimator_error_final"] {
            let (g, w) = (got["followers"][id][m].as_f64().unwrap(), want["followers"][id][m].as_f64().unwrap());
            assert!(
                (g - w).abs() < 1e-9,
                "follower {id} {m}: {g} through odometry from its start, {w} in formation sim"
            );
        }
    }
}
