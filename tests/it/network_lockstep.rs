//! Lock-step networked runs against the in-process simulator (free ports
//! on 127.0.0.1, see `common::Ports`; multicast scouting off in every
//! session).
//!
//! Each run is `formation launch` in its own process group; a guard kills
//! the whole group on every path, and every wait is bounded.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use common::{Group, Ports, LAUNCH_PORTS, LIMIT, SCENARIO};
use formation_leader::LeaderState;
use formation_net::session::{self, ZenohArgs};
use formation_protocol::wire::{self, EstimateMsg, Header, FORMAT_VERSION};

fn sim(dir: &Path, sets: &[&str]) -> String {
    let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
    c.args(["sim", SCENARIO, "-q", "--out"]).arg(dir);
    for s in sets {
        c.args(["--set", s]);
    }
    assert!(c.status().expect("formation sim").success());
    std::fs::read_to_string(dir.join("summary.json")).expect("sim summary")
}

/// Launches a networked lock-step run and checks that its folder matches
/// `formation sim`'s byte for byte (summary.json and every CSV).
fn same_as_sim(tag: &str, sets: &[&str], extra: &[&str]) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("tempdir");
    let tmp = dir.path().to_path_buf();
    let net = tmp.join("net");
    let mut g = Group::launch(&net, sets, extra);
    let expected = sim(&tmp.join("sim"), sets);
    let status = g.wait(LIMIT);
    assert!(status.success(), "{tag}: formation launch failed: {status}");
    let got = std::fs::read_to_string(net.join("summary.json")).expect("monitor summary");
    assert_eq!(got, expected, "{tag}: networked summary.json differs from formation sim's");
    for f in ["follower_1.csv", "follower_4.csv", "leader.csv"] {
        let a = std::fs::read(net.join(f)).expect("net csv");
        let b = std::fs::read(tmp.join("sim").join(f)).expect("sim csv");
        assert!(a == b, "{tag}: {f} differs");
    }
    (dir, net)
}

fn network(dir: &Path) -> serde_json::Value {
    common::json(dir, "network.json")
}

#[test]
fn lockstep_noise_free_equals_sim() {
    let base = Ports::free(LAUNCH_PORTS).release().to_string();
    let (_dir, net) =
        same_as_sim("noise off", &["duration=2", "noise=false"], &["--base-port", &base, "--run", "ls-a"]);
    let n = network(&net);
    assert_eq!(n["complete"], true);
    assert_eq!(n["nodes"]["1"]["rejected_invalid"], 0);
}

#[test]
fn lockstep_with_noise_equals_sim() {
    let base = Ports::free(LAUNCH_PORTS).release().to_string();
    same_as_sim("noise on", &["duration=2"], &["--base-port", &base, "--run", "ls-b"]);
}

/// docs/model.md §15: the agents drive velocity-commanded robots (the same
/// `SimFollower`, fed odometry), and lock-step still equals the simulator.
#[test]
fn lockstep_on_velocity_commanded_robots_equals_sim() {
    let base = Ports::free(LAUNCH_PORTS).release().to_string();
    same_as_sim("velocity robot", &["duration=2", "robot.model=velocity"], &["--base-port", &base, "--run", "ls-v"]);
}

/// `launch --links tcp`: the nodes link over loopback TCP, as between hosts,
/// instead of the default unix sockets; the same run.
#[test]
fn lockstep_over_tcp_links_equals_sim() {
    let base = Ports::free(LAUNCH_PORTS).release().to_string();
    same_as_sim("tcp links", &["duration=1"], &["--links", "tcp", "--base-port", &base, "--run", "ls-t"]);
}

#[test]
fn client_mode_through_router_equals_sim() {
    let base = Ports::free(1).release().to_string();
    same_as_sim("client mode", &["duration=1"], &["--mode", "client", "--base-port", &base, "--run", "ls-c"]);
}

fn msg(sender: u32, step: u64, v: f64) -> Vec<u8> {
    wire::encode(&EstimateMsg {
        header: Header { version: FORMAT_VERSION, sender, step, time_s: step as f64 * 1e-3, sent_ns: 0 },
        state: LeaderState { v, ..Default::default() },
        fresh: true,
        term: u32::from(sender == 0),
    })
}

/// A rogue session publishes garbage, wrong-sender, non-finite and
/// foreign-version messages, far-future steps (u64::MAX and a flood of
/// distinct future steps) on every estimate key during a lock-step run,
/// and start-barrier messages with a foreign fingerprint: the result is
/// unchanged and the rejections are counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rogue_messages_are_rejected_and_counted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let tmp = dir.path();
    let net = tmp.join("net");
    let sets = ["duration=3", "noise=false"];
    // Ports: the monitor's base, the leader's base + 1, the agents' base +
    // 2 to base + 5; the rogue listens on base + 6.
    let base = Ports::free(LAUNCH_PORTS + 1).release();
    let mut g = Group::launch(&net, &sets, &["--base-port", &base.to_string(), "--run", "rogue"]);
    let args = ZenohArgs {
        listen: vec![format!("tcp/127.0.0.1:{}", base + 6)],
        connect: (base + 1..=base + 5).map(|p| format!("tcp/127.0.0.1:{p}")).collect(),
        ..Default::default()
    };
    let rogue = tokio::time::timeout(Duration::from_secs(10), session::open(&args)).await.expect("open").expect("open");
    let t = Instant::now();
    let mut k = 0u64;
    while g.0.try_wait().expect("try_wait").is_none() {
        assert!(t.elapsed() < LIMIT, "run did not finish");
        // Start-barrier traffic with a foreign fingerprint, under expected and unexpected names.
        let foreign_ready =
            formation_protocol::codec::encode(&formation_protocol::barrier::Ready { fingerprint: 0xbad, keys: vec![] });
        for name in ["rogue", "1", "monitor"] {
            let key = format!("formation/rogue/control/ready/{name}");
            let _ = tokio::time::timeout(Duration::from_secs(1), rogue.put(key, foreign_ready.clone())).await;
        }
        let foreign_start = formation_protocol::codec::encode(&formation_protocol::barrier::Start {
            fingerprint: 0xbad,
            epoch_unix_ns: 1,
            time_scale: 1.0,
            sent_ns: 0,
            absent: Vec::new(),
        });
        let _ = tokio::time::timeout(Duration::from_secs(1), rogue.put("formation/rogue/control/start", foreign_start))
            .await;
        for id in 0..=4u32 {
            let key = format!("formation/rogue/estimate/{id}");
            let mut bad_version = EstimateMsg {
                header: Header { version: FORMAT_VERSION + 7, sender: id, step: k, time_s: 0.0, sent_ns: 0 },
                state: LeaderState::default(),
                fresh: true,
                term: u32::from(id == 0),
            };
            bad_version.header.version = FORMAT_VERSION + 7;
            for payload in [
                b"\x01not a message".to_vec(),
                msg(id % 4 + 1 + u32::from(id == 0), k + 1, 1.0),
                msg(id, k + 1, f64::NAN),
                wire::encode(&bad_version),
                // Correct sender, but a step no genuine node can have reached.
                msg(id, u64::MAX, 1.0),
            ] {
                let _ = tokio::time::timeout(Duration::from_secs(1), rogue.put(key.as_str(), payload)).await;
            }
            // A flood of distinct future steps (would pile up in a lock-step inbox).
            for j in 0..20 {
                let payload = msg(id, 1_000_000 + k * 20 + j, 1.0);
                let _ = tokio::time::timeout(Duration::from_secs(1), rogue.put(key.as_str(), payload)).await;
            }
        }
        k += 1;
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let status = g.wait(LIMIT);
    let _ = tokio::time::timeout(Duration::from_secs(5), rogue.close()).await;
    assert!(status.success(), "formation launch failed: {status}");
    let expected = sim(&tmp.join("sim"), &sets);
    assert_eq!(std::fs::read_to_string(net.join("summary.json")).expect("summary"), expected);
    let n = network(&net);
    let total = |what: &str| -> u64 {
        n["nodes"].as_object().expect("nodes").values().map(|v| v["rejected"][what].as_u64().unwrap_or(0)).sum()
    };
    for what in ["malformed", "wrong_sender", "non_finite", "version", "future"] {
        assert!(total(what) > 0, "no {what} rejection counted: {n}");
    }
    eprintln!(
        "rogue run: rejected malformed {}, wrong_sender {}, non_finite {}, version {}, future {}",
        total("malformed"),
        total("wrong_sender"),
        total("non_finite"),
        total("version"),
        total("future")
    );
}

/// A follower that leaves at 1 s (issue 50, `launch --leave 3@1`) in
/// lock-step: its neighbours and the leader learn it from its last
/// telemetry and stop waiting for it, and every other follower's record
/// and the leader's equal `formation sim` byte for byte with the fault
/// row `node = 3` from 1 s to the end (the model of a leave); its own
/// record ends before step 1000, and the run names the leave.
#[test]
fn lockstep_a_follower_that_leaves_equals_sim_with_its_node_cut_off() {
    let dir = tempfile::tempdir().expect("tempdir");
    let net = dir.path().join("net");
    let n = without_follower_3(&net, &["--run", "ls-leave", "--leave", "3@1"], "faults+={node=3, from=1, to=2.001}");
    // -q: the leave is news, and the agent keeps it to itself as the monitor does.
    let said = std::fs::read_to_string(net.with_file_name("launch.stderr")).expect("launch's stderr");
    assert!(!said.contains("leave"), "launch -q said:\n{said}");
    let rows3 = std::fs::read_to_string(net.join("follower_3.csv")).expect("follower_3.csv").lines().count();
    assert_eq!(rows3, 1 + 1000, "follower 3: a header and steps 0..1000");
    assert_eq!(
        (n["left"][0]["follower"].as_u64(), n["left"][0]["step"].as_u64()),
        (Some(3), Some(1000)),
        "{}",
        n["left"]
    );
    assert_eq!(n["left"][0]["why"], "--leave, as scheduled");
    assert_eq!(n["health"]["verdict"], "disturbed", "{}", n["health"]);
    // The run again from its record, and beside its model (the leave as
    // the model's node fault): the same bytes, and no departure.
    common::replays_byte_for_byte("lock-step leave", &net);
    let explained =
        common::run_ok(Command::new(env!("CARGO_BIN_EXE_formation")).args(["replay", "--explain"]).arg(&net));
    let text = String::from_utf8_lossy(&explained.stdout);
    assert!(text.contains("the run heard exactly what the model assumes: no departure"), "{text}");
}

/// Issue 50's join as the fault table's row, in lock-step: `{ node = 3,
/// from = 0, to = 1, join = true }` — follower 3's links down until 1 s,
/// then it starts as a new process does (its robot at its initial pose, a
/// fresh filter, its estimate taken from what it hears, nothing published
/// before its first step). Every record, follower 3's and the summary
/// included, equals `formation sim`'s byte for byte. (A process started
/// late in lock-step is refused, `lab --join`: see docs/model.md §14.)
#[test]
fn lockstep_a_join_row_equals_sim_byte_for_byte() {
    let dir = tempfile::tempdir().expect("tempdir");
    let net = dir.path().join("net");
    let base = Ports::free(LAUNCH_PORTS).release().to_string();
    let sets = ["duration=2", "faults+={node=3, from=0, to=1, join=true}"];
    let mut g = Group::launch(&net, &sets, &["--base-port", &base, "--run", "ls-join"]);
    let status = g.wait(LIMIT);
    assert!(status.success(), "formation launch with a join row: {status}: {}", network(&net)["health"]);
    common::assert_equals_the_simulator(&net, &dir.path().join("sim"), &sets, "a lock-step join row");
    g.assert_group_empty();
}

/// A 2 s lock-step launch of the paper with `flags` into `net`, in which
/// follower 3 takes fewer steps than the run: every other follower's
/// record and the leader's equal `formation sim` with the fault row `row`
/// byte for byte. Its network.json.
fn without_follower_3(net: &Path, flags: &[&str], row: &str) -> serde_json::Value {
    let base = Ports::free(LAUNCH_PORTS).release().to_string();
    let simd = net.with_file_name("sim");
    let mut args = vec!["--base-port", &base];
    args.extend(flags);
    let out = net.display().to_string();
    let mut launch = vec!["launch", common::SCENARIO, "-q", "--out", &out, "--set", "duration=2"];
    launch.extend(args);
    let mut g = Group::spawn_logged(&launch, &net.with_file_name("launch.stderr"));
    sim(&simd, &["duration=2", row]);
    let status = g.wait(LIMIT);
    let n = network(net);
    assert!(status.success(), "formation launch {flags:?}: {status}: {}", n["health"]);
    for f in ["follower_1.csv", "follower_2.csv", "follower_4.csv", "leader.csv"] {
        let a = std::fs::read(net.join(f)).expect("net csv");
        let b = std::fs::read(simd.join(f)).expect("sim csv");
        assert!(a == b, "{flags:?}: {f} differs from formation sim's with {row}");
    }
    n
}

/// Issue 50's quorum start: follower 3's agent never started (`--absent
/// 3`), the run starts with the three present once the quorum wait is
/// over, names follower 3 absent (network.json, the leader's and the
/// monitor's lines), and every present follower's record and the leader's
/// equal `formation sim` byte for byte with the fault row `node = 3` over
/// the whole run (the model of an absent follower); follower 3 has no row.
#[test]
fn lockstep_a_quorum_start_without_follower_3_equals_sim_with_its_node_cut_off() {
    let dir = tempfile::tempdir().expect("tempdir");
    let net = dir.path().join("net");
    let quorum = ["--run", "ls-quorum", "--quorum", "3", "--quorum-wait", "1", "--absent", "3"];
    let n = without_follower_3(&net, &quorum, "faults+={node=3, from=0}");
    let rows3 = std::fs::read_to_string(net.join("follower_3.csv")).expect("follower_3.csv").lines().count();
    assert_eq!(rows3, 1, "follower 3: a header and no row");
    assert_eq!(n["absent"], serde_json::json!([3]), "{}", n["absent"]);
    assert_eq!(n["left"][0]["why"], "absent at the start", "{}", n["left"]);
    assert_eq!(n["health"]["verdict"], "disturbed", "{}", n["health"]);
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(net.join("summary.json")).expect("summary.json")).expect("JSON");
    assert_eq!(summary["incomplete"]["3"]["left"], "absent at the start", "{}", summary["incomplete"]);
    common::replays_byte_for_byte("lock-step quorum start", &net);
}

/// A quorum start asked for badly is refused before anything starts, in
/// one line with exit 2: a quorum below 1 or above the formation, a wait
/// outside (0, 120] s, an unknown follower, more absent than the quorum
/// allows, and an absent follower that is the leader's only link (follower
/// 1 of the paper's ring: the others, cut off, are named).
#[test]
fn a_bad_quorum_is_refused_up_front_in_one_line() {
    let cases: [(&[&str], &str); 6] = [
        (&["--quorum", "0"], "--quorum 0: a quorum is 1 to 4 followers (this formation has 4)"),
        (&["--quorum", "5"], "--quorum 5: a quorum is 1 to 4 followers"),
        (
            &["--quorum", "3", "--quorum-wait", "0"],
            "--quorum-wait 0: give 0 < seconds < 119 (the start's time limit, 120 s",
        ),
        (&["--quorum", "3", "--absent", "9"], "--absent 9: no follower 9 in this scenario"),
        (&["--quorum", "4", "--absent", "3"], "--quorum 4 with followers 3 absent: only 3 can be ready"),
        (
            &["--quorum", "3", "--absent", "1"],
            "--absent 1: without follower 1, followers 2, 3, 4 no longer reach the leader (Lemma 1): not started",
        ),
    ];
    for (flags, says) in cases {
        let dir = tempfile::tempdir().expect("tempdir");
        let out = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(["launch", common::SCENARIO, "-q", "--out"])
            .arg(dir.path().join("run"))
            .args(flags)
            .output()
            .expect("formation launch");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{flags:?}: {err}");
        assert!(err.lines().count() == 1 && err.contains(says), "{flags:?}: {err}");
        assert!(!dir.path().join("run").exists(), "{flags:?}: a run folder was made");
    }
}
