//! A real-time networked run (free ports on 127.0.0.1): the run
//! ends and the formation and estimator errors stay within bounds.
//!
//! Settings and tolerances, and why: tests run unoptimised on a loaded
//! 2-core machine, where six processes cannot hold a 1 kHz loop at ×3
//! speed, and a real-time node that falls behind its schedule drifts from
//! its neighbours (which then leave it out as silent). So the scenario is
//! the paper's with Δt = 10 ms (100 Hz control, T = 30 s), run at time
//! scale 2 (a 200 Hz wall-clock loop, 15 s), and a silence timeout of 0.2 s
//! (20 steps, 100 ms of wall-clock time). On a machine so overloaded that
//! the nodes fall more than that behind, the run degrades as real time
//! should, and this test fails: its message then shows each node's
//! lateness. Bounds: docs/model.md §12's formation
//! bound as it stands (RMS over the last 10 s below 0.2 m); the estimator
//! bound relaxed from 0.01 m to 0.1 m at t = T, because at Δt = 10 ms the
//! in-process simulator itself ends at 0.04–0.06 m (forward Euler at a
//! coarser step), and real time adds a lag of a step or two (≈ 1.2 m/s ×
//! 10–20 ms). Both are also checked against the simulator: within 0.1 m.

use crate::common;

use std::process::Command;

use common::{json, Group, SCENARIO};

/// Six processes at 200 Hz use 0.15–0.2 cores, but the run has no slack
/// for lateness: each takes a lab's share ([`common::Load::Lab`]), so that
/// at most one other such run goes beside it.

/// No modelled delay: §12's bounds were set so (with a step of delay at
/// Δt = 10 ms the model's own estimator error at T is 0.16–0.24 m). Its
/// late source-steps then count the step-k/k−1 mix too, and the bounds are
/// judged only in a run with few (common::judge_if_timely).
const SETS: [&str; 4] = ["timing=realtime", "dt=0.01", "duration=30", "network.silence_timeout=0.2"];

#[test]
fn realtime_run_ends_within_spec_bounds() {
    let _cores = common::cores(common::Load::Lab);
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("net");
    let base = common::Ports::free(common::LAUNCH_PORTS).release().to_string();
    let mut g = Group::launch(&out, &SETS, &["--time-scale", "2", "--base-port", &base, "--run", "rt", "--mcap"]);

    let mut sim = Command::new(env!("CARGO_BIN_EXE_formation"));
    sim.args(["sim", SCENARIO, "-q", "--out"]).arg(tmp.path().join("sim"));
    for s in SETS {
        sim.args(["--set", s]);
    }
    assert!(sim.status().expect("formation sim").success());
    let reference = json(&tmp.path().join("sim"), "summary.json");

    let status = g.wait(common::LIMIT);
    assert!(status.success(), "formation launch failed: {status}");
    let got = json(&out, "summary.json");
    let network = json(&out, "network.json");
    let lateness: Vec<String> = network["nodes"]
        .as_object()
        .expect("nodes")
        .iter()
        .map(|(n, v)| format!("{n}: p99 {:.0} µs, silent {}", v["loop"]["lateness_p99_us"], v["silent"]))
        .collect();
    let context = format!("(node lateness behind schedule: {})", lateness.join("; "));
    // Always: every step recorded, and the record replays byte for byte.
    let mut bounds = Vec::new();
    for id in ["1", "2", "3", "4"] {
        let f = &got["followers"][id];
        let r = &reference["followers"][id];
        assert_eq!(f["samples"], 3001, "follower {id}: every step recorded");
        let form = f["formation_rms_last10"].as_f64().expect("number");
        let est = f["estimator_error_final"].as_f64().expect("number");
        let form_ref = r["formation_rms_last10"].as_f64().expect("number");
        let est_ref = r["estimator_error_final"].as_f64().expect("number");
        // The bounds: judged when the run kept its period.
        if form >= 0.2 {
            bounds.push(format!("follower {id}: formation RMS over the last 10 s {form} m ≥ 0.2 m"));
        }
        if est >= 0.1 {
            bounds.push(format!("follower {id}: estimator error at T {est} m ≥ 0.1 m"));
        }
        if (form - form_ref).abs() >= 0.1 {
            bounds.push(format!("follower {id}: formation RMS {form} vs simulator {form_ref}"));
        }
        if (est - est_ref).abs() >= 0.1 {
            bounds.push(format!("follower {id}: estimator error {est} vs simulator {est_ref}"));
        }
    }
    common::replays_byte_for_byte("real time at 200 Hz", &out);
    links_and_clocks_are_measured(&out, &network, &mut bounds);
    common::judge_if_timely("real time at 200 Hz, docs/model.md §12's bounds", &bounds, &[&network], &context);
}

/// Issue 23's figures, in network.json and run.mcap: per follower its
/// estimate of the leader's clock (one host: one wall clock, so an offset
/// within 1 ms of 0), and per source the one-way latency and the age at
/// use of its messages.
/// What depends on the host's speed (the clock's offset, the latencies and
/// ages) goes into `timing`, judged when the run kept its period; the rest
/// is asserted.
fn links_and_clocks_are_measured(out: &std::path::Path, network: &serde_json::Value, timing: &mut Vec<String>) {
    // Sources per follower in scenarios/paper.toml (neighbours, and the leader for 1).
    let sources = [("1", vec![0, 2, 3]), ("2", vec![1, 4]), ("3", vec![1, 4]), ("4", vec![2, 3])];
    // One host, one wall clock: every follower's offset 0, less what the
    // host's own wall clock stepped during the run (every node's alike;
    // this VM's moved 50–150 ms in some runs).
    let offsets: Vec<f64> =
        sources.iter().filter_map(|(id, _)| network["nodes"][id]["clock"]["offset_ms"].as_f64()).collect();
    let host_step = offsets.iter().sum::<f64>() / offsets.len().max(1) as f64;
    assert!(offsets.len() == 4 && host_step.abs() < 500.0, "the followers' clock offsets: {offsets:?} ms");
    for (id, want) in &sources {
        let n = &network["nodes"][id];
        let (offset, uncertainty) = (n["clock"]["offset_ms"].as_f64(), n["clock"]["uncertainty_us"].as_f64());
        assert!(offset.is_some() && uncertainty.is_some_and(|u| u > 0.0), "follower {id}: clock {}", n["clock"]);
        if !offset.is_some_and(|o| (o - host_step).abs() < 1.0) || !uncertainty.is_some_and(|u| u < 5_000.0) {
            timing.push(format!(
                "follower {id}: clock {} (one host: within 1 ms of the others' {host_step:.3} ms, known to 5 ms)",
                n["clock"]
            ));
        }
        let links = n["links"].as_array().expect("links");
        let mut got: Vec<u64> = links.iter().map(|l| l["source"].as_u64().expect("source")).collect();
        got.sort_unstable();
        assert_eq!(&got, want, "follower {id}: one entry per source");
        for l in links {
            let lat = |i: usize| l["latency_us"][i].as_u64().expect("latency");
            assert!(l["messages"].as_u64() > Some(0) && l["uses"].as_u64() > Some(0), "follower {id}: {l}");
            assert!(lat(0) <= lat(1) && lat(1) <= lat(2), "follower {id}: {l}");
            if !(l["messages"].as_u64() > Some(2_500) && l["uses"].as_u64() > Some(2_500)) {
                timing.push(format!("follower {id}: fewer than 2,500 messages or uses of 3,001: {l}"));
            }
            if lat(0) >= 50_000 || l["age_steps"][0].as_u64() > Some(2) {
                timing.push(format!("follower {id}: a median latency of {} µs or age over 2 steps: {l}", lat(0)));
            }
        }
    }
    let bytes = std::fs::read(out.join("run.mcap")).expect("run.mcap");
    let mut topics = std::collections::BTreeMap::<String, usize>::new();
    for m in mcap::MessageStream::new(&bytes).expect("mcap") {
        *topics.entry(m.expect("message").channel.topic.clone()).or_default() += 1;
    }
    assert_eq!(topics.get("/network/links"), Some(&9), "one message per link: {topics:?}");
    assert_eq!(topics.get("/network/clocks"), Some(&4), "one message per follower: {topics:?}");
}

/// docs/model.md §14's communication delay: with `network.delay_steps = d` a step
/// uses only messages that had d periods to arrive, so the real-time run
/// is the one `formation sim` predicts with the same delay (with d = 0,
/// each step mixes step-k and step-(k−1) messages as they happen to
/// arrive, which nothing models: 26 % more torque variation measured). Here
/// d = 2 at time scale 2 (10 ms of wall-clock slack), because the test
/// build on a loaded 2-core machine is often a period late; on a quiet
/// machine d = 1 does as well (see issue 12's note).
///
/// The comparison with the model is judged only when the run kept its
/// period ([`common::judge_if_timely`]): a clean-clone CI run on a busy host
/// measured a loop lateness p99 of 123 ms, every node silent for the others
/// at the same two instants, and torque variation 4-7 times the model's;
/// what the network code did there cannot be told from what the host did.
/// That the run completes with every step recorded is judged always.
#[test]
fn a_realtime_run_with_a_communication_delay_is_the_one_the_simulator_predicts() {
    let _cores = common::cores(common::Load::Lab);
    let sets = ["timing=realtime", "dt=0.01", "duration=20", "network.silence_timeout=0.2", "network.delay_steps=2"];
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("net");
    let base = common::Ports::free(common::LAUNCH_PORTS).release().to_string();
    let mut g = Group::launch(&out, &sets, &["--time-scale", "2", "--base-port", &base, "--run", "rt-delay"]);
    let mut sim = Command::new(env!("CARGO_BIN_EXE_formation"));
    sim.args(["sim", SCENARIO, "-q", "--out"]).arg(tmp.path().join("sim"));
    for s in sets {
        sim.args(["--set", s]);
    }
    assert!(sim.status().expect("formation sim").success());
    let status = g.wait(common::LIMIT);
    assert!(status.success(), "formation launch failed: {status}");
    let (got, reference, network) =
        (json(&out, "summary.json"), json(&tmp.path().join("sim"), "summary.json"), json(&out, "network.json"));
    for id in ["1", "2", "3", "4"] {
        assert_eq!(got["followers"][id]["samples"], 2001, "follower {id}: every step recorded");
    }
    common::replays_byte_for_byte("real time with a delay of 2 steps", &out);
    let bad = common::unlike_the_simulator(&got, &reference, &network, 0.10, &common::COMPARED);
    common::judge_fault_free_if_timely(
        "real time with a delay of 2 steps, against the simulator (10 %)",
        &bad,
        &network,
    );
}

/// A robot that is not running is still there, in real time (docs/model.md
/// §14, §16): on `scenarios/turtlebot.toml` (filter on, `network.gone_after
/// = 1`) at time scale 3, follower 4 absent at a quorum start, follower 3
/// leaving at 10 s, and follower 2's agent killed with SIGKILL at 10 s.
/// Always (what the filter promises whatever the timing): the run
/// completes with every step of the others recorded, and no two robots
/// came closer than `safety.distance`, the one not running included (the
/// monitor's closest pair counts its last pose). Judged on a quiet machine:
/// each other follower's formation error over the last 10 s within 0.15 m
/// of the fault-free model's (the bound of the lock-step test,
/// tests/it/safety.rs).
#[test]
fn a_robot_absent_leaving_or_killed_in_real_time_is_kept_clear_of_and_the_others_reach_their_slots() {
    let _cores = common::cores(common::Load::Light);
    let scenario = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/turtlebot.toml");
    let tmp = tempfile::tempdir().expect("tempdir");
    let free = tmp.path().join("free");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", scenario, "-q", "--out"])
        .arg(&free)
        .output()
        .expect("formation sim");
    assert!(o.status.success(), "formation sim turtlebot: {}", String::from_utf8_lossy(&o.stderr));
    let free = json(&free, "summary.json");
    let cases: [(&str, &[&str], u32, bool); 3] = [
        ("follower 4 absent", &["--quorum", "3", "--quorum-wait", "2", "--absent", "4"], 4, false),
        ("follower 3 leaving at 10 s", &["--leave", "3@10"], 3, false),
        ("follower 2 killed at 10 s", &[], 2, true),
    ];
    for (what, flags, out_id, kill) in cases {
        let out = tmp.path().join(out_id.to_string());
        let base = common::Ports::free(common::LAUNCH_PORTS).release().to_string();
        let (out_s, log) = (out.display().to_string(), tmp.path().join(format!("launch-{out_id}.log")));
        let mut args = vec!["launch", scenario, "--out", &out_s, "--set", "timing=\"realtime\"", "--time-scale", "3"];
        args.extend(["--base-port", &base, "--run", "rt-members"]);
        args.extend(flags);
        let mut g = Group::spawn_logged(&args, &log);
        let said = || std::fs::read_to_string(&log).unwrap_or_default();
        if kill {
            common::wait_started(&log);
            // 10 s of run time at time scale 3, after the 0.5 s start lead.
            std::thread::sleep(std::time::Duration::from_secs_f64(0.5 + 10.0 / 3.0));
            let pid = g.agent_pid(2).unwrap_or_else(|| panic!("{what}: agent 2 not found: {}", said()));
            let _ = Command::new("kill").args(["-KILL", &pid.to_string()]).status();
        }
        let status = g.wait(common::LIMIT);
        // A run worse than its model exits 3 (degraded): that is judged below.
        assert!(status.success() || status.code() == Some(3), "{what}: {status}\n{}", said());
        g.assert_group_empty();
        let (summary, network) = (json(&out, "summary.json"), json(&out, "network.json"));
        assert_eq!(network["complete"], true, "{what}: ending {}", network["ending"]);
        let safety = &summary["safety"];
        let (closest, distance) = (safety["closest"]["distance"].as_f64(), safety["distance"].as_f64());
        let (Some(closest), Some(distance)) = (closest, distance) else { panic!("{what}: no safety figures") };
        eprintln!(
            "{what}: closest {closest:.4} m ({}), {}",
            safety["closest"]["pair"],
            said().lines().filter(|l| l.contains("members:")).collect::<String>()
        );
        assert!(
            closest >= distance,
            "{what}: robots {} came {closest:.4} m apart ({distance} m)",
            safety["closest"]["pair"]
        );
        let mut wrong = Vec::new();
        for id in (1..=4u32).filter(|&i| i != out_id) {
            let f = &summary["followers"][id.to_string()];
            assert_eq!(f["samples"], 3001, "{what}: follower {id}'s steps recorded");
            let rms = f["formation_rms_last10"].as_f64().unwrap_or(f64::INFINITY);
            let model = free["followers"][id.to_string()]["formation_rms_last10"].as_f64().unwrap_or(0.0);
            eprintln!(
                "{what}: follower {id}: formation error over the last 10 s {rms:.3} m (fault-free model {model:.3} m)"
            );
            if rms > model + 0.15 {
                wrong.push(format!("{what}: follower {id} {rms:.3} m from its slot (fault-free model {model:.3} m)"));
            }
        }
        common::judge_if_timely(what, &wrong, &[&network], "");
    }
}
