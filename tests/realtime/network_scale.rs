//! Many agents as processes on one host. Issue 12: a generated ring of 100
//! followers through `formation launch`, lock-step, equals the simulator
//! byte for byte: one process per agent in client mode (one router port),
//! and 50 agents per process in peer mode (four ports), on free ports of
//! 127.0.0.1 (`common::Ports`); 50 agents in real time behave like the
//! simulator. Issue 33: 100 agents in real time, one process each.

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
    let _cores = common::cores(common::Load::Whole);
    let base = common::Ports::free(1).release().to_string();
    hundred_agents_in_lockstep(&["--mode", "client", "--base-port", &base, "--run", "scale100"], 0.1);
}

/// `launch --group 50`: two agent processes of 50 followers each, their
/// in-process messages never on a socket; still the simulator's bytes.
#[test]
fn a_hundred_agents_in_two_processes_in_lockstep_equal_the_simulator() {
    // Alone in the `realtime` binary (see its main.rs), before the ports are chosen.
    let _cores = common::cores(common::Load::Whole);
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
/// simulator with the same one-step communication delay.
///
/// Asserted whatever the machine does (issue 47): every step of every
/// follower recorded, the record complete and not degraded, the run
/// replayed byte for byte from its hearing record, and its health naming
/// what `replay --explain` finds: a stall of every node at once as one
/// event (both count the same stalls), more than 0.1 % of link-steps heard
/// otherwise than the model said.
///
/// The model's figures (each follower's formation and estimator metrics
/// within 10 %, the formation's median torque variation within 3 % as root
/// under `--rt-priority 10`, within 25 % otherwise) are judged when the host
/// kept the period: no stall, no source-step that heard nothing, at most
/// [`KEPT_THE_PERIOD`] link-steps that used an older message than the model.
/// Otherwise the test says by how much the host fell behind.
///
/// Why not judge every run: 52 processes at 100 Hz load two cores, and under
/// `--rt-priority` the kernel stops every real-time process on a CPU for the
/// rest of a second once they used 95 % of it (RT throttling). On a clean
/// CI machine that stalled every node for 60 ms at t = 6.47 s with the host
/// otherwise idle: 419 link-steps heard late or nothing, and this ring's
/// torques moved by up to +112 % (issue 47). The host decides that, not the
/// network code; the record and its replay say exactly what happened.
///
/// The estimator gain is k_i = 0.5: at the scenario's k_i = 1 this ring at
/// Δt = 10 ms with one step of delay is unstable in the model itself (an
/// oscillation growing ×1.30 a second; `formation sim` warns), so a single
/// late message grows without bound instead of fading, and the torque
/// variation measured how the chatter amplified it (2, 50, 2 and 2 late
/// link-steps moved the median to 0.996, 0.927, 0.992 and 0.987 on
/// 2026-11-24). At 0.5 the model is stable.
#[test]
fn fifty_agents_in_real_time_at_100_hz_behave_like_the_simulator() {
    // Alone in the `realtime` binary (see its main.rs), before the ports are chosen.
    let _cores = common::cores(common::Load::Whole);
    let run = RingInRealTime::run(50, &["estimator.k=[0.5,0.5,0.5]"], "rt50");
    // Without real-time scheduling a few messages a run come a step late on
    // a busy 2-core machine (see above): 25 %, as before.
    let allowed = if run.fifo { TORQUE_TV_MEDIAN } else { 0.25 };
    run.judge(0.10, allowed);
}

/// How many link-steps of a 100-agent real-time run may differ from the
/// model (a message older than `network.delay_steps`) for the run to be
/// judged against the model's figures (see the test).
const KEPT_THE_PERIOD: u64 = 50;

/// Issue 33's 100 agents, one process each, linked as peers along the
/// topology over unix sockets (as `launch` does by default), real time at 100 Hz with a one-step delay,
/// no source silent: every step of every follower recorded, the record
/// complete, the run replayed byte for byte from its hearing record, and
/// its health saying whether more than 0.1 % of link-steps heard otherwise
/// than the model, as `replay --explain` counts them — unconditionally;
/// and, when the host kept the period, within 3 % of the model
/// (`formation sim` with the same delay).
///
/// The estimator gain is k_i = 0.2: on this ring at Δt = 10 ms and one step
/// of delay, the scenario's k_i = 1 makes the model itself unstable (an
/// oscillation growing ×1.46 a second; `formation sim` warns), and a run of
/// an unstable model amplifies every late message without bound. At 0.2
/// the linearised estimator's spectral radius is 0.9998 a step (×0.98 a
/// second; 0.3 gives ×1.03, 0.5 ×1.14), so a late message disturbs the
/// model once and fades.
///
/// "Kept the period": 101 processes at 100 Hz fill this project's 2-core VM
/// (90–95 % busy, zenoh's own floor for this traffic alone 1.6 cores; see
/// docs/performance.md), and how many messages come a step late depends on
/// the VM's speed of the hour. Measured 2026-11-26 (test build, as root
/// with `--rt-priority 10`, k_i = 0.3): 22, 289, 780, 1,386, 1,830 and
/// 3,088 late link-steps of 241,241 in six runs, the median torque
/// variation 1.000, 1.039, 1.069, 1.128, 1.221 and 1.233 of the model's;
/// an hour later with k_i = 0.2, 4,416–8,824 late and 1.43–1.75. The
/// model's figures are judged when at most [`KEPT_THE_PERIOD`] link-steps
/// differ and none went silent (the first run); otherwise the test says by
/// how much the host fell behind, and judges the rest. Over unix links
/// (launch's default since, interleaved with TCP: a median of 461 late
/// link-steps against 3,750 in 12 pairs of runs without real-time
/// scheduling), three runs of this test: 176 (median 1.011), 2,724 and
/// 3,027 late.
#[test]
fn a_hundred_agents_in_real_time_at_100_hz_record_everything_and_follow_the_model() {
    // Alone in the `realtime` binary (see its main.rs), before the ports are chosen.
    let _cores = common::cores(common::Load::Whole);
    let run = RingInRealTime::run(100, &["estimator.k=[0.2,0.2,0.2]"], "rt100");
    run.judge(0.03, TORQUE_TV_MEDIAN);
}

/// A generated ring of `followers` (chords: a fifth of them, seed 1) run
/// by `formation launch` in real time at 100 Hz for 10 s with a one-step
/// delay (plus `extra` settings), one process per agent, and by `formation
/// sim` with the same settings.
struct RingInRealTime {
    _dir: tempfile::TempDir,
    net: std::path::PathBuf,
    got: serde_json::Value,
    want: serde_json::Value,
    network: serde_json::Value,
    /// As root (CI) with two cores or more: every node under real-time
    /// scheduling (`--rt-priority 10`), as a real-time deployment runs.
    fifo: bool,
}

impl RingInRealTime {
    fn run(followers: usize, extra: &[&str], tag: &str) -> Self {
        let dir = tempfile::tempdir().expect("tempdir");
        let scenario = dir.path().join(format!("ring{followers}.toml"));
        let chords = (followers / 5).to_string();
        let o = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(["generate", "--followers", &followers.to_string(), "--graph", "ring", "--chords", &chords])
            .args(["--seed", "1", "--out"])
            .arg(&scenario)
            .output()
            .expect("formation generate");
        assert!(o.status.success(), "formation generate: {}", String::from_utf8_lossy(&o.stderr));
        let scenario = scenario.display().to_string();
        let mut sets = vec!["timing=realtime", "dt=0.01", "duration=10", "network.delay_steps=1"];
        sets.extend(extra);
        let net = dir.path().join("net");
        let net_s = net.display().to_string();
        // Ports: the monitor, the leader, one per agent.
        let base = common::Ports::free(followers + 2).release().to_string();
        let mut args = vec!["launch", &scenario, "-q", "--out", &net_s, "--base-port", &base, "--run", tag];
        // Not on one CPU (`taskset -c 0`; std reads the affinity mask): 50
        // or 100 SCHED_FIFO processes at 100 Hz on one core leave the rest of
        // the machine, this test's harness and the kernel's own threads
        // included, the 5 % of RT throttling. The one-core acceptance run
        // (`taskset -c 0 bash .ci/run`) sat 23 minutes at a load of 150 in
        // this test, its processes deaf to SIGKILL until each thread was put
        // back to SCHED_OTHER (2026-12-02).
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        // SAFETY: geteuid has no preconditions.
        let fifo = unsafe { libc::geteuid() } == 0 && cpus >= 2;
        if fifo {
            args.extend(["--rt-priority", "10"]);
        }
        for s in &sets {
            args.extend(["--set", s]);
        }
        let mut g = Group::spawn(&args);
        let status = g.wait(std::time::Duration::from_secs(600));
        assert!(status.success(), "formation launch with {followers} agents failed: {status}");
        g.assert_group_empty();
        let sim = dir.path().join("sim");
        let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
        c.args(["sim", &scenario, "-q", "--out"]).arg(&sim);
        for s in &sets {
            c.args(["--set", s]);
        }
        common::run_ok(&mut c);
        let (got, want, network) = (
            common::json(&net, "summary.json"),
            common::json(&sim, "summary.json"),
            common::json(&net, "network.json"),
        );
        RingInRealTime { _dir: dir, net, got, want, network, fifo }
    }

    /// Asserts what holds whatever the timing, and, when the host kept the
    /// period, the model's figures: each follower's converging metrics
    /// within `rel`, the median torque variation within `tv_allowed`;
    /// otherwise says by how much the host fell behind.
    fn judge(&self, rel: f64, tv_allowed: f64) {
        let agents = self.want["followers"].as_object().map_or(0, |f| f.len());
        self.assert_complete_and_replayed();
        let explained = self.explain();
        let hearing = Hearing::parse(&explained);
        self.assert_health_says(&hearing, &explained);
        let mut bad =
            common::unlike_the_simulator(&self.got, &self.want, &self.network, rel, &common::COMPARED_CONVERGING);
        let tv = self.torque_variation();
        if !((tv.median - 1.0).abs() <= tv_allowed) {
            bad.push(tv.complaint(tv_allowed));
        }
        let verdict = self.verdict(&hearing, tv.median);
        let why_not = (!self.kept_the_period(&hearing)).then(|| format!("the host fell behind: {verdict}"));
        common::judge_unless(
            &format!("{agents} agents in real time"),
            &bad,
            why_not,
            &format!("the host keeping the period ({verdict})\n{explained}"),
        );
        eprintln!("{agents} agents in real time: {verdict}; the record complete and replayed byte for byte");
    }

    /// What holds whatever the timing: the record complete, every step of
    /// every follower a row, not degraded, and replayed byte for byte.
    fn assert_complete_and_replayed(&self) {
        let (n, agents) = (&self.network, self.want["followers"].as_object().map_or(0, |f| f.len()));
        let tag = format!("{agents} agents");
        assert_eq!(n["complete"], true, "{tag}: record not complete: ending {}, lost {}", n["ending"], n["lost_steps"]);
        let steps = n["steps"].as_u64().expect("steps") + 1;
        for id in 1..=agents {
            let csv = std::fs::read_to_string(self.net.join(format!("follower_{id}.csv"))).expect("follower csv");
            let rows = csv.lines().count().saturating_sub(1) as u64;
            assert_eq!(rows, steps, "{tag}: follower {id} recorded {rows} steps of {steps}");
        }
        assert_ne!(n["health"]["verdict"], "degraded", "{tag}: {}", n["health"]);
        common::replays_byte_for_byte(&tag, &self.net);
    }

    /// The run's health says what `replay --explain` counts: the same
    /// stalls, and the link-steps that heard otherwise past 0.1 %.
    fn assert_health_says(&self, hearing: &Hearing, explained: &str) {
        let h = &self.network["health"];
        let said = h["disturbed"].to_string();
        let over = hearing.differ * 1000 > hearing.link_steps;
        assert_eq!(
            said.contains(&format!("{} of {} link-steps", hearing.differ, hearing.link_steps)),
            over,
            "{} of {} link-steps differ from the model (replay --explain), and the health says: {said}",
            hearing.differ,
            hearing.link_steps
        );
        let stalls = h["stalls"].as_array().map_or(0, Vec::len);
        let explained_stalls = explained.lines().filter(|l| l.starts_with("stall:")).count();
        assert_eq!(
            stalls, explained_stalls,
            "the health names {stalls} stalls, replay --explain {explained_stalls}:\n{said}\n{explained}"
        );
        assert_eq!(
            said.matches("a stall of the path every message shares").count(),
            stalls,
            "network.json's health.stalls holds {stalls}, its lines say: {said}"
        );
    }

    /// Whether the run heard what the model assumes closely enough for its
    /// figures to be judged: no stall, nothing silent, few older messages.
    fn kept_the_period(&self, hearing: &Hearing) -> bool {
        let stalls = self.network["health"]["stalls"].as_array().map_or(0, Vec::len);
        stalls == 0 && hearing.silent == 0 && hearing.differ <= KEPT_THE_PERIOD
    }

    /// The run's hearing in one line, for the verdict.
    fn verdict(&self, hearing: &Hearing, median: f64) -> String {
        let stalls = self.network["health"]["stalls"].as_array().map_or(0, Vec::len);
        format!(
            "{} of {} link-steps differ from the model ({} heard nothing), {stalls} stall(s) of every node at once; \
             median torque variation {median:.3} of the model's",
            hearing.differ, hearing.link_steps, hearing.silent
        )
    }

    /// The followers' torque variation, the run's over the model's.
    fn torque_variation(&self) -> Ratios {
        let ratio = |id: &str| {
            let (g, s) =
                (self.got["followers"][id]["torque_tv"].as_f64(), self.want["followers"][id]["torque_tv"].as_f64());
            g.zip(s).map_or(f64::NAN, |(g, s)| g / s)
        };
        let mut r: Vec<f64> =
            self.want["followers"].as_object().expect("followers").keys().map(|id| ratio(id)).collect();
        r.sort_by(f64::total_cmp);
        let at = |i: usize| r.get(i).copied().unwrap_or(f64::NAN);
        Ratios { median: at(r.len() / 2), min: at(0), max: at(r.len().saturating_sub(1)) }
    }

    /// `formation replay --explain --top 5` on the run.
    fn explain(&self) -> String {
        let o = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(["replay", "--explain", "--top", "5"])
            .arg(&self.net)
            .output()
            .expect("formation replay --explain");
        String::from_utf8_lossy(&o.stdout).into_owned()
    }
}

/// A figure of every follower, the run's over the model's.
struct Ratios {
    median: f64,
    min: f64,
    max: f64,
}

impl Ratios {
    fn complaint(&self, allowed: f64) -> String {
        format!(
            "the formation's median torque variation is {:.3} of the simulator's (allowed 1 ± {allowed}; followers \
             {:.3}–{:.3})",
            self.median, self.min, self.max
        )
    }
}

/// `replay --explain`'s hearing line: "hearing: D of N link-steps differ
/// from the model (…): …, S heard nothing where the model heard, …".
struct Hearing {
    differ: u64,
    link_steps: u64,
    silent: u64,
}

impl Hearing {
    fn parse(explained: &str) -> Self {
        let line = explained
            .lines()
            .find(|l| l.starts_with("hearing:"))
            .unwrap_or_else(|| panic!("no hearing line in formation replay --explain's output:\n{explained}"));
        let number_before = |words: &str| -> u64 {
            let head = line.split(words).next().unwrap_or("");
            head.split_whitespace()
                .last()
                .and_then(|w| w.parse().ok())
                .unwrap_or_else(|| panic!("no number before '{words}' in: {line}"))
        };
        let after_hearing = line.trim_start_matches("hearing:").trim_start();
        let differ = after_hearing.split_whitespace().next().and_then(|w| w.parse().ok());
        Hearing {
            differ: differ.unwrap_or_else(|| panic!("no count in: {line}")),
            link_steps: number_before(" link-steps"),
            silent: number_before(" heard nothing"),
        }
    }
}
