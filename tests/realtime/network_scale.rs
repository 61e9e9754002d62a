//! 100 agents as processes on one host (issue 12): a generated ring of 100
//! followers through `formation launch`, lock-step, equals the simulator
//! byte for byte: one process per agent in client mode (one router port),
//! and 50 agents per process in peer mode (four ports), on free ports of
//! 127.0.0.1 (`common::Ports`).

use crate::common;

use std::process::Command;

use common::Group;

const AGENTS: usize = 100;

/// How far the formation's median torque variation may sit from the
/// simulator's in the 50-agent real-time run (see the test; issue 25's 3 %).
const TORQUE_TV_MEDIAN: f64 = 0.03;

#[test]
fn a_hundred_agents_in_lockstep_through_launch_equal_the_simulator() {
    // Alone in the `realtime` binary (see its main.rs), before the ports are chosen.
    let _alone = common::alone();
    let base = common::Ports::free(1).release().to_string();
    hundred_agents_in_lockstep(&["--mode", "client", "--base-port", &base, "--run", "scale100"], 0.1);
}

/// `launch --group 50`: two agent processes of 50 followers each, their
/// in-process messages never on a socket; still the simulator's bytes.
#[test]
fn a_hundred_agents_in_two_processes_in_lockstep_equal_the_simulator() {
    // Alone in the `realtime` binary (see its main.rs), before the ports are chosen.
    let _alone = common::alone();
    // Ports: the monitor, the leader, two agent processes.
    let base = common::Ports::free(4).release().to_string();
    hundred_agents_in_lockstep(&["--group", "50", "--base-port", &base, "--run", "scale100g"], 0.5);
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
/// simulator with the same one-step communication delay — each follower's
/// formation and estimator metrics within 10 %, no source silent after the
/// first second — judged against the simulator on a quiet machine only (52
/// processes at 100 Hz on two cores; see [`common::judge_if_quiet`]).
///
/// Torque variation is judged for the formation, not per follower: this
/// ring is far from converged after 10 s and its torques chatter, so one
/// follower's torque variation measures how sensitive the chatter is to
/// the timing of single messages. On 2026-11-24 it sat about 10 % below the
/// simulator's (median 0.90, follower 11 2.21 against 2.49): the run used
/// many messages a step older than the model assumes, and a lagging
/// estimate makes this ring's torques smoother (`formation sim` with the
/// whole ring at network.delay_steps = 2: median −20 %; see
/// docs/why-did-my-run-differ.md). Since the run's timebase and the
/// router-only rate limits, the run hears what the model assumes: on
/// 2026-11-25 every message one step old, summary.json the simulator's byte
/// for byte (median ratio 1.000); with two CPU-bound processes beside it,
/// one link-step of 121,121 late (+0.03 %); but in more runs 2, 50, 2 and
/// 2 late link-steps (scheduling stalls of 10–27 ms: 52 processes on 2
/// cores) moved the median to 0.996, 0.927, 0.992 and 0.987, so sensitive
/// is this ring. Under real-time scheduling (`launch --rt-priority 10`):
/// 0, 0 and 4 late, medians 1.000, 1.000 and 1.005. As root (CI) the
/// median must be within 3 % with it; otherwise within 25 %. A failure
/// prints `formation replay --explain`'s ranking of the links.
#[test]
fn fifty_agents_in_real_time_at_100_hz_behave_like_the_simulator() {
    // Alone in the `realtime` binary (see its main.rs), before the ports are chosen.
    let _alone = common::alone();
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
    // Ports: the monitor, the leader, 50 agents.
    // Below the ephemeral ports, which the peers' outgoing links take.
    let base = common::Ports::below_ephemeral(52).release().to_string();
    let mut args = vec!["launch", &scenario, "-q", "--out", &net_s, "--base-port", &base, "--run", "rt50"];
    // As root (CI): every node under real-time scheduling, as a real-time
    // deployment runs; the 3 % below is judged with it.
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    if root {
        args.extend(["--rt-priority", "10"]);
    }
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
    let mut bad = common::unlike_the_simulator(&got, &want, &network, 0.10, &common::COMPARED_CONVERGING);
    let ratio = |id: &str| {
        let (g, s) = (got["followers"][id]["torque_tv"].as_f64(), want["followers"][id]["torque_tv"].as_f64());
        g.zip(s).map_or(f64::NAN, |(g, s)| g / s)
    };
    let mut ratios: Vec<f64> = want["followers"].as_object().expect("followers").keys().map(|id| ratio(id)).collect();
    ratios.sort_by(f64::total_cmp);
    let median = ratios.get(ratios.len() / 2).copied().unwrap_or(f64::NAN);
    // Without real-time scheduling a few messages a run come a step late on
    // a busy 2-core machine (see above): 25 %, as before.
    let allowed = if root { TORQUE_TV_MEDIAN } else { 0.25 };
    if !((median - 1.0).abs() <= allowed) {
        bad.push(format!(
            "the formation's median torque variation is {median:.3} of the simulator's (allowed 1 ± {allowed}; \
             followers {:.3}–{:.3})",
            ratios.first().unwrap_or(&f64::NAN),
            ratios.last().unwrap_or(&f64::NAN)
        ));
    }
    let explained = if bad.is_empty() {
        String::new()
    } else {
        let o = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(["replay", "--explain", "--top", "5"])
            .arg(&net)
            .output()
            .expect("formation replay --explain");
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    common::judge_if_quiet(
        "50 agents in real time, against the simulator",
        &bad,
        host,
        &format!("at 100 Hz\n{explained}"),
    );
    eprintln!("50 agents in real time: median torque variation ratio {median:.3} (real time over the simulator)");
}
