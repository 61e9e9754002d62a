//! A formation in the leader's frame, with shapes that change during a run
//! (docs/model.md §17): the slots turn with the leader, a shape change gives
//! the robots the slots that cost least and the safety filter keeps them
//! apart while they change places, `scenarios/doorway.toml` passes its door
//! as a column, and lock-step runs equal `formation sim` byte for byte.
//! A leader played from a run's record (docs/model.md §18) is that run's
//! leader bit for bit, in `sim` and in lock-step; the live sources' bad
//! inputs are one line and exit 2.

use std::path::Path;
use std::process::Command;

use crate::common::{self, Group, LIMIT};
use formation_scenario::shape::{named, total_cost};
use formation_scenario::Scenario;

const TURTLEBOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/turtlebot.toml");

/// The doorway's door: its x, m, and the half width a robot's centre must
/// keep inside (a 0.6 m opening less a Burger's half width, 0.09 m).
const DOOR_X: f64 = 0.5;
const DOOR_HALF_M: f64 = 0.21;

/// What `formation sim` said and wrote.
fn sim(scenario: &str, out: &Path, sets: &[&str]) -> (std::process::Output, serde_json::Value) {
    let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
    c.args(["sim", scenario, "--out"]).arg(out);
    for s in sets {
        c.args(["--set", s]);
    }
    let o = c.output().expect("formation sim");
    assert!(o.status.success(), "formation sim {scenario} {sets:?}: {}", String::from_utf8_lossy(&o.stderr));
    (o, common::json(out, "summary.json"))
}

/// One CSV's columns by name, as numbers.
fn columns(path: &Path, names: &[&str]) -> Vec<Vec<f64>> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let at: Vec<usize> = names.iter().map(|n| header.iter().position(|h| h == n).expect("column")).collect();
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            at.iter().map(|&i| f[i].parse().expect("number")).collect()
        })
        .collect()
}

/// Each follower's position in the leader's frame (ahead, to the left) at
/// every step of the run in `dir`.
fn in_leader_frame(dir: &Path, id: u32) -> Vec<[f64; 2]> {
    let leader = columns(&dir.join("leader.csv"), &["x", "y", "theta"]);
    let f = columns(&dir.join(format!("follower_{id}.csv")), &["x", "y"]);
    leader
        .iter()
        .zip(&f)
        .map(|(l, p)| {
            let (s, c) = l[2].sin_cos();
            let (dx, dy) = (p[0] - l[0], p[1] - l[1]);
            [c * dx + s * dy, -s * dx + c * dy]
        })
        .collect()
}

/// `turtlebot` in the leader's frame, its followers 1 and 2 starting on
/// their own sides (in the scenario they start crossed, and in the leader's
/// frame 1 is then held behind 2 for good: the gap between 2 and 3 is
/// 0.71 m, the barrier needs 0.70 m and its margin).
fn turtlebot_in_the_leaders_frame(dir: &Path) -> String {
    let text = std::fs::read_to_string(TURTLEBOT).expect("turtlebot.toml");
    let (one, two) = ("pose = [-1.3, -1.7, 0.6]", "pose = [-1.3, -0.7, -0.6]");
    assert!(text.contains(one) && text.contains(two), "turtlebot.toml's start poses changed");
    let text = text.replace(one, "pose = [X]").replace(two, one).replace("pose = [X]", two);
    let path = dir.join("turtlebot-leader.toml");
    std::fs::write(&path, format!("{text}\n[formation]\nframe = \"leader\"\n")).expect("write scenario");
    path.display().to_string()
}

#[test]
fn in_the_leaders_frame_the_slots_turn_with_the_leader_and_lock_step_equals_sim() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = turtlebot_in_the_leaders_frame(dir.path());
    let sim_dir = dir.path().join("sim");
    let (_, summary) = sim(&scenario, &sim_dir, &[]);
    assert_eq!(summary["frame"], "leader", "summary.json names the frame");
    let offsets = [[-0.5, 0.25], [-0.5, -0.25], [-1.0, 0.25], [-1.0, -0.25]];
    let leader = columns(&sim_dir.join("leader.csv"), &["x", "y", "theta"]);
    let last10 = leader.len() - 500; // 10 s at 20 ms
    for (i, want) in offsets.iter().enumerate() {
        let id = i as u32 + 1;
        let at = in_leader_frame(&sim_dir, id);
        let worst = at[last10..].iter().map(|p| (p[0] - want[0]).hypot(p[1] - want[1])).fold(0.0, f64::max);
        assert!(
            worst < 0.05,
            "follower {id}: {worst:.3} m from its offset {want:?} in the leader's frame in the last 10 s"
        );
        // The slot turned: in the world frame the follower is no longer at p_r + Δ.
        let f = columns(&sim_dir.join(format!("follower_{id}.csv")), &["x", "y"]);
        let k = leader.len() / 2; // t = 30 s: the leader has turned about 3 rad
        let world = (f[k][0] - leader[k][0] - want[0]).hypot(f[k][1] - leader[k][1] - want[1]);
        assert!(world > 0.5, "follower {id}: {world:.3} m from p_r + Δ at t = 30 s: the slot did not turn");
    }
    let closest = summary["safety"]["closest"]["distance"].as_f64().unwrap();
    assert!(closest >= 0.25, "robots came {closest} m apart (safety.distance 0.25 m)");

    let out = dir.path().join("run");
    let o = out.display().to_string();
    let log = dir.path().join("launch.log");
    let mut run = Group::spawn_logged(&["launch", &scenario, "-q", "--out", &o], &log);
    let status = run.wait(LIMIT * 2);
    let said = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(status.success(), "launch (leader's frame): {status}\n{said}");
    run.assert_group_empty();
    common::same_files(&out, &sim_dir, "the leader's-frame lock-step run");
}

/// The permutation of `to` that costs least from `from`, by trying all.
fn brute_force(from: &[[f64; 2]], to: &[[f64; 2]]) -> (f64, Vec<usize>) {
    fn each(p: &mut Vec<usize>, k: usize, visit: &mut dyn FnMut(&[usize])) {
        if k == p.len() {
            return visit(p);
        }
        for i in k..p.len() {
            p.swap(k, i);
            each(p, k + 1, visit);
            p.swap(k, i);
        }
    }
    let mut best = (f64::INFINITY, Vec::new());
    each(&mut (0..from.len()).collect(), 0, &mut |p| {
        let c = total_cost(from, to, p);
        if c < best.0 {
            best = (c, p.to_vec());
        }
    });
    best
}

#[test]
fn a_shape_change_at_20_s_gives_the_cheapest_slots_and_the_robots_reach_them_apart() {
    let s = Scenario::load(Path::new("doorway"), &[]).expect("doorway");
    let wedge: Vec<[f64; 2]> = s.followers.iter().map(|f| f.offset).collect();
    let column = named("column", 4, 0.5).unwrap();
    let change = &s.shapes[0];
    assert_eq!((change.at_s, change.name.as_str()), (20.0, "column"));
    let assigned: Vec<usize> =
        change.offsets.iter().map(|o| column.iter().position(|c| c == o).expect("a column slot")).collect();
    let (best, by) = brute_force(&wedge, &column);
    let cost = total_cost(&wedge, &column, &assigned);
    assert!((cost - best).abs() < 1e-12, "assigned {assigned:?} costs {cost} m², the best {by:?} {best} m²");
    // Robots 1 and 2 start side by side and end in one file: one of them
    // must cross the other's lane (as must 3 and 4).
    for (a, b) in [(0, 1), (2, 3)] {
        assert!(wedge[a][1] * wedge[b][1] < 0.0 && change.offsets[a][1] == 0.0 && change.offsets[b][1] == 0.0);
    }

    let dir = tempfile::tempdir().expect("tempdir");
    let (o, summary) = sim("doorway", &dir.path().join("sim"), &[]);
    let said = String::from_utf8_lossy(&o.stdout);
    for (i, change) in summary["shapes"].as_array().expect("shapes").iter().enumerate() {
        for (id, t) in change["settled_after"].as_object().unwrap() {
            let t = t.as_f64().unwrap_or_else(|| panic!("change {i}: follower {id} never within 0.1 m:\n{said}"));
            assert!(t <= 15.0, "change {i}: follower {id} within 0.1 m of its slot {t} s after (stated: 15 s)");
        }
        let closest = summary["safety"]["after_shapes"][i]["closest"]["distance"].as_f64().unwrap();
        assert!(closest >= 0.25, "change {i}: robots came {closest} m apart (safety.distance 0.25 m)");
    }
    assert_eq!(summary["safety"]["steps_below"], 0);
    assert!(said.contains("shape at t = 20 s, column"), "the end-of-run lines name the change:\n{said}");
}

/// Through the door every robot's centre is within the opening, in lock-step
/// with stand-in robots as in `formation sim`, byte for byte.
#[test]
fn the_doorway_is_passed_as_a_column_by_sim_and_by_stand_in_robots_alike() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sim_dir = dir.path().join("sim");
    sim("doorway", &sim_dir, &[]);
    for id in 1..=4 {
        let p = columns(&sim_dir.join(format!("follower_{id}.csv")), &["t", "x", "y"]);
        let at = p.windows(2).find(|w| w[0][1] < DOOR_X && w[1][1] >= DOOR_X).expect("the follower reached the door");
        let y = at[1][2];
        assert!(y.abs() < DOOR_HALF_M, "follower {id} passed the door {y:.3} m off its centre at t = {} s", at[1][0]);
        assert!(at[1][0] > 20.0 && at[1][0] < 60.0, "follower {id} at the door at t = {} s, not as a column", at[1][0]);
    }
    let out = dir.path().join("run");
    let (o, log) = (out.display().to_string(), dir.path().join("launch.log"));
    let mut run = Group::spawn_logged(&["launch", "doorway", "-q", "--out", &o, "--robots", "stand-in"], &log);
    let status = run.wait(LIMIT * 2);
    let said = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(status.success(), "launch doorway --robots stand-in: {status}\n{said}");
    run.assert_group_empty();
    common::same_files(&out, &sim_dir, "the doorway with stand-in robots");
    common::replays_byte_for_byte("doorway, stand-in robots", &out);
}

#[test]
fn bad_frames_shapes_and_routes_are_one_line_and_exit_2() {
    let dir = tempfile::tempdir().expect("tempdir");
    for (set, want) in [
        ("formation.frame=\"diagonal\"", "formation.frame: `diagonal` is not one of: world, leader"),
        ("formation.shapes=[{at=20.0,shape=\"star\"}]", "`star` is not one of: line, column, wedge, diamond, circle"),
        ("formation.shapes=[{at=20.0,offsets=[[-1.0,0.0]]}]", "1 offsets for 4 followers: give one per follower"),
        ("formation.shapes=[{at=20.0,shape=\"line\",spacing=0.1}]", "closer than safety.distance (0.25 m)"),
        ("formation.shapes=[{at=90.0,shape=\"line\"}]", "90 s is not after 0 s and before the run's end (85 s)"),
        ("formation.shapes=[{at=20.0}]", "missing: give `shape`"),
        ("leader.waypoints=[[9.0,0.0]]", "point 1 (9, 0) is outside the arena"),
        ("leader.turn_rate=-1", "leader.turn_rate: must be positive, got -1"),
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(["sim", "doorway", "-q", "--set", set, "--out"])
            .arg(dir.path().join("x"))
            .output()
            .expect("formation sim");
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "--set {set}: {err}");
        assert_eq!(err.lines().count(), 1, "--set {set}: one line, got:\n{err}");
        assert!(err.contains(want), "--set {set}: {err}");
    }
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", "turtlebot", "-q", "--set", "leader.reach=0.2", "--out"])
        .arg(dir.path().join("y"))
        .output()
        .expect("formation sim");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("leader.reach: only for trajectory = \"waypoints\""), "{err}");
    assert!(!dir.path().join("x").exists(), "a refused scenario wrote a folder");
}

/// A run's leader record played again (`leader.source = "recorded"`):
/// `formation sim` writes every file of the run it came from byte for
/// byte, and a lock-step run with it equals that sim and replays.
#[test]
fn a_recorded_leader_is_its_run_again_in_sim_and_in_lock_step() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = turtlebot_in_the_leaders_frame(dir.path());
    let first = dir.path().join("first");
    sim(&scenario, &first, &[]);
    let recorded = format!("leader.recorded=\"{}\"", first.display());
    let again = dir.path().join("again");
    sim(&scenario, &again, &["leader.source=recorded", &recorded]);
    common::same_files(&again, &first, "the run simulated again from its leader's record");
    // `--leader RUN` is the same.
    let flag = dir.path().join("flag");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", &scenario, "-q", "--leader"])
        .arg(&first)
        .arg("--out")
        .arg(&flag)
        .output()
        .expect("formation sim --leader");
    assert!(o.status.success(), "sim --leader RUN: {}", String::from_utf8_lossy(&o.stderr));
    common::same_files(&flag, &first, "the run simulated again with --leader RUN");

    let out = dir.path().join("run");
    let o = out.display().to_string();
    let log = dir.path().join("launch.log");
    let args = ["launch", &scenario, "-q", "--out", &o, "--set", "leader.source=recorded", "--set", &recorded];
    let mut run = Group::spawn_logged(&args, &log);
    let status = run.wait(LIMIT * 2);
    let said = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(status.success(), "launch with a recorded leader: {status}\n{said}");
    run.assert_group_empty();
    common::same_files(&out, &first, "the lock-step run with a recorded leader");
    common::replays_byte_for_byte("a recorded leader, lock-step", &out);
}

#[test]
fn bad_leader_sources_and_records_are_one_line_and_exit_2() {
    let dir = tempfile::tempdir().expect("tempdir");
    let record = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).expect("write");
        format!("leader.recorded=\"{}\"", p.display())
    };
    let fine_dt = record("fine.csv", "t,x,y,theta,v,w\n0,0,0,0,0,0\n0.01,0,0,0,0,0\n");
    let short = record("short.csv", "t,x,y,theta,v,w\n0,0,0,0,0,0\n0.02,0,0,0,0,0\n");
    let not_csv = record("notes.txt", "hello\n");
    let missing = format!("leader.recorded=\"{}\"", dir.path().join("nowhere").display());
    let cases: [(&[&str], &str); 13] = [
        (
            &["leader.source=cmd_vel", "timing=realtime", "leader.reach=0.2"],
            "leader.reach: not with source = \"cmd_vel\"",
        ),
        (&["leader.source=robot", "timing=realtime", "leader.timeout=1e20"], "leader.timeout: 1e20 is beyond ±3600 s"),
        (&["leader.source=joystick"], "`joystick` is not one of: trajectory, cmd_vel, path, robot, recorded"),
        (&["leader.source=path", "timing=realtime", "leader.waypoints=[[1.0,0.0]]"], "the route comes on /leader/path"),
        (&["leader.source=path", "timing=realtime", "leader.reach=0"], "leader.reach: must be positive"),
        (&["leader.source=cmd_vel"], "it runs in real time (timing = \"realtime\")"),
        (&["leader.source=cmd_vel", "timing=realtime"], "a simulation plays such a run again from its record"),
        (&["leader.source=robot", "timing=realtime", "leader.timeout=0"], "leader.timeout: must be positive"),
        (&["leader.source=recorded"], "leader.recorded: missing"),
        (&["leader.source=recorded", &fine_dt], "its rows are 0.01 s apart; the scenario's dt is 0.02 s"),
        (&["leader.source=recorded", &short], "it ends at t = 0.02 s (1 steps); the scenario runs 60 s"),
        (&["leader.source=recorded", &not_csv], "not a leader record"),
        (&["leader.source=recorded", &missing], "No such file"),
    ];
    for (sets, want) in cases {
        let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
        c.args(["sim", TURTLEBOT, "-q", "--out"]).arg(dir.path().join("x"));
        for s in sets {
            c.args(["--set", s]);
        }
        let o = c.output().expect("formation sim");
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "--set {sets:?}: {err}");
        assert_eq!(err.lines().count(), 1, "--set {sets:?}: one line, got:\n{err}");
        assert!(err.contains(want), "--set {sets:?}: {err}");
        assert!(!dir.path().join("x").exists(), "--set {sets:?}: no run folder for a refused scenario");
    }
    // The limits of cmd_vel, and a standby for a leader that nobody but it hears.
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", "teleop", "-q", "--set", "leader.turn_rate=-1", "--out"])
        .arg(dir.path().join("y"))
        .output()
        .expect("formation sim");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && err.contains("leader.turn_rate: must be positive, got -1"), "{err}");
    let o = Command::new(env!("CARGO_BIN_EXE_leader"))
        .args(["--scenario", "teleop", "--standby", "--run", "standby-refused"])
        .output()
        .expect("leader --standby");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && err.contains("cannot be taken over"), "leader --standby: {err}");
}
