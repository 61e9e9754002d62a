//! `--foxglove`: the run live over the Foxglove WebSocket protocol (free
//! ports on 127.0.0.1, see `common::Ports`), read by a client of our own that speaks
//! the protocol as Foxglove does (subprotocol `foxglove.sdk.v1`, JSON
//! advertise and subscribe, binary message frames), and compared with the
//! run folder the monitor wrote.

use crate::common;

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use common::{Group, SCENARIO};
use futures_util::{SinkExt, StreamExt};
use serde_json::{json, Value};
use tokio_tungstenite::tungstenite::{client::IntoClientRequest, Message};

/// The CSV `name` of a run folder as rows of numbers, by column name.
fn csv(dir: &Path, name: &str) -> (Vec<String>, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(dir.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().expect("header").split(',').map(str::to_string).collect();
    let rows = lines.map(|l| l.split(',').map(|x| x.parse::<f64>().expect("number")).collect()).collect();
    (header, rows)
}

/// One message frame: (subscription id, log time in ns, JSON payload).
fn message_frame(bytes: &[u8]) -> Option<(u32, u64, Value)> {
    if bytes.len() < 13 || bytes[0] != 1 {
        return None;
    }
    let sub = u32::from_le_bytes(bytes[1..5].try_into().ok()?);
    let ns = u64::from_le_bytes(bytes[5..13].try_into().ok()?);
    Some((sub, ns, serde_json::from_slice(&bytes[13..]).ok()?))
}

type Socket = tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// Connects as Foxglove does, retrying until `g`'s server listens.
async fn connect(addr: &str, g: &mut Group) -> Socket {
    let t0 = Instant::now();
    loop {
        let mut req = format!("ws://{addr}").into_client_request().expect("request");
        req.headers_mut().insert("sec-websocket-protocol", "foxglove.sdk.v1".parse().expect("header"));
        match tokio_tungstenite::connect_async(req).await {
            Ok((ws, _)) => return ws,
            Err(e) => {
                assert!(t0.elapsed() < common::LIMIT, "no Foxglove server at {addr} within {:?}: {e}", common::LIMIT);
                assert!(g.0.try_wait().expect("try_wait").is_none(), "it ended before its Foxglove server was reached");
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn foxglove_sees_the_channels_of_a_lockstep_run_as_recorded_and_the_run_still_equals_the_simulator() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let sets = ["duration=20"];
    let port = common::Ports::free(1).release();
    let addr = format!("127.0.0.1:{port}");
    let base = common::Ports::free(common::LAUNCH_PORTS).release().to_string();
    let mut g = Group::launch(
        &out,
        &sets,
        &["--base-port", &base, "--run", "fox-ls", "--foxglove", &addr, "--web-linger", "2"],
    );

    let mut ws = connect(&addr, &mut g).await;

    // serverInfo, then the channels.
    let mut channels: BTreeMap<String, Value> = BTreeMap::new();
    let mut server_info = Value::Null;
    let expected: Vec<String> = ["/leader/pose", "/leader/state", "/network/events"]
        .into_iter()
        .map(str::to_string)
        .chain((1..=4).flat_map(|i| ["pose", "estimate", "state"].map(|c| format!("/follower_{i}/{c}"))))
        .collect();
    while channels.len() < expected.len() {
        let m = tokio::time::timeout(Duration::from_secs(20), ws.next())
            .await
            .expect("no advertise within 20 s")
            .expect("the server closed the connection")
            .expect("websocket");
        if let Message::Text(text) = m {
            let v: Value = serde_json::from_str(text.as_str()).expect("JSON");
            match v["op"].as_str() {
                Some("serverInfo") => server_info = v,
                Some("advertise") => {
                    for c in v["channels"].as_array().expect("channels") {
                        channels.insert(c["topic"].as_str().expect("topic").to_string(), c.clone());
                    }
                }
                _ => {}
            }
        }
    }
    assert!(server_info["name"].as_str().is_some_and(|n| n.contains("fox-ls")), "serverInfo: {server_info}");
    let mut topics: Vec<String> = channels.keys().cloned().collect();
    topics.sort();
    let mut want = expected.clone();
    want.sort();
    assert_eq!(topics, want, "the advertised channels");
    for (topic, c) in &channels {
        assert_eq!(c["encoding"], "json", "{topic}: {c}");
        assert_eq!(c["schemaEncoding"], "jsonschema", "{topic}: {c}");
        if topic.ends_with("/pose") || topic.ends_with("/estimate") {
            assert_eq!(c["schemaName"], "foxglove.PoseInFrame", "{topic}: {c}");
        }
    }

    // Subscribe to a follower's every column, the leader's pose and a follower's pose.
    let watched = ["/follower_1/state", "/leader/pose", "/follower_3/pose"];
    let subscriptions: Vec<Value> =
        watched.iter().enumerate().map(|(i, t)| json!({"id": i + 1, "channelId": channels[*t]["id"]})).collect();
    ws.send(Message::text(json!({"op": "subscribe", "subscriptions": subscriptions}).to_string()))
        .await
        .expect("subscribe");

    // Everything until the server closes (after the run and its linger).
    let mut got: Vec<Vec<(u64, Value)>> = vec![Vec::new(); watched.len()];
    let t1 = Instant::now();
    loop {
        assert!(t1.elapsed() < Duration::from_secs(180), "the Foxglove stream did not end within 180 s");
        match tokio::time::timeout(Duration::from_secs(30), ws.next()).await {
            Ok(Some(Ok(Message::Binary(b)))) => {
                let (sub, ns, v) = message_frame(&b).unwrap_or_else(|| panic!("a malformed frame: {b:?}"));
                got[sub as usize - 1].push((ns, v));
            }
            Ok(Some(Ok(Message::Close(_)))) | Ok(None) | Ok(Some(Err(_))) => break,
            Ok(Some(Ok(_))) => {}
            Err(_) => panic!("nothing from the Foxglove server for 30 s"),
        }
    }
    let status = g.wait(Duration::from_secs(60));
    assert!(status.success(), "formation launch --foxglove failed: {status}");

    // What Foxglove received is what the run recorded at that step.
    let last_k = 20_000u64;
    let (names, f1) = csv(&out, "follower_1.csv");
    let (_, leader) = csv(&out, "leader.csv");
    let (_, f3) = csv(&out, "follower_3.csv");
    let counts: Vec<usize> = got.iter().map(Vec::len).collect();
    eprintln!("foxglove_live: messages received per subscription {watched:?}: {counts:?}");
    for (i, msgs) in got.iter().enumerate() {
        // Subscribed mid-run: at least a second of run time at 50 per second.
        assert!(msgs.len() >= 50, "{}: only {} messages", watched[i], msgs.len());
        let mut prev = None;
        for (ns, _) in msgs {
            let k = (*ns as f64 * 1e-6).round() as u64;
            assert_eq!(*ns, k * 1_000_000, "{}: log time {ns} ns is not a step's run time", watched[i]);
            assert!(
                k % 20 == 0 || k == last_k,
                "{}: step {k} is not one of the thinned steps (every 20th)",
                watched[i]
            );
            assert!(prev.is_none_or(|p| k > p), "{}: step {k} after step {prev:?}", watched[i]);
            prev = Some(k);
        }
        assert_eq!(prev, Some(last_k), "{}: the final step was not sent", watched[i]);
    }
    for (ns, v) in &got[0] {
        let k = (*ns / 1_000_000) as usize;
        for (c, name) in names.iter().enumerate() {
            let sent = v[name].as_f64().unwrap_or_else(|| panic!("/follower_1/state at step {k}: no {name}: {v}"));
            assert_eq!(sent, f1[k][c], "/follower_1/state at step {k}: {name} sent {sent}, recorded {}", f1[k][c]);
        }
    }
    let pose_matches = |v: &Value, row: &[f64]| {
        let p = &v["pose"]["position"];
        let q = &v["pose"]["orientation"];
        p["x"].as_f64() == Some(row[1])
            && p["y"].as_f64() == Some(row[2])
            && (q["z"].as_f64().unwrap_or(f64::NAN) - (row[3] / 2.0).sin()).abs() < 1e-12
            && v["frame_id"] == "world"
    };
    for (ns, v) in &got[1] {
        let k = (*ns / 1_000_000) as usize;
        assert!(pose_matches(v, &leader[k]), "/leader/pose at step {k}: sent {v}, recorded {:?}", &leader[k][..4]);
    }
    for (ns, v) in &got[2] {
        let k = (*ns / 1_000_000) as usize;
        assert!(pose_matches(v, &f3[k]), "/follower_3/pose at step {k}: sent {v}, recorded {:?}", &f3[k][..4]);
    }

    // A viewer did not disturb the run: byte for byte the simulator's.
    common::assert_equals_the_simulator(&out, &tmp.path().join("sim"), &sets, "the lock-step run watched in Foxglove");
    g.assert_group_empty();
    plays_again_to_foxglove(&out).await;
}

/// `formation play RUN_DIR --foxglove` (issue 25): the finished
/// run played again at 10× from its hearing record; what Foxglove receives
/// of follower 1 is its recorded rows, step by step, to the final step.
async fn plays_again_to_foxglove(out: &Path) {
    let addr = format!("127.0.0.1:{}", common::Ports::free(1).release());
    let run = out.display().to_string();
    let mut g = Group::spawn(&["play", &run, "--foxglove", &addr, "--speed", "10", "--linger", "0"]);
    let mut ws = connect(&addr, &mut g).await;
    let channel = loop {
        let m = tokio::time::timeout(Duration::from_secs(20), ws.next()).await.expect("advertise").expect("open");
        if let Ok(Message::Text(text)) = m {
            let v: Value = serde_json::from_str(text.as_str()).expect("JSON");
            let found = v["channels"].as_array().into_iter().flatten().find(|c| c["topic"] == "/follower_1/state");
            if let Some(c) = found {
                break c["id"].clone();
            }
        }
    };
    ws.send(Message::text(json!({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel}]}).to_string()))
        .await
        .expect("subscribe");
    let mut got = Vec::new();
    loop {
        match tokio::time::timeout(Duration::from_secs(30), ws.next()).await {
            Ok(Some(Ok(Message::Binary(b)))) => got.extend(message_frame(&b)),
            Ok(Some(Ok(Message::Close(_)))) | Ok(None) | Ok(Some(Err(_))) => break,
            Ok(Some(Ok(_))) => {}
            Err(_) => panic!("nothing from the Foxglove playback for 30 s"),
        }
    }
    assert!(g.wait(Duration::from_secs(60)).success(), "formation play --foxglove failed");
    let (names, f1) = csv(out, "follower_1.csv");
    // 20 s at 10×: 2 s of wall time, at up to 50 messages per run second.
    assert!(got.len() >= 200, "only {} messages of /follower_1/state in the playback", got.len());
    for (_, ns, v) in &got {
        let k = (*ns / 1_000_000) as usize;
        for (c, name) in names.iter().enumerate() {
            assert_eq!(v[name].as_f64(), Some(f1[k][c]), "played /follower_1/state at step {k}: {name}: {v}");
        }
    }
    assert_eq!(got.last().map(|m| m.1), Some(20_000_000_000), "the final step was not played");
    eprintln!("foxglove playback: {} messages of /follower_1/state, every one the recorded row", got.len());

    // Ctrl-C and SIGTERM end a playback at once, 130 and 143, and leave no
    // scratch folder (Ctrl-C waited for the playback's end and said 0).
    for (signal, code) in [("-INT", 130), ("-TERM", 143)] {
        let addr = format!("127.0.0.1:{}", common::Ports::free(1).release());
        let mut g = Group::spawn(&["play", &run, "--foxglove", &addr, "--speed", "0.1"]);
        let _ws = connect(&addr, &mut g).await;
        let pid = g.0.id();
        let sent = std::process::Command::new("kill").args([signal, &pid.to_string()]).status().expect("kill");
        assert!(sent.success());
        let status = g.wait(Duration::from_secs(10));
        assert_eq!(status.code(), Some(code), "playback after kill {signal}: {status}");
        let left: Vec<_> = std::fs::read_dir(std::env::temp_dir())
            .expect("tmp")
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().starts_with(&format!("formation-playback-{pid}-")))
            .map(|e| e.file_name())
            .collect();
        assert!(left.is_empty(), "playback after kill {signal} left {left:?}");
    }
}

#[test]
fn a_foxglove_address_that_cannot_be_used_gets_one_clear_line_and_no_folder() {
    // Held (listening) until the monitor has tried it.
    let taken = common::Ports::free(1);
    let addr = format!("127.0.0.1:{}", taken.base());
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["node", "monitor", "--scenario", SCENARIO, "--foxglove", &addr, "--open-timeout", "2"])
        .arg("--out")
        .arg(&out)
        .output()
        .expect("formation monitor");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "exit status; stderr: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(err.contains(&format!("--foxglove {addr}")), "stderr: {err}");
    drop(taken);
    let leftovers: Vec<_> = std::fs::read_dir(tmp.path()).expect("tmp").flatten().map(|e| e.file_name()).collect();
    assert!(leftovers.is_empty(), "a failed start left {leftovers:?}");

    // The lab's monitor lives in a namespace of its own: refused, in one
    // line, before anything listens (the address is only named).
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["lab", SCENARIO, "--foxglove", &addr])
        .output()
        .expect("formation lab");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "lab --foxglove: exit status; stderr: {err}");
    assert!(err.contains("--foxglove is not available in the lab"), "stderr: {err}");
}
