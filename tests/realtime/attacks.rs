//! A node that holds a valid certificate and attacks the formation with
//! only what it may send: its own keys flooded with `Block`, telemetry far
//! larger than a batch, and a storm of failed TLS handshakes from a host
//! with no certificate (free ports on 127.0.0.1, see `common::Ports`;
//! multicast scouting off). Every figure in a message is what the test measured.

use crate::common;

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{Group, Ports, LAUNCH_PORTS};
use formation_net::session::{self, ZenohArgs, ZenohMode};

/// The floods and the storm load the machine on purpose: [`Load::Whole`],
/// alone; the attack on a real-time run is judged on its timing beside at
/// most another lab's load ([`Load::Lab`]).
use common::Load;

fn client(port: u16) -> ZenohArgs {
    ZenohArgs { mode: Some(ZenohMode::Client), connect: vec![format!("tcp/127.0.0.1:{port}")], ..Default::default() }
}

fn peer(port: u16) -> ZenohArgs {
    ZenohArgs {
        mode: Some(ZenohMode::Peer),
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        listen: vec!["tcp/127.0.0.1:0".into()],
        no_gossip: true,
        ..Default::default()
    }
}

/// A session with `name`'s identity from `dir`, as `args`.
async fn open_as(dir: &Path, name: &str, args: ZenohArgs) -> zenoh::Session {
    let args = ZenohArgs { tls: Some(dir.into()), identity: Some(name.into()), ..args };
    tokio::time::timeout(Duration::from_secs(20), session::open(&args))
        .await
        .unwrap_or_else(|_| panic!("{name}: no session within 20 s"))
        .unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// The largest resident set (kB) of the group's `node monitor` process, polled until `stop`.
fn watch_monitor(group_pid: u32, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<u64> {
    std::thread::spawn(move || {
        let mut peak = 0u64;
        while !stop.load(Ordering::Relaxed) {
            for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
                let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
                let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else { continue };
                let pgrp = stat.rsplit_once(')').and_then(|(_, r)| r.split_whitespace().nth(2)?.parse::<u32>().ok());
                if pgrp != Some(group_pid) {
                    continue;
                }
                let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
                if !String::from_utf8_lossy(&cmd).contains("monitor") {
                    continue;
                }
                let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
                let hwm = status
                    .lines()
                    .find(|l| l.starts_with("VmHWM:"))
                    .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
                    .unwrap_or(0);
                peak = peak.max(hwm);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        peak
    })
}

/// Formation error over the last 10 s, per follower, of a run folder.
fn formation_errors(dir: &Path) -> Vec<(String, f64)> {
    let s = common::json(dir, "summary.json");
    let f = s["followers"].as_object().expect("followers");
    f.iter().map(|(id, v)| (id.clone(), v["formation_rms_last10"].as_f64().expect("formation_rms_last10"))).collect()
}

/// What a second process with agent 2's certificate does during a run.
#[derive(Clone, Copy, PartialEq, Debug)]
enum Attack {
    None,
    /// Floods agent 2's estimate key with `Block` (100 puts a millisecond at
    /// most) and puts 1.8 MB on its telemetry key ten times a second.
    Flood,
    /// Hears the genuine agent 2's estimates and publishes each again,
    /// stamped 5 steps ahead, with the leader's estimate moved 5 m.
    Twin,
}

/// What the attacker did and what it saw.
#[derive(Default)]
struct Done {
    sent: AtomicU64,
    big: AtomicU64,
    /// The first step it stamped (the genuine step + 5).
    first_step: AtomicU64,
}

async fn attack(kind: Attack, certs: &Path, port: u16, run: &str, done: &Done, stop: &AtomicBool) {
    tokio::time::sleep(Duration::from_secs(1)).await;
    let s = open_as(certs, "agent-2", client(port)).await;
    let start = Instant::now();
    let over = || stop.load(Ordering::Relaxed) || start.elapsed() > Duration::from_secs(12);
    match kind {
        Attack::None => {}
        Attack::Flood => {
            let est = s
                .declare_publisher(format!("formation/{run}/estimate/2"))
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .express(true)
                .await
                .expect("publisher");
            let tel = s
                .declare_publisher(format!("formation/{run}/telemetry/2"))
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .await
                .expect("publisher");
            let (junk, huge) = (vec![0u8; 83], vec![7u8; 1_800_000]);
            let mut next_big = Instant::now();
            while !over() {
                let tick = Instant::now();
                for _ in 0..100 {
                    if est.put(junk.clone()).await.is_ok() {
                        done.sent.fetch_add(1, Ordering::Relaxed);
                    }
                }
                if tick >= next_big {
                    if tel.put(huge.clone()).await.is_ok() {
                        done.big.fetch_add(1, Ordering::Relaxed);
                    }
                    next_big += Duration::from_millis(100);
                }
                if let Some(rest) = Duration::from_millis(1).checked_sub(tick.elapsed()) {
                    tokio::time::sleep(rest).await;
                }
            }
        }
        Attack::Twin => {
            use formation_protocol::wire;
            let key = format!("formation/{run}/estimate/2");
            let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<Vec<u8>>();
            // Only the genuine agent 2's messages (not its own copies).
            let _sub = s
                .declare_subscriber(&key)
                .allowed_origin(zenoh::sample::Locality::Remote)
                .callback(move |m| {
                    let _ = tx.send(m.payload().to_bytes().into_owned());
                })
                .await
                .expect("subscriber");
            let p = s.declare_publisher(&key).await.expect("publisher");
            while !over() {
                let Ok(Some(bytes)) = tokio::time::timeout(Duration::from_millis(100), rx.recv()).await else {
                    continue;
                };
                let Ok(mut m) = wire::decode(&bytes) else { continue };
                m.header.step += 5;
                m.state.pose.x += 5.0;
                let _ = done.first_step.compare_exchange(0, m.header.step, Ordering::Relaxed, Ordering::Relaxed);
                if p.put(wire::encode(&m)).await.is_ok() {
                    done.sent.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }
    let _ = s.close().await;
}

/// Real-time runs (client mode, TLS, 12 s) unattacked and attacked by a
/// second process holding agent 2's certificate, using only agent 2's keys:
/// - a flood with `Block` and 1.8 MB telemetry puts (which took every
///   follower's error over the last 10 s from 0.10–0.13 m to 3.6 m and ended
///   the run);
/// - a twin stamping 5 steps ahead (which held back 19,245 of agent 2's
///   genuine messages as stale, errors 3.0–4.5 m for everyone, unsaid).
///
/// Each attacked run must keep every follower's error within 10 % of the
/// unattacked run's and the monitor below 100 MB; the twin must be flagged
/// in network.json within 1 s.
#[test]
fn a_certified_node_cannot_take_a_realtime_formation_down_with_its_own_keys() {
    let _cores = common::cores(Load::Lab);
    let tmp = tempfile::tempdir().expect("tempdir");
    let certs = tmp.path().join("certs");
    common::certs(&certs);
    let c = certs.display().to_string();
    // A modelled delay of 5 steps: a run's late source-steps then say
    // whether it kept the period (common::judge_if_timely).
    let sets = ["timing=realtime", "duration=12", "network.delay_steps=5"];
    let run = |kind: Attack| -> (std::path::PathBuf, Done, u64) {
        let out = tmp.path().join(format!("{kind:?}"));
        let name = format!("atk-{kind:?}").to_lowercase();
        let port = Ports::free(1).release();
        let base = port.to_string();
        let mut g =
            Group::launch(&out, &sets, &["--mode", "client", "--tls", &c, "--base-port", &base, "--run", &name]);
        let stop = Arc::new(AtomicBool::new(false));
        let rss = watch_monitor(g.0.id(), stop.clone());
        let done = Arc::new(Done::default());
        let attacker = {
            let (done, stop, certs) = (done.clone(), stop.clone(), certs.clone());
            std::thread::spawn(move || {
                let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
                rt.block_on(attack(kind, &certs, port, &name, &done, &stop));
            })
        };
        let status = g.wait(Duration::from_secs(90));
        stop.store(true, Ordering::Relaxed);
        attacker.join().expect("attacker");
        let peak = rss.join().expect("rss");
        let health = std::fs::read_to_string(out.join("network.json"))
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok().map(|v| v["health"].to_string()));
        assert!(status.success(), "the run ({kind:?}) ended {status}; health: {health:?}");
        (out, Arc::try_unwrap(done).unwrap_or_default(), peak)
    };
    let (calm, _, calm_rss) = run(Attack::None);
    let (flood, flooded, flood_rss) = run(Attack::Flood);
    let (twin, twinned, twin_rss) = run(Attack::Twin);

    let sent = flooded.sent.load(Ordering::Relaxed);
    // The attacker's own link pushes back on Block (how much varies, 64,500–
    // 254,400 here): at least 40,000 is more than three times what the
    // genuine agent 2 publishes in the run (12,001).
    assert!(sent > 40_000, "the flood sent only {sent} estimates: not an attack");
    let copies = twinned.sent.load(Ordering::Relaxed);
    assert!(copies > 1_000, "the twin sent only {copies} estimates: not an attack");
    for (what, rss) in [("flooded", flood_rss), ("twinned", twin_rss)] {
        assert!(
            rss < 100 * 1024,
            "the {what} run's monitor peaked at {} MB (unattacked {} MB)",
            rss / 1024,
            calm_rss / 1024
        );
    }
    // The twin is flagged, by the followers that hear agent 2, within 1 s.
    let n = common::json(&twin, "network.json");
    let flagged = n["twins"].as_array().cloned().unwrap_or_default();
    let two =
        flagged.iter().find(|t| t["follower"] == 2).unwrap_or_else(|| panic!("follower 2 not flagged: {flagged:?}"));
    let began = twinned.first_step.load(Ordering::Relaxed).saturating_sub(5) as f64 * 1e-3;
    let since = two["since_t"].as_f64().expect("since_t");
    assert!(since >= began, "the twin began at t = {began:.3} s and was flagged before, at {since:.3} s: {two}");
    assert_eq!(two["seen_by"], serde_json::json!([1, 4]), "{two}");
    let (a, b, t) = (formation_errors(&calm), formation_errors(&flood), formation_errors(&twin));
    let mut wrong = Vec::new();
    // How soon is the host's speed as much as the code's: judged below.
    if since - began > 1.0 {
        wrong.push(format!("the twin began at t = {began:.3} s and was flagged at {since:.3} s (1 s allowed)"));
    }
    for (what, run) in [("flood", &b), ("twin", &t)] {
        for ((id, x), (_, y)) in a.iter().zip(run) {
            if (y - x).abs() > 0.10 * x {
                wrong.push(format!("{what}: follower {id} {y:.4} m against {x:.4} m unattacked"));
            }
        }
    }
    let networks: Vec<serde_json::Value> =
        [&calm, &flood, &twin].iter().map(|d| common::json(d, "network.json")).collect();
    common::judge_if_timely(
        "attacks with agent 2's certificate",
        &wrong,
        &networks.iter().collect::<Vec<_>>(),
        &format!("flood: {sent} estimates, {} of 1.8 MB; twin: {copies} copies", flooded.big.load(Ordering::Relaxed)),
    );
    eprintln!(
        "realtime attacks: formation error over the last 10 s unattacked {a:?}; flood ({sent} estimates with Block, {} \
         puts of 1.8 MB) {b:?}; twin ({copies} copies 5 steps ahead, flagged at t = {since:.3} s, began {began:.3} s) \
         {t:?}; monitor peak {} / {} / {} MB",
        flooded.big.load(Ordering::Relaxed),
        calm_rss / 1024,
        flood_rss / 1024,
        twin_rss / 1024
    );
}

/// A certified agent 2 dials the monitor straight (peer mode) during a
/// lock-step run and sends it 400 telemetry puts of 1.8 MB and 2,000 of
/// 80 KB that are not telemetry. Without the limits the monitor went from
/// 21 MB to 784 MB and the run failed; now the run must equal the
/// simulator byte for byte and the monitor stay below 100 MB.
#[test]
fn telemetry_sent_straight_to_the_monitor_cannot_fill_its_memory() {
    let _cores = common::cores(Load::Whole);
    let tmp = tempfile::tempdir().expect("tempdir");
    let certs = tmp.path().join("certs");
    common::certs(&certs);
    let c = certs.display().to_string();
    let out = tmp.path().join("net");
    let sets = ["duration=5"];
    // Peer ports: the monitor's is the first.
    let port = Ports::free(LAUNCH_PORTS).release();
    let mut g = Group::launch(&out, &sets, &["--tls", &c, "--base-port", &port.to_string(), "--run", "mem"]);
    let stop = Arc::new(AtomicBool::new(false));
    let rss = watch_monitor(g.0.id(), stop.clone());
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let (big, junk) = rt.block_on(async {
        tokio::time::sleep(Duration::from_millis(300)).await;
        let s = open_as(&certs, "agent-2", peer(port)).await;
        let p = s.declare_publisher("formation/mem/telemetry/2").await.expect("publisher");
        let (mut big, mut junk) = (0, 0);
        let huge = vec![1u8; 1_800_000];
        for _ in 0..400 {
            big += u32::from(p.put(huge.clone()).await.is_ok());
        }
        let mid = vec![2u8; 80_000];
        for _ in 0..2000 {
            junk += u32::from(p.put(mid.clone()).await.is_ok());
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        let _ = s.close().await;
        (big, junk)
    });
    let status = g.wait(Duration::from_secs(120));
    stop.store(true, Ordering::Relaxed);
    let peak = rss.join().expect("rss");
    assert!(status.success(), "the run ended {status}");
    assert!(peak > 0, "the monitor's memory was never read");
    assert!(
        peak < 100 * 1024,
        "the monitor peaked at {} MB after {big} puts of 1.8 MB and {junk} of 80 KB",
        peak / 1024
    );
    common::assert_equals_the_simulator(
        &out,
        &tmp.path().join("sim"),
        &sets,
        "a lock-step run with the monitor attacked",
    );
    eprintln!(
        "monitor: {big} puts of 1.8 MB and {junk} of 80 KB sent; peak {} MB; the run equals formation sim",
        peak / 1024
    );
}

/// 100 connections a second that close before their TLS handshake, from a
/// host with no certificate, at the TLS router: a certified node must still
/// join within 1 s (upstream's accept loop slept 100 ms after each, and 20
/// a second kept certified nodes out).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_storm_of_failed_handshakes_does_not_delay_a_certified_join() {
    let _cores = common::cores(Load::Whole);
    let tmp = tempfile::tempdir().expect("tempdir");
    let certs = tmp.path().join("certs");
    common::certs(&certs);
    let port = Ports::free(1).release();
    let ep = format!("tcp/127.0.0.1:{port}");
    let _router = Group::spawn(&["node", "router", "--listen", &ep, "--tls", &certs.display().to_string()]);
    let t = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t.elapsed() < common::GUARD, "the TLS router did not listen within {:?}", common::GUARD);
        std::thread::sleep(Duration::from_millis(50));
    }
    let stop = Arc::new(AtomicBool::new(false));
    let storms = Arc::new(AtomicU64::new(0));
    let storm = {
        let (stop, storms) = (stop.clone(), storms.clone());
        std::thread::spawn(move || {
            let start = Instant::now();
            while !stop.load(Ordering::Relaxed) {
                // Connect, say something that is not TLS, close.
                if let Ok(mut s) = std::net::TcpStream::connect(("127.0.0.1", port)) {
                    use std::io::Write;
                    let _ = s.write_all(b"not a TLS hello\r\n");
                    storms.fetch_add(1, Ordering::Relaxed);
                }
                let due = start + Duration::from_millis(10 * storms.load(Ordering::Relaxed));
                if let Some(rest) = due.checked_duration_since(Instant::now()) {
                    std::thread::sleep(rest);
                }
            }
        })
    };
    tokio::time::sleep(Duration::from_secs(2)).await;
    let mut joins = Vec::new();
    for name in ["agent-1", "agent-3", "leader"] {
        let t = Instant::now();
        let s = open_as(&certs, name, client(port)).await;
        joins.push((name, t.elapsed()));
        let _ = s.close().await;
    }
    stop.store(true, Ordering::Relaxed);
    storm.join().expect("storm");
    let rate = storms.load(Ordering::Relaxed) as f64 / t.elapsed().as_secs_f64();
    assert!(rate > 80.0, "the storm reached only {rate:.0} connections/s");
    for (name, took) in &joins {
        assert!(*took < Duration::from_secs(1), "{name} took {took:?} to join under {rate:.0} failed handshakes/s");
    }
    eprintln!("storm: {rate:.0} failed handshakes/s; joins {joins:?}");
}
