//! Issue 30's attacks from the wire, each with its crafted bytes here, each
//! held: a process on the run's router (no TLS, client mode, a free port
//! on 127.0.0.1, multicast scouting off) sends
//! - a 46-byte telemetry message on `telemetry/1` whose `diverged` string
//!   declares 2^62 bytes (it aborted the monitor), a 13-byte start-up
//!   `ready` with a like length field (it aborted four nodes, the leader
//!   among them), puts on control keys and a flood of time questions;
//! - answers on `control/time` from a clock 0.5 s ahead of the leader's,
//!   from the start or joining mid-run (every follower ran 500 steps ahead
//!   and ended 11.5 m off, and the run said "complete").
//!
//! No process may die, the formation's error must be its model's (lock-step:
//! the simulator's exactly; real time: within 1 %), and network.json must
//! name the attack.

use crate::common;

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{Group, Ports};
use formation_net::session::{self, ZenohArgs, ZenohMode};

/// The floods load the machine on purpose ([`Load::Whole`], alone); the
/// second clock's real-time run is judged beside at most another lab's
/// load ([`Load::Lab`]).
use common::Load;

fn client(port: u16) -> ZenohArgs {
    ZenohArgs { mode: Some(ZenohMode::Client), connect: vec![format!("tcp/127.0.0.1:{port}")], ..Default::default() }
}

async fn open(port: u16) -> zenoh::Session {
    tokio::time::timeout(Duration::from_secs(20), session::open(&client(port)))
        .await
        .expect("the attacker has no session within 20 s")
        .expect("the attacker's session")
}

/// bincode's varint of a u64 that needs 8 bytes: marker 253, then little-endian.
fn varint_u64(v: u64) -> Vec<u8> {
    let mut b = vec![253];
    b.extend_from_slice(&v.to_le_bytes());
    b
}

/// A follower's telemetry batch as follower 1 would send it, with no samples
/// and its `diverged` string declared 2^62 bytes long: the encoding of a
/// real batch with `diverged = Some("")`, its last byte (the string's length,
/// 0) replaced by the varint of 2^62.
fn telemetry_declaring_2_pow_62() -> Vec<u8> {
    use formation_protocol::telemetry::Telemetry;
    let mut batch = common::empty_follower_batch(1);
    if let Telemetry::Follower { diverged, .. } = &mut batch {
        *diverged = Some(String::new());
    }
    let mut bytes = formation_protocol::codec::encode(&batch);
    assert_eq!(bytes.pop(), Some(0), "the batch ends with the empty string's length");
    bytes.extend(varint_u64(1 << 62));
    bytes
}

/// A start-up `ready` (fingerprint 0, one key digest) whose key's string
/// declares 2^62 bytes: 13 bytes.
fn ready_declaring_2_pow_62() -> Vec<u8> {
    let mut b = vec![0, 1];
    b.extend(varint_u64(1 << 62));
    b.extend([0, 0]);
    b
}

/// Each follower's formation error over the last 10 s, by id.
fn errors(dir: &Path) -> Vec<(String, f64)> {
    let s = common::json(dir, "summary.json");
    let f = s["followers"].as_object().expect("followers");
    f.iter().map(|(id, v)| (id.clone(), v["formation_rms_last10"].as_f64().expect("formation_rms_last10"))).collect()
}

/// The lock-step paper run (5 s) while a process on its router sends the
/// crafted messages, garbage on every control key and a flood of time
/// questions, from before the start to the end.
#[test]
fn crafted_length_fields_and_control_floods_crash_nothing_and_are_counted() {
    let _cores = common::cores(Load::Whole);
    let tmp = tempfile::tempdir().expect("tempdir");
    let (out, sim) = (tmp.path().join("run"), tmp.path().join("sim"));
    let sets = ["duration=5"];
    let run = "wire-lengths";
    let telemetry = telemetry_declaring_2_pow_62();
    let ready = ready_declaring_2_pow_62();
    // The were 46 and 13 bytes: these are as small (the batch 47
    // since its counters count old-term messages too, format 5).
    assert!(telemetry.len() <= 47 && ready.len() == 13, "{} and {} bytes", telemetry.len(), ready.len());
    let stop = Arc::new(AtomicBool::new(false));
    let (puts, queries) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let port = Ports::free(1).release();
    let mut g = Group::launch(&out, &sets, &["--mode", "client", "--base-port", &port.to_string(), "--run", run]);
    let attacker = {
        let (stop, puts, queries) = (stop.clone(), puts.clone(), queries.clone());
        std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
            rt.block_on(async move {
                tokio::time::sleep(Duration::from_millis(300)).await;
                let s = open(port).await;
                let key = |rest: &str| format!("formation/{run}/{rest}");
                let began = Instant::now();
                while !stop.load(Ordering::Relaxed) && began.elapsed() < Duration::from_secs(60) {
                    for (k, bytes) in [
                        (key("telemetry/1"), telemetry.clone()),
                        (key("control/ready/1"), ready.clone()),
                        (key("control/ready/monitor"), ready.clone()),
                        (key("control/start"), ready.clone()),
                        (key("control/ack"), telemetry.clone()),
                        (key("control/hello/leader"), b"garbage".to_vec()),
                    ] {
                        if s.put(k, bytes).await.is_ok() {
                            puts.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    // Time questions as fast as the leader answers them.
                    for _ in 0..20 {
                        if let Ok(r) = s.get(key("control/time")).timeout(Duration::from_millis(200)).await {
                            while r.recv_async().await.is_ok() {}
                            queries.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
                let _ = s.close().await;
            })
        })
    };
    let status = g.wait(Duration::from_secs(120));
    stop.store(true, Ordering::Relaxed);
    attacker.join().expect("attacker");
    let (puts, queries) = (puts.load(Ordering::Relaxed), queries.load(Ordering::Relaxed));
    assert!(puts > 200 && queries > 500, "not an attack: {puts} puts, {queries} time questions");
    assert_eq!(status.code(), Some(0), "the attacked run ended {status} ({puts} puts, {queries} questions)");
    g.assert_group_empty();
    // The formation is untouched: the simulator's numbers, byte for byte.
    common::assert_equals_the_simulator(&out, &sim, &sets, "the attacked lock-step run");
    // And the attack is named.
    let n = common::json(&out, "network.json");
    let by_key = &n["malformed_telemetry_by_key"]["telemetry/1"];
    assert!(
        by_key.as_u64().unwrap_or(0) > 0,
        "the crafted telemetry is not counted on telemetry/1: {}",
        n["malformed_telemetry_by_key"]
    );
    for k in ["control/ready/1", "control/start", "control/ack", "control/hello/leader"] {
        let refused = n["control_puts"][k]["refused"].as_u64().unwrap_or(0);
        assert!(refused > 0, "{k}: no refused put counted ({puts} sent): {}", n["control_puts"]);
    }
    let leader = &n["nodes"]["leader"];
    let peak = leader["time_queries_peak_per_s"].as_u64().unwrap_or(0);
    // The leader counts what reached it while it ran (the attacker asks on after it ends).
    let counted = leader["time_queries"].as_u64().unwrap_or(0);
    assert!(counted >= 1_000 && peak > 240, "time questions not counted ({queries} asked): {leader}");
    let h = &n["health"];
    assert_eq!(h["verdict"], "disturbed", "{h}");
    let said = h["disturbed"].to_string();
    for words in ["puts refused on control keys", "telemetry messages refused", "a flood of questions on control/time"]
    {
        assert!(said.contains(words), "health does not say '{words}': {said}");
    }
    eprintln!(
        "crafted lengths: {puts} puts and {queries} time questions (the leader's peak {peak}/s); the run equals the \
         simulator; health: {said}"
    );
}

/// Answers `control/time` with the leader's reply format from a clock
/// `ahead` of this host's wall clock (the leader's timebase is its wall
/// clock at its start) until `stop`, from `after` on.
/// `first_unix_ns`: this host's wall clock at the first forged answer;
/// `epoch`: the run's, from the leader's start announcements.
async fn forge_time(
    port: u16,
    run: &str,
    ahead: Duration,
    after: Duration,
    stop: Arc<AtomicBool>,
    answered: Arc<AtomicU64>,
    first_unix_ns: Arc<AtomicU64>,
    epoch: Arc<AtomicU64>,
) {
    tokio::time::sleep(after).await;
    let s = open(port).await;
    let unix_ns =
        || std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as i64).unwrap_or(0);
    // The run's epoch, from the leader's start announcements.
    let _start = {
        let epoch = epoch.clone();
        s.declare_subscriber(format!("formation/{run}/control/start"))
            .callback(move |m| {
                if let Some(st) =
                    formation_protocol::codec::decode::<formation_protocol::barrier::Start>(&m.payload().to_bytes())
                {
                    epoch.store(st.epoch_unix_ns, Ordering::Relaxed);
                }
            })
            .await
            .expect("start subscriber")
    };
    let ahead_ns = ahead.as_nanos() as i64;
    let _q = s
        .declare_queryable(format!("formation/{run}/control/time"))
        .callback(move |q| {
            use zenoh::Wait;
            let t2 = unix_ns() + ahead_ns;
            let reply = formation_protocol::codec::encode(&formation_net::clock_sync::TimeReply {
                t2,
                t3: unix_ns() + ahead_ns,
            });
            if q.reply(q.key_expr().clone(), reply).wait().is_ok() && answered.fetch_add(1, Ordering::Relaxed) == 0 {
                first_unix_ns.store(unix_ns() as u64, Ordering::Relaxed);
            }
        })
        .await
        .expect("queryable");
    while !stop.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let _ = s.close().await;
}

/// Real-time runs (10 s, client mode, no TLS) with a second clock 0.5 s
/// ahead answering on `control/time`: from before the start, and joining at
/// about 4 s. Each must end with every follower's error within 1 % of its
/// model's, the second clock named by the followers within 1 s of joining
/// (mid-run) and in network.json's health, and exit 0 ("disturbed").
#[test]
fn a_second_clock_half_a_second_ahead_never_moves_the_formation() {
    let _cores = common::cores(Load::Lab);
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut wrong = Vec::new();
    let mut networks = Vec::new();
    let mut seen = Vec::new();
    for (case, after, tag) in
        [("from the start", Duration::ZERO, "start"), ("joining mid-run", Duration::from_secs(4), "mid")]
    {
        let out = tmp.path().join(tag);
        let run = format!("wire-clock-{tag}");
        let stop = Arc::new(AtomicBool::new(false));
        let answered = Arc::new(AtomicU64::new(0));
        let (first_unix_ns, epoch) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
        let began = Instant::now();
        let port = Ports::free(1).release();
        let mut g = Group::launch(
            &out,
            &["timing=realtime", "duration=10", "network.delay_steps=5"],
            &["--mode", "client", "--base-port", &port.to_string(), "--run", &run],
        );
        let forger = {
            let (stop, answered, run) = (stop.clone(), answered.clone(), run.clone());
            let (first, epoch) = (first_unix_ns.clone(), epoch.clone());
            std::thread::spawn(move || {
                let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
                rt.block_on(forge_time(port, &run, Duration::from_millis(500), after, stop, answered, first, epoch));
            })
        };
        let status = g.wait(Duration::from_secs(120));
        stop.store(true, Ordering::Relaxed);
        forger.join().expect("forger");
        let answered = answered.load(Ordering::Relaxed);
        assert!(answered > 10, "{case}: the forger answered only {answered} questions: not an attack");
        assert_eq!(status.code(), Some(0), "{case}: the run ended {status}");
        g.assert_group_empty();
        let n = common::json(&out, "network.json");
        let h = &n["health"];
        assert_eq!(h["verdict"], "disturbed", "{case}: {h}");
        // Every follower's error against its model (the simulator on the same scenario).
        for m in h["model"].as_array().expect("the model was run") {
            let (run_m, model_m) = (m["run_m"].as_f64().unwrap(), m["model_m"].as_f64().unwrap());
            if (run_m - model_m).abs() > 0.01 * model_m {
                wrong.push(format!("{case}: follower {} {run_m:.4} m, its model {model_m:.4} m", m["follower"]));
            }
        }
        // Named by the followers: in their clock report and on their timeline.
        let mut named = 0;
        for id in ["1", "2", "3", "4"] {
            let node = &n["nodes"][id];
            if node["clock"]["guard"]["second_clock_since_ns"].is_null() {
                continue;
            }
            named += 1;
            let worst = node["clock"]["guard"]["worst_disagreement_ms"].as_f64().unwrap_or(0.0);
            assert!((worst - 500.0).abs() < 50.0, "{case}: follower {id} saw clocks {worst} ms apart");
            let when = node["timeline"]
                .as_array()
                .into_iter()
                .flatten()
                .find(|e| e["event"].as_str().is_some_and(|s| s.contains("second clock")))
                .and_then(|e| e["t"].as_f64());
            let when = when.unwrap_or_else(|| panic!("{case}: follower {id}'s timeline does not name the clock"));
            seen.push(format!("{case}: follower {id} named it at t = {when:.2} s"));
            if !after.is_zero() {
                // Mid-run: named within 1 s of the forger's first answer.
                let (f, e) = (first_unix_ns.load(Ordering::Relaxed) as f64, epoch.load(Ordering::Relaxed) as f64);
                assert!(e > 0.0, "{case}: the forger never heard the leader's start announcement");
                let first = (f - e) * 1e-9;
                assert!(first > 0.5, "{case}: the forger's first answer came at t = {first:.2} s: not mid-run");
                if when - first > 1.0 {
                    wrong.push(format!(
                        "{case}: follower {id} named the clock at t = {when:.2} s, its first answer was at {first:.2} s"
                    ));
                }
            }
        }
        assert!(named >= 1, "{case}: no follower named the second clock: {}", n["nodes"]);
        eprintln!(
            "second clock {case}: {answered} forged answers, {:.1} s; errors {:?}; {}",
            began.elapsed().as_secs_f64(),
            errors(&out),
            h["disturbed"]
        );
        networks.push(n.clone());
    }
    common::judge_if_timely("a second clock", &wrong, &networks.iter().collect::<Vec<_>>(), &seen.join("; "));
}
