//! `formation certs` and `--tls`: mutual TLS on every link and access
//! control derived from the topology (free ports on 127.0.0.1, see
//! `common::Ports`; multicast scouting off in every session). Every count
//! in a message is what the test measured.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{Group, Ports, LAUNCH_PORTS, LIMIT, SCENARIO};
use formation_leader::LeaderState;
use formation_net::session::{self, ZenohArgs, ZenohMode};
use formation_protocol::wire::{self, EstimateMsg, Header, FORMAT_VERSION};

/// A TLS router child on a free port, up and listening; the port.
fn router(dir: &Path) -> (u16, Group) {
    let port = Ports::free(1).release();
    let ep = format!("tcp/127.0.0.1:{port}");
    let d = dir.display().to_string();
    let g = Group::spawn(&["node", "router", "--listen", &ep, "--tls", &d]);
    let t = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t.elapsed() < common::GUARD, "the TLS router did not listen on {port} within {:?}", common::GUARD);
        std::thread::sleep(Duration::from_millis(50));
    }
    (port, g)
}

/// A folder of certificates and a TLS router using them; its port.
fn tls_router() -> (tempfile::TempDir, PathBuf, u16, Group) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let (port, g) = router(&dir);
    (tmp, dir, port, g)
}

fn client(port: u16) -> ZenohArgs {
    ZenohArgs { mode: Some(ZenohMode::Client), connect: vec![format!("tcp/127.0.0.1:{port}")], ..Default::default() }
}

/// A client with `name`'s identity from `dir`.
async fn open_as(dir: &Path, name: &str, port: u16) -> zenoh::Session {
    let args = ZenohArgs { tls: Some(dir.into()), identity: Some(name.into()), ..client(port) };
    tokio::time::timeout(Duration::from_secs(20), session::open(&args))
        .await
        .unwrap_or_else(|_| panic!("{name}: no session within 20 s"))
        .unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn estimate(sender: u32, step: u64) -> Vec<u8> {
    wire::encode(&EstimateMsg {
        header: Header { version: FORMAT_VERSION, sender, step, time_s: step as f64 * 1e-3, sent_ns: 0 },
        state: LeaderState { v: 1.0, ..Default::default() },
        fresh: true,
        term: u32::from(sender == 0),
    })
}

/// Counts the samples arriving on `key`.
async fn counter(s: &zenoh::Session, key: &str) -> (zenoh::pubsub::Subscriber<()>, Arc<AtomicU64>) {
    let n = Arc::new(AtomicU64::new(0));
    let m = n.clone();
    let sub = s
        .declare_subscriber(key)
        .callback(move |_| {
            m.fetch_add(1, Ordering::Relaxed);
        })
        .await
        .expect("subscriber");
    (sub, n)
}

/// Records the step of every estimate arriving on `key`.
async fn steps_heard(
    s: &zenoh::Session,
    key: &str,
) -> (zenoh::pubsub::Subscriber<()>, Arc<std::sync::Mutex<Vec<u64>>>) {
    let v = Arc::new(std::sync::Mutex::new(Vec::new()));
    let w = v.clone();
    let sub = s
        .declare_subscriber(key)
        .callback(move |sample| {
            if let Ok(m) = wire::decode(&sample.payload().to_bytes()) {
                w.lock().unwrap().push(m.header.step);
            }
        })
        .await
        .expect("subscriber");
    (sub, v)
}

/// The steps of 0..n that never arrived, as ranges ("0-135, 700-712").
fn lost_steps(heard: &std::sync::Mutex<Vec<u64>>, n: u64) -> String {
    let got: std::collections::BTreeSet<u64> = heard.lock().unwrap().iter().copied().collect();
    let mut ranges: Vec<(u64, u64)> = Vec::new();
    for k in (0..n).filter(|k| !got.contains(k)) {
        match ranges.last_mut() {
            Some(r) if r.1 + 1 == k => r.1 = k,
            _ => ranges.push((k, k)),
        }
    }
    let text: Vec<String> =
        ranges.iter().map(|(a, b)| if a == b { a.to_string() } else { format!("{a}-{b}") }).collect();
    if text.is_empty() {
        "none".into()
    } else {
        text.join(", ")
    }
}

/// Waits up to `limit` for `n` to reach `want`; its last value.
async fn settle(n: &AtomicU64, want: u64, limit: Duration) -> u64 {
    let t = Instant::now();
    while n.load(Ordering::Relaxed) < want && t.elapsed() < limit {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    n.load(Ordering::Relaxed)
}

#[test]
fn certs_keeps_the_authority_apart_refuses_to_overwrite_and_never_follows_links() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let names = ["router", "leader", "monitor", "agent-1", "agent-2", "agent-3", "agent-4"];
    for n in names {
        let id = formation_certs::identity(&dir, n).unwrap_or_else(|e| panic!("{n}: {e}"));
        let mode = std::fs::metadata(&id.key).expect("key").permissions().mode() & 0o777;
        assert_eq!(mode, 0o600, "{n}'s key is {mode:o}, not readable by its owner only");
        // A node's folder alone (as copied to its host) is enough, and holds no authority key.
        let own = dir.join(n);
        formation_certs::identity(&own, n).unwrap_or_else(|e| panic!("{n}'s folder alone: {e}"));
        let files: Vec<String> = std::fs::read_dir(&own)
            .expect("node folder")
            .map(|e| e.expect("entry").file_name().into_string().unwrap())
            .collect();
        assert!(!files.iter().any(|f| f == "ca.key"), "{n}'s folder holds the authority's key: {files:?}");
    }
    let ca_mode = std::fs::metadata(dir.join("ca/ca.key")).expect("ca/ca.key").permissions().mode() & 0o777;
    assert_eq!(ca_mode, 0o600, "the authority's key is {ca_mode:o}");
    // Again: refused, nothing replaced.
    let before = std::fs::read(dir.join("agent-3/agent-3.key")).expect("key");
    let o = common::certs_with(&dir, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "a second run without --force: {err}");
    assert!(err.contains("exists") && err.contains("--force"), "{err}");
    assert_eq!(std::fs::read(dir.join("agent-3/agent-3.key")).expect("key"), before, "a key was replaced");
    // --node reissues one node with the same authority and revokes its old certificate.
    let old3 = tmp.path().join("old-agent-3");
    copy_dir(&dir.join("agent-3"), &old3);
    let ca = std::fs::read(dir.join("ca/ca.pem")).expect("ca.pem");
    let o = common::certs_with(&dir, &["--node", "agent-3"]);
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success() && said.contains("using the existing authority"), "--node said: {said}");
    assert_eq!(std::fs::read(dir.join("ca/ca.pem")).expect("ca.pem"), ca, "the authority was replaced");
    formation_certs::identity(&dir, "agent-3").expect("re-issued agent-3 under the same authority");
    // The old certificate with the new folder's revocation list: revoked.
    std::fs::copy(dir.join("agent-3/revoked.crl"), old3.join("revoked.crl")).expect("copy crl");
    std::fs::copy(dir.join("agent-3/policy.json5"), old3.join("policy.json5")).expect("copy policy");
    std::fs::copy(dir.join("agent-3/policy.pem"), old3.join("policy.pem")).expect("copy policy.pem");
    let e = formation_certs::identity(&old3, "agent-3").expect_err("the superseded certificate");
    assert!(e.0.contains("revoked"), "{e}");
    // --force: a new authority, which the old certificates do not verify against.
    let o = common::certs_with(&dir, &["--force"]);
    assert!(o.status.success(), "--force: {}", String::from_utf8_lossy(&o.stderr));
    assert_ne!(std::fs::read(dir.join("ca/ca.pem")).expect("ca.pem"), ca, "--force kept the old authority");
    // Links are never followed: a planted link to an unrelated file is
    // refused before anything is written (tests/it/certs_safety.rs checks every byte).
    let victim = tmp.path().join("victim.txt");
    std::fs::write(&victim, "unrelated").expect("victim");
    std::fs::remove_file(dir.join("agent-1/policy.json5")).expect("rm");
    std::os::unix::fs::symlink(&victim, dir.join("agent-1/policy.json5")).expect("symlink");
    let o = common::certs_with(&dir, &["--node", "agent-1"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "--node with a planted link: {err}");
    assert!(err.contains("symbolic link") && err.contains("policy.json5"), "{err}");
    assert_eq!(std::fs::read_to_string(&victim).expect("victim"), "unrelated", "a file was written through a link");
    let linked = tmp.path().join("linked");
    std::os::unix::fs::symlink(tmp.path().join("elsewhere"), &linked).expect("symlink");
    let o = common::certs_with(&linked, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "--out through a link: {err}");
    assert!(err.contains("symbolic link"), "{err}");
    assert!(!tmp.path().join("elsewhere").exists(), "a folder was made through a link");
    // The policy, for review.
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["certs", SCENARIO, "--policy"])
        .output()
        .expect("certs --policy");
    let policy: serde_json::Value = serde_json::from_slice(&o.stdout).expect("--policy prints JSON");
    assert_eq!(policy["default_permission"], "deny");
    let rules = policy["rules"].as_array().expect("rules");
    let agent3 = rules.iter().find(|r| r["id"] == "agent-3-publishes").expect("agent-3-publishes");
    assert_eq!(
        agent3["key_exprs"],
        serde_json::json!([
            "formation/*/estimate/3",
            "formation/*/telemetry/3",
            "formation/*/control/hello/3",
            "formation/*/control/ready/3",
            "formation/*/control/claim/3",
            "formation/*/control/denied/agent-3",
            "formation/*/control/holds/3"
        ])
    );
    // Its liveliness token (lock-step deaths, formation_protocol::died):
    // its own only.
    let alive = rules.iter().find(|r| r["id"] == "agent-3-is-alive").expect("agent-3-is-alive");
    assert_eq!(alive["key_exprs"], serde_json::json!(["formation/*/alive/3"]));
    assert_eq!(alive["messages"], serde_json::json!(["liveliness_token"]));
}

/// `formation launch --tls` in lock-step equals `formation sim` byte for
/// byte; with `forge`, a session with agent 2's valid identity floods agent
/// 3's and the leader's estimate keys through the router during the run.
fn tls_same_as_sim(mode: &str, run: &str, forge: bool) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let net = tmp.path().join("net");
    let d = dir.display().to_string();
    let port = Ports::free(LAUNCH_PORTS).release();
    let p = port.to_string();
    let mut g = Group::launch(&net, &["duration=1"], &["--mode", mode, "--base-port", &p, "--run", run, "--tls", &d]);
    let sim = tmp.path().join("sim");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", SCENARIO, "-q", "--set", "duration=1", "--out"])
        .arg(&sim)
        .output()
        .expect("sim");
    assert!(o.status.success());
    if forge {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().expect("rt");
        let sent = rt.block_on(flood(&dir, port, run));
        assert_eq!(sent, 20_000, "the forger's puts that returned Ok");
    }
    let status = g.wait(LIMIT);
    assert!(status.success(), "{mode} --tls: formation launch failed: {status}");
    if !forge {
        // The policy lets every node do what the run needs: nothing refused,
        // and the run healthy (an agent's watch of its neighbours' final
        // telemetry was refused once, and every TLS run said "disturbed").
        let n = common::json(&net, "network.json");
        let denied = n["access_denied"].as_array().cloned().unwrap_or_default();
        assert!(
            denied.is_empty(),
            "{mode} --tls: access control refused {} kinds of message: {denied:?}",
            denied.len()
        );
        assert_eq!(n["health"]["verdict"], "healthy", "{mode} --tls: {}", n["health"]);
    }
    if forge {
        let n = common::json(&net, "network.json");
        for id in ["1", "2", "3", "4"] {
            let node = &n["nodes"][id];
            assert_eq!(node["rejected_invalid"], 0, "follower {id} saw forged messages: {node}");
            // Half the forgeries are stamped a million steps ahead: one that
            // reached a follower is counted there as from the future, and
            // nothing else is (a duplicate of a step, such as the lock-step
            // leader's repeats after its last step, is counted late: under
            // load follower 1 got up to 40 of those with no forger at all).
            let future = node["rejected"]["future"].as_u64().expect("rejected.future");
            assert_eq!(future, 0, "follower {id} received {future} of agent 2's forged estimates: {node}");
        }
        // The router's access control refused them, and says so: per subject, action and key.
        let denied = n["access_denied"].as_array().cloned().unwrap_or_default();
        let count = |key: &str| -> u64 {
            denied
                .iter()
                .filter(|d| d["by"] == "router" && d["subject"] == "agent-2" && d["action"] == "Put (ingress)")
                .filter(|d| d["key"] == format!("formation/{run}/{key}"))
                .map(|d| d["count"].as_u64().unwrap_or(0))
                .sum()
        };
        let (as3, as_leader) = (count("estimate/3"), count("estimate/0"));
        // The run may end before the forger does: what the router refused until then.
        assert!(
            (1..=10_000).contains(&as3) && (1..=10_000).contains(&as_leader),
            "network.json counts {as3} refused puts of agent 2 on estimate/3 and {as_leader} on estimate/0 \
             (10,000 each sent, some after the run's end): {denied:?}"
        );
        eprintln!(
            "the router refused, during the run, {as3} of agent 2's puts on estimate/3 and {as_leader} on estimate/0"
        );
    }
    for f in ["summary.json", "follower_1.csv", "follower_2.csv", "follower_3.csv", "follower_4.csv", "leader.csv"] {
        let a = std::fs::read(net.join(f)).expect("net file");
        let b = std::fs::read(sim.join(f)).expect("sim file");
        assert!(a == b, "{mode} --tls: {f} differs from formation sim's ({} against {} bytes)", a.len(), b.len());
    }
}

#[test]
fn tls_lockstep_equals_the_simulator_in_peer_mode() {
    tls_same_as_sim("peer", "tls-peer", false);
}

#[test]
fn tls_lockstep_equals_the_simulator_in_client_mode() {
    tls_same_as_sim("client", "tls-client", false);
}

/// The case: agent 2's own valid certificate, 10,000 estimates on
/// agent 3's key and 10,000 on the leader's during a run (half of them of
/// the run's steps, which a receiver without access control would take;
/// half a million steps ahead, which it would count as from the future):
/// none reaches a follower, and the run equals the simulator.
#[test]
fn forged_estimates_from_a_valid_agent_during_a_tls_run_change_nothing() {
    tls_same_as_sim("client", "tls-forged", true);
}

/// Connects as agent 2 to the run's router and puts 10,000 forged estimates
/// on each of agent 3's and the leader's keys; the puts that returned Ok.
async fn flood(dir: &Path, port: u16, run: &str) -> u64 {
    let forger = open_as(dir, "agent-2", port).await;
    // Once the run is under way (agent 2 may hear follower 1).
    let (_sub, running) = counter(&forger, &format!("formation/{run}/estimate/1")).await;
    let seen = settle(&running, 1, Duration::from_secs(30)).await;
    assert!(seen > 0, "the forger never saw the run start");
    let mut sent = 0;
    for k in 0..10_000u64 {
        // Even puts: the run's own steps (taken, they would change the run);
        // odd: a million steps ahead (taken or not, counted as from the future).
        let step = if k % 2 == 0 { k } else { FORGED_AHEAD + k };
        for sender in [3u32, 0] {
            let key = format!("formation/{run}/estimate/{sender}");
            if forger.put(&key, estimate(sender, step)).await.is_ok() {
                sent += 1;
            }
        }
    }
    sent
}

/// How far ahead of the run half the forged estimates are stamped.
const FORGED_AHEAD: u64 = 1_000_000;

/// A zenoh config file for a rogue: give up after 3 s instead of waiting,
/// plus `extra` (json5 members).
fn rogue_config(tmp: &Path, name: &str, extra: &str) -> PathBuf {
    let f = tmp.join(format!("{name}.json5"));
    std::fs::write(&f, format!("{{ connect: {{ timeout_ms: 3000, exit_on_failure: true }}, {extra} }}"))
        .expect("write");
    f
}

/// A publisher on `key` that waits for room rather than drop, once it
/// knows of a subscriber (at most `limit`; a session that reaches none
/// never does): the control bursts below measure whether a session's
/// messages reach a node, not whether a burst outruns its link.
///
/// Zenoh's default for a put is `CongestionControl::Drop`: when a link's
/// queue (2 batches per priority, a TLS batch at most a record of 16 KB,
/// about 170 estimates) is full for more than `wait_before_drop` (1 ms),
/// the put is dropped at the source and still returns Ok. A burst of 1,000
/// puts on a busy 2-core machine, the link's thread descheduled a few
/// milliseconds, lost 152 that way (CI, issue 47); with the queue at one
/// batch and no wait it loses every put past the first 460 here, a
/// contiguous tail. The formation's own real-time estimates are one put a
/// step (a newer supersedes a dropped one, and the receiver's hearing
/// record counts what it used); its telemetry is acknowledged and resent,
/// and lock-step puts block.
async fn matched_publisher(
    s: &zenoh::Session,
    key: &str,
    limit: Duration,
) -> (zenoh::pubsub::Publisher<'static>, bool) {
    let p = s
        .declare_publisher(key.to_string())
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("publisher");
    let t = Instant::now();
    loop {
        let matched = p.matching_status().await.is_ok_and(|m| m.matching());
        if matched || t.elapsed() >= limit {
            return (p, matched);
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Opens `args`; if it opens, puts 1,000 estimates on agent 2's key.
/// Returns (opened, puts that returned Ok).
async fn rogue(args: &ZenohArgs) -> (bool, u64) {
    let Ok(Ok(s)) = tokio::time::timeout(Duration::from_secs(10), session::open(args)).await else {
        return (false, 0);
    };
    // A session that reaches the leader's subscriber matches at once; one
    // refused by the router never does, and its puts go nowhere.
    let (p, _matched) = matched_publisher(&s, "formation/sec/estimate/2", Duration::from_secs(3)).await;
    let mut sent = 0;
    for k in 0..1000 {
        if p.put(estimate(2, k)).await.is_ok() {
            sent += 1;
        }
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    (true, sent)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_without_a_trusted_certificate_or_without_tls_reach_no_node() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let revoked2 = tmp.path().join("revoked-agent-2");
    copy_dir(&dir.join("agent-2"), &revoked2);
    let o = common::certs_with(&dir, &["--node", "agent-2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (port, _router) = router(&dir);
    let other = tmp.path().join("other");
    common::certs(&other);
    // The receiver (the leader may receive every estimate) and a positive
    // control: agent 2 itself, whose messages must arrive.
    let leader = open_as(&dir, "leader", port).await;
    let (_sub, heard) = counter(&leader, "formation/sec/estimate/*").await;
    let agent2 = open_as(&dir, "agent-2", port).await;
    let (_sub_steps, steps) = steps_heard(&leader, "formation/sec/estimate/2").await;
    let (p, matched) = matched_publisher(&agent2, "formation/sec/estimate/2", Duration::from_secs(10)).await;
    for k in 0..100 {
        p.put(estimate(2, k)).await.expect("put");
    }
    let control = settle(&heard, 100, Duration::from_secs(5)).await;
    assert_eq!(
        control,
        100,
        "the genuine agent 2's 100 estimates: {control} reached the leader (matched its subscriber: {matched}; lost: \
         {})",
        lost_steps(&steps, 100)
    );
    drop(p);
    steps.lock().unwrap().clear();
    heard.store(0, Ordering::Relaxed);

    let ca = dir.join("ca/ca.pem").display().to_string();
    let no_cert = ZenohArgs {
        connect: vec![format!("tls/127.0.0.1:{port}")],
        config: Some(rogue_config(
            tmp.path(),
            "no-cert",
            &format!("transport: {{ link: {{ tls: {{ root_ca_certificate: {ca:?} }} }} }}"),
        )),
        ..client(port)
    };
    let foreign_ca = ZenohArgs {
        tls: Some(other.clone()),
        identity: Some("agent-2".into()),
        config: Some(rogue_config(tmp.path(), "foreign", "")),
        ..client(port)
    };
    let plain_tcp = ZenohArgs { config: Some(rogue_config(tmp.path(), "tcp", "")), ..client(port) };
    // The authority's own certificate for agent 2, expired, given to zenoh
    // directly (our start-up check would refuse it before dialling).
    let expired = reissued(tmp.path(), &dir, "expired", &["--not-before", "2020-01-01", "--days", "30"]);
    let raw_tls = |name: &str, certs: &Path| {
        let (cert, key) =
            (certs.join("agent-2.pem").display().to_string(), certs.join("agent-2.key").display().to_string());
        // `certs` is agent 2's own folder.
        ZenohArgs {
            connect: vec![format!("tls/127.0.0.1:{port}")],
            config: Some(rogue_config(
                tmp.path(),
                name,
                &format!(
                    "transport: {{ link: {{ tls: {{ root_ca_certificate: {ca:?}, connect_certificate: {cert:?}, \
                     connect_private_key: {key:?}, enable_mtls: true }} }} }}"
                ),
            )),
            ..client(port)
        }
    };
    // Control: the same raw configuration with the valid certificate connects.
    let (opened, sent) = rogue(&raw_tls("valid", &dir.join("agent-2"))).await;
    let got = settle(&heard, 1000, Duration::from_secs(5)).await;
    assert!(
        opened && got == 1000,
        "the raw TLS configuration with agent 2's valid certificate: opened {opened}, {sent} sent, {got} arrived \
         (lost: {})",
        lost_steps(&steps, 1000)
    );
    heard.store(0, Ordering::Relaxed);
    let expired_cert = raw_tls("expired", &expired.join("agent-2"));
    // Agent 2's previous certificate, revoked when it was issued a new one
    // (before the router started), given to zenoh directly.
    let revoked_cert = raw_tls("revoked", &revoked2);
    for (what, args) in [
        ("no certificate", no_cert),
        ("a certificate from another authority", foreign_ca),
        ("plain TCP", plain_tcp),
        ("an expired certificate of the authority", expired_cert),
        ("a revoked certificate of the authority", revoked_cert),
    ] {
        let (opened, sent) = rogue(&args).await;
        let got = settle(&heard, 1, Duration::from_millis(500)).await;
        assert_eq!(
            got, 0,
            "a session with {what} (opened: {opened}, {sent} puts returned Ok): {got} of its messages reached the leader"
        );
        assert!(!opened, "a session with {what} opened a session with the TLS router ({sent} puts returned Ok)");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_valid_agent_cannot_speak_for_another_node() {
    let (_tmp, dir, port, _router) = tls_router();
    // Receivers: follower 1 (hears the leader and follower 2... and may
    // receive estimates 0 and its neighbours'), follower 4 (a neighbour of
    // follower 3), the monitor (telemetry).
    let f1 = open_as(&dir, "agent-1", port).await;
    let (_s1, f1_heard) = counter(&f1, "formation/sec/estimate/0").await;
    let f4 = open_as(&dir, "agent-4", port).await;
    let (_s4, f4_heard) = counter(&f4, "formation/sec/estimate/3").await;
    let monitor = open_as(&dir, "monitor", port).await;
    let (_sm, mon_heard) = counter(&monitor, "formation/sec/telemetry/*").await;
    let forger = open_as(&dir, "agent-2", port).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut sent = 0u64;
    for k in 0..10_000u64 {
        for (key, sender) in [("formation/sec/estimate/3", 3), ("formation/sec/estimate/0", 0)] {
            if forger.put(key, estimate(sender, k)).await.is_ok() {
                sent += 1;
            }
        }
        if k % 10 == 0 && forger.put("formation/sec/telemetry/3", vec![0u8; 64]).await.is_ok() {
            sent += 1;
        }
    }
    // A positive control through the same router: the genuine follower 3.
    let f3 = open_as(&dir, "agent-3", port).await;
    let (p3, _) = matched_publisher(&f3, "formation/sec/estimate/3", Duration::from_secs(10)).await;
    for k in 0..50 {
        p3.put(estimate(3, k)).await.expect("put");
    }
    let control = settle(&f4_heard, 50, Duration::from_secs(5)).await;
    let (a, b, c) = (f1_heard.load(Ordering::Relaxed), control.saturating_sub(50), mon_heard.load(Ordering::Relaxed));
    assert_eq!(
        (a, b, c),
        (0, 0, 0),
        "agent 2 sent {sent} forged messages: {a} of its leader estimates reached follower 1, {b} of its follower-3 \
         estimates follower 4, {c} of its follower-3 telemetry the monitor"
    );
    assert_eq!(control, 50, "the genuine follower 3's 50 estimates: {control} reached follower 4");
}

/// A copy of `dir` where agent 2's certificate is re-issued with the given
/// validity (same authority).
fn reissued(tmp: &Path, dir: &Path, name: &str, extra: &[&str]) -> PathBuf {
    let copy = tmp.join(name);
    copy_dir(dir, &copy);
    let mut args = vec!["--node", "agent-2"];
    args.extend_from_slice(extra);
    let o = common::certs_with(&copy, &args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    copy
}

/// A copy of a folder and its folders.
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("mkdir");
    for e in std::fs::read_dir(from).expect("read_dir").flatten() {
        if e.file_type().expect("type").is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).expect("copy");
        }
    }
}

/// `formation node agent --id 2 --tls DIR` against a port nobody listens
/// on: its status and stderr (it must fail before it dials).
fn agent2(dir: &Path) -> (Option<i32>, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["node", "agent", "--id", "2", "--scenario", SCENARIO, "--mode", "client"])
        .args(["--connect", &format!("tcp/127.0.0.1:{}", Ports::free(1).release()), "--open-timeout", "3", "--tls"])
        .arg(dir)
        .output()
        .expect("agent");
    (o.status.code(), String::from_utf8_lossy(&o.stderr).trim().to_string())
}

#[test]
fn expired_not_yet_valid_missing_and_wrong_files_are_one_line_and_exit_2() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let expired = reissued(tmp.path(), &dir, "expired", &["--not-before", "2020-01-01", "--days", "30"]);
    let future = reissued(tmp.path(), &dir, "future", &["--not-before", "2099-01-01"]);
    let wrong_node = reissued(tmp.path(), &dir, "wrong-node", &[]);
    std::fs::copy(dir.join("agent-1/agent-1.pem"), wrong_node.join("agent-2/agent-2.pem")).expect("copy");
    let wrong_key = reissued(tmp.path(), &dir, "wrong-key", &[]);
    std::fs::copy(dir.join("agent-1/agent-1.key"), wrong_key.join("agent-2/agent-2.key")).expect("copy");
    let foreign = tmp.path().join("foreign");
    common::certs(&foreign);
    let mixed = reissued(tmp.path(), &dir, "mixed", &[]);
    std::fs::copy(foreign.join("agent-2/agent-2.pem"), mixed.join("agent-2/agent-2.pem")).expect("copy");
    std::fs::copy(foreign.join("agent-2/agent-2.key"), mixed.join("agent-2/agent-2.key")).expect("copy");
    let no_key = reissued(tmp.path(), &dir, "no-key", &[]);
    std::fs::remove_file(no_key.join("agent-2/agent-2.key")).expect("rm");
    let garbage = reissued(tmp.path(), &dir, "garbage", &[]);
    std::fs::write(garbage.join("agent-2/agent-2.pem"), "not a certificate").expect("write");
    let no_policy = reissued(tmp.path(), &dir, "no-policy", &[]);
    std::fs::remove_file(no_policy.join("agent-2/policy.json5")).expect("rm");
    let other_topology = reissued(tmp.path(), &dir, "other-topology", &[]);
    std::fs::write(other_topology.join("agent-2/policy.json5"), "{ enabled: true, default_permission: \"allow\" }")
        .expect("w");
    // The attack of the issue: the policy switched off in a node's copy.
    let disabled = reissued(tmp.path(), &dir, "disabled", &[]);
    let text = std::fs::read_to_string(disabled.join("agent-2/policy.json5")).expect("policy");
    std::fs::write(disabled.join("agent-2/policy.json5"), text.replacen("\"enabled\": true", "\"enabled\": false", 1))
        .expect("w");
    let unsigned = reissued(tmp.path(), &dir, "unsigned", &[]);
    std::fs::remove_file(unsigned.join("agent-2/policy.pem")).expect("rm");
    let forged_signature = reissued(tmp.path(), &dir, "forged-signature", &[]);
    std::fs::copy(foreign.join("agent-2/policy.pem"), forged_signature.join("agent-2/policy.pem")).expect("copy");
    let revoked = tmp.path().join("revoked");
    copy_dir(&dir, &revoked);
    let o = common::certs_with(&revoked, &["--revoke", "agent-2"]);
    assert!(o.status.success(), "--revoke: {}", String::from_utf8_lossy(&o.stderr));
    // A folder in the layout of the previous `formation certs` (flat, ca.key beside the nodes' files).
    let old_layout = tmp.path().join("old-layout");
    copy_dir(&dir.join("agent-2"), &old_layout);
    std::fs::copy(dir.join("ca/ca.key"), old_layout.join("ca.key")).expect("copy");
    std::fs::remove_file(old_layout.join("policy.pem")).expect("rm");
    let cases: [(&str, &Path, &str); 15] = [
        ("expired", &expired, "expired on"),
        ("not yet valid", &future, "not valid yet"),
        ("another node's certificate", &wrong_node, "is the certificate of \"agent-1\""),
        ("another node's key", &wrong_key, "is not the key of"),
        ("another authority", &mixed, "was not issued by the authority"),
        ("no key", &no_key, "cannot read"),
        ("garbage", &garbage, "not a PEM certificate"),
        ("no policy", &no_policy, "policy.json5"),
        ("a policy for another topology", &other_topology, "not the file the authority signed"),
        ("a policy switched off", &disabled, "agent-2/policy.json5 is refused"),
        ("a policy without its signature", &unsigned, "policy.pem"),
        ("a policy signed by another authority", &forged_signature, "not the authority's signature"),
        ("a revoked certificate", &revoked, "was revoked on"),
        ("the previous layout", &old_layout, "older `formation certs`"),
        ("no folder", &tmp.path().join("absent"), "cannot read"),
    ];
    for (what, d, says) in cases {
        let (code, err) = agent2(d);
        assert_eq!(code, Some(2), "{what}: exit {code:?}, said {err:?}");
        assert_eq!(err.lines().count(), 1, "{what}: not one line: {err:?}");
        assert!(err.contains(says), "{what}: {err:?} does not say {says:?}");
    }
    // launch checks every node before it starts any.
    let out = tmp.path().join("run");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["launch", SCENARIO, "-q", "--base-port", &Ports::free(LAUNCH_PORTS).release().to_string(), "--tls"])
        .arg(&expired)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("launch");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "launch with an expired agent-2: {err}");
    assert!(err.contains("agent-2.pem expired on"), "{err}");
    assert!(!out.exists() && !tmp.path().join("run.partial").exists(), "launch left a run folder behind");
}

/// Peer links never pass a router: each peer enforces the policy itself.
/// Follower 4 as a TLS peer; agent 2's valid identity dials it directly and
/// publishes on agent 3's key; the genuine follower 3 does the same.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_refuses_a_valid_agent_speaking_for_another() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let port = Ports::free(1).release();
    let peer = |name: &str, listen: Vec<String>, connect: Vec<String>| ZenohArgs {
        mode: Some(ZenohMode::Peer),
        listen,
        connect,
        tls: Some(dir.clone()),
        identity: Some(name.into()),
        ..Default::default()
    };
    let open = |a: ZenohArgs| async move {
        tokio::time::timeout(Duration::from_secs(20), session::open(&a)).await.expect("open in 20 s").expect("open")
    };
    let f4 = open(peer("agent-4", vec![format!("tcp/127.0.0.1:{port}")], vec![])).await;
    let (_s4, heard) = counter(&f4, "formation/sec/estimate/3").await;
    let forger = open(peer("agent-2", vec![], vec![format!("tcp/127.0.0.1:{port}")])).await;
    let f3 = open(peer("agent-3", vec![], vec![format!("tcp/127.0.0.1:{port}")])).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut sent = 0u64;
    for k in 0..10_000 {
        if forger.put("formation/sec/estimate/3", estimate(3, k)).await.is_ok() {
            sent += 1;
        }
    }
    let forged = settle(&heard, 1, Duration::from_millis(500)).await;
    for k in 0..50 {
        f3.put("formation/sec/estimate/3", estimate(3, k)).await.expect("put");
    }
    let genuine = settle(&heard, forged + 50, Duration::from_secs(5)).await - forged;
    assert_eq!(forged, 0, "agent 2 put {sent} estimates on agent 3's key to peer agent 4: {forged} arrived");
    assert_eq!(genuine, 50, "the genuine follower 3's 50 estimates to peer agent 4: {genuine} arrived");
}
