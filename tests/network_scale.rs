//! 100 agents as processes on one host (issue 12): a generated ring of 100
//! followers through `formation launch`, lock-step, equals the simulator
//! byte for byte: one process per agent in client mode (router port 17646),
//! and 50 agents per process in peer mode (ports 18420–18423), 127.0.0.1 only.

mod common;

use std::process::Command;

use common::Group;

const AGENTS: usize = 100;

#[test]
fn a_hundred_agents_in_lockstep_through_launch_equal_the_simulator() {
    hundred_agents_in_lockstep(&["--mode", "client", "--base-port", "17646", "--run", "scale100"], 0.1);
}

/// `launch --group 50`: two agent processes of 50 followers each, their
/// in-process messages never on a socket; still the simulator's bytes.
#[test]
fn a_hundred_agents_in_two_processes_in_lockstep_equal_the_simulator() {
    hundred_agents_in_lockstep(&["--group", "50", "--base-port", "18420", "--run", "scale100g"], 0.5);
}

fn hundred_agents_in_lockstep(launch_args: &[&str], duration: f64) {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = dir.path().join("ring100.toml");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["generate", "--followers", &AGENTS.to_string(), "--graph", "ring", "--chords", "10", "--out"])
        .arg(&scenario)
        .output()
        .expect("formation generate");
    assert!(o.status.success(), "formation generate: {}", String::from_utf8_lossy(&o.stderr));
    let scenario = scenario.display().to_string();
    let duration = format!("duration={duration}");
    let sets = [duration.as_str()];

    let net = dir.path().join("net");
    let net_s = net.display().to_string();
    let mut args = vec!["launch", &scenario, "-q", "--out", &net_s];
    args.extend(launch_args);
    for s in sets {
        args.extend(["--set", s]);
    }
    let mut g = Group::spawn(&args);
    let status = g.wait(std::time::Duration::from_secs(240));
    assert!(status.success(), "formation launch with {AGENTS} agents failed: {status}");
    g.assert_group_empty();

    let sim = dir.path().join("sim");
    let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
    c.args(["sim", &scenario, "-q", "--out"]).arg(&sim);
    for s in sets {
        c.args(["--set", s]);
    }
    let o = c.output().expect("formation sim");
    assert!(o.status.success(), "formation sim: {}", String::from_utf8_lossy(&o.stderr));

    let network = common::json(&net, "network.json");
    assert_eq!(network["complete"], true, "record not complete: {}", network["ending"]);
    let startup = network["wall"]["startup_s"].as_f64().expect("wall.startup_s");
    assert!(startup < 60.0, "{AGENTS} agents took {startup:.1} s to start");
    let mut differ = Vec::new();
    for id in 1..=AGENTS {
        let f = format!("follower_{id}.csv");
        let (a, b) = (std::fs::read(net.join(&f)), std::fs::read(sim.join(&f)));
        if a.as_ref().ok() != b.as_ref().ok() || a.is_err() {
            differ.push(id);
        }
    }
    assert!(differ.is_empty(), "followers {differ:?} differ from the simulator (of {AGENTS})");
    let (a, b) = (std::fs::read(net.join("summary.json")), std::fs::read(sim.join("summary.json")));
    assert!(a.is_ok() && a.ok() == b.ok(), "summary.json differs from the simulator's");
    eprintln!("{AGENTS} agents ({launch_args:?}): every node ready {startup:.1} s after the monitor's start");
}

/// Issue 12's real-time goal: 50 agents at 100 Hz behave like the
/// simulator with the same one-step communication delay — formation
/// metrics and torque variation within 10 %, no source silent after the
/// first second. Judged against the simulator on a quiet machine only (52
/// processes at 100 Hz on two cores; see [`common::judge_if_quiet`]): on
/// this project's VM it passes when the host steals no CPU and failed when
/// it stole 6–30 %; the message says what the machine did.
#[test]
fn fifty_agents_in_real_time_at_100_hz_behave_like_the_simulator() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = dir.path().join("ring50.toml");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["generate", "--followers", "50", "--graph", "ring", "--chords", "10", "--seed", "1", "--out"])
        .arg(&scenario)
        .output()
        .expect("formation generate");
    assert!(o.status.success(), "formation generate: {}", String::from_utf8_lossy(&o.stderr));
    let scenario = scenario.display().to_string();
    let sets = ["timing=realtime", "dt=0.01", "duration=10", "network.delay_steps=1"];
    let net = dir.path().join("net");
    let net_s = net.display().to_string();
    let mut args = vec!["launch", &scenario, "-q", "--out", &net_s, "--base-port", "18200", "--run", "rt50"];
    for s in sets {
        args.extend(["--set", s]);
    }
    let before = common::Host::now();
    let mut g = Group::spawn(&args);
    let status = g.wait(std::time::Duration::from_secs(120));
    let host = common::Host::now().since(&before);
    assert!(status.success(), "formation launch with 50 agents failed: {status}");
    g.assert_group_empty();
    let sim = dir.path().join("sim");
    let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
    c.args(["sim", &scenario, "-q", "--out"]).arg(&sim);
    for s in sets {
        c.args(["--set", s]);
    }
    common::run_ok(&mut c);
    let (got, want, network) =
        (common::json(&net, "summary.json"), common::json(&sim, "summary.json"), common::json(&net, "network.json"));
    let bad = common::unlike_the_simulator(&got, &want, &network, 0.10);
    common::judge_if_quiet("50 agents in real time, against the simulator (10 %)", &bad, host, "at 100 Hz");
}
