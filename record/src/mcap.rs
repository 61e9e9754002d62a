//! `run.mcap`: a run folder's samples as an MCAP recording (issue 13), so
//! that Foxglove and the `mcap` tools and libraries open a run directly.
//!
//! Written from the folder's CSVs when the folder is finished, so it holds
//! exactly their rows (one message per row and channel, the same numbers)
//! and costs nothing while the run steps. Messages are JSON with a JSON
//! schema; log and publish times are run time (t = 0 at step 0), in ns.
//!
//! | topic | schema | one message per |
//! | --- | --- | --- |
//! | `/leader/pose`, `/follower_<id>/pose` | `foxglove.PoseInFrame` (frame `world`) | CSV row |
//! | `/follower_<id>/estimate` | `foxglove.PoseInFrame`: its estimate of the leader's pose | CSV row |
//! | `/leader/state` | `formation.LeaderState`: `leader.csv`'s columns | CSV row |
//! | `/follower_<id>/state` | `formation.FollowerState`: `follower_<id>.csv`'s columns | CSV row |
//! | `/network/events` | `formation.NetworkEvent` (`network.json`'s timelines) | event |
//! | `/network/links` | `formation.LinkStats`: a link's one-way latency and age at use (`network.json`) | receiver and source, at the run's end |
//! | `/network/clocks` | `formation.ClockEstimate`: a node's estimate of the leader's clock (`network.json`) | node, at the run's end |
//! | `/hearing` | `formation.Heard`: which step's message a follower used of a source (`hearing.bin`) | change of a link's hearing |

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use mcap::records::MessageHeader;
use serde_json::{json, Value};

/// The file's name in a run folder.
pub const FILE: &str = "run.mcap";

fn err(e: impl std::fmt::Display) -> std::io::Error {
    std::io::Error::other(format!("{FILE}: {e}"))
}

pub const POSE_IN_FRAME: &str = r#"{"title":"foxglove.PoseInFrame","type":"object","properties":{
"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},
"frame_id":{"type":"string"},
"pose":{"type":"object","properties":{
"position":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},
"orientation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}}}}}"#;

pub const EVENT: &str = r#"{"title":"formation.NetworkEvent","type":"object","properties":{
"node":{"type":"string"},"t":{"type":"number"},"event":{"type":"string"}}}"#;

pub const LINK: &str = r#"{"title":"formation.LinkStats","type":"object","properties":{
"node":{"type":"string"},"source":{"type":"integer"},"messages":{"type":"integer"},
"latency_us":{"type":"array","items":{"type":"integer"},"description":"p50, p99, max"},
"uses":{"type":"integer"},"age_steps":{"type":"array","items":{"type":"integer"},"description":"p50, p99, max"}}}"#;

pub const CLOCK: &str = r#"{"title":"formation.ClockEstimate","type":"object","properties":{
"node":{"type":"string"},"offset_ms":{"type":"number"},"uncertainty_us":{"type":"number"},
"drift_ppm":{"type":"number"},"exchanges":{"type":"integer"},"steps":{"type":"integer"}}}"#;

/// A JSON schema of one object with a number per column.
pub fn columns_schema(title: &str, columns: &[&str]) -> String {
    let props: serde_json::Map<String, Value> =
        columns.iter().map(|c| (c.to_string(), json!({"type": ["number", "null"]}))).collect();
    json!({"title": title, "type": "object", "properties": props}).to_string()
}

/// The column names of a header [`crate::row`] writes.
pub fn names(header: &'static str) -> Vec<&'static str> {
    header.trim_end().split(',').collect()
}

/// A run-folder CSV's columns `names`, or None when the file is absent.
fn read(path: &Path, names: &[&str]) -> std::io::Result<Option<Vec<Vec<f64>>>> {
    if !path.exists() {
        return Ok(None);
    }
    crate::columns::read_columns(path, names).map(Some).map_err(err)
}

/// The index of a column the record's header has.
fn column(names: &[&str], name: &str) -> std::io::Result<usize> {
    names.iter().position(|n| *n == name).ok_or_else(|| err(format_args!("no column {name}")))
}

/// Run time t (s) as ns, and as Foxglove's {sec, nsec}.
pub fn stamp(t: f64) -> (u64, Value) {
    let ns = (t.max(0.0) * 1e9).round() as u64;
    (ns, json!({"sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000}))
}

pub fn pose_in_frame(stamp: &Value, x: f64, y: f64, theta: f64) -> Value {
    let (s, c) = (theta / 2.0).sin_cos();
    json!({
        "timestamp": stamp,
        "frame_id": "world",
        "pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": s, "w": c}},
    })
}

/// Row `r` of `columns` as one JSON object, by column name.
fn row_object(names: &[&str], columns: &[Vec<f64>], r: usize) -> Value {
    Value::Object(names.iter().zip(columns).map(|(n, c)| (n.to_string(), json!(c[r]))).collect())
}

struct Out<W: Write + std::io::Seek> {
    w: mcap::Writer<W>,
    sequence: BTreeMap<u16, u32>,
}

impl<W: Write + std::io::Seek> Out<W> {
    fn channel(&mut self, topic: &str, schema: &str, data: &str) -> std::io::Result<u16> {
        let id = self.w.add_schema(schema, "jsonschema", data.as_bytes()).map_err(err)?;
        self.w.add_channel(id, topic, "json", &BTreeMap::new()).map_err(err)
    }

    fn put(&mut self, channel: u16, ns: u64, v: &Value) -> std::io::Result<()> {
        let seq = self.sequence.entry(channel).or_insert(0);
        *seq += 1;
        let header = MessageHeader { channel_id: channel, sequence: *seq, log_time: ns, publish_time: ns };
        self.w.write_to_known_channel(&header, v.to_string().as_bytes()).map_err(err)
    }
}

/// Writes `dir/run.mcap` from the CSVs (and `network.json`, if any) in `dir`
/// for the followers `ids`.
pub fn write(dir: &Path, ids: &[u32]) -> std::io::Result<()> {
    let path = dir.join(FILE);
    let file = File::create(&path).map_err(|e| err(format_args!("creating {}: {e}", path.display())))?;
    let w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .profile("")
        .library(concat!("formation ", env!("CARGO_PKG_VERSION")))
        .create(BufWriter::new(file))
        .map_err(err)?;
    let mut out = Out { w, sequence: BTreeMap::new() };
    // The run's last time, for what network.json says of the whole run.
    let mut t_end = 0.0f64;

    let names = self::names(crate::row::LEADER_HEADER);
    if let Some(cols) = read(&dir.join("leader.csv"), &names)? {
        let schema = columns_schema("formation.LeaderState", &names);
        let pose = out.channel("/leader/pose", "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let state = out.channel("/leader/state", "formation.LeaderState", &schema)?;
        let c = |n: &str| column(&names, n).map(|i| &cols[i]);
        let (t, x, y, th) = (c("t")?, c("x")?, c("y")?, c("theta")?);
        t_end = t.last().copied().unwrap_or(0.0);
        for r in 0..t.len() {
            let (ns, st) = stamp(t[r]);
            out.put(pose, ns, &pose_in_frame(&st, x[r], y[r], th[r]))?;
            out.put(state, ns, &row_object(&names, &cols, r))?;
        }
    }
    let names = self::names(crate::row::FOLLOWER_HEADER);
    for id in ids {
        let Some(cols) = read(&dir.join(format!("follower_{id}.csv")), &names)? else { continue };
        let schema = columns_schema("formation.FollowerState", &names);
        let pose = out.channel(&format!("/follower_{id}/pose"), "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let estimate = out.channel(&format!("/follower_{id}/estimate"), "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let state = out.channel(&format!("/follower_{id}/state"), "formation.FollowerState", &schema)?;
        let c = |n: &str| column(&names, n).map(|i| &cols[i]);
        let (t, x, y, th) = (c("t")?, c("x")?, c("y")?, c("theta")?);
        let (xe, ye, the) = (c("x_ir")?, c("y_ir")?, c("theta_ir")?);
        for r in 0..t.len() {
            let (ns, st) = stamp(t[r]);
            out.put(pose, ns, &pose_in_frame(&st, x[r], y[r], th[r]))?;
            out.put(estimate, ns, &pose_in_frame(&st, xe[r], ye[r], the[r]))?;
            out.put(state, ns, &row_object(&names, &cols, r))?;
        }
    }
    if let Ok(text) = std::fs::read_to_string(dir.join("network.json")) {
        let network: Value = serde_json::from_str(&text).unwrap_or(Value::Null);
        let mut events: Vec<(f64, String, String)> = Vec::new();
        if let Some(nodes) = network["nodes"].as_object() {
            for (node, n) in nodes {
                for e in n["timeline"].as_array().into_iter().flatten() {
                    let t = e["t"].as_f64().unwrap_or(0.0);
                    let what = e["event"].as_str().map_or_else(|| e["event"].to_string(), str::to_string);
                    events.push((t, node.clone(), what));
                }
            }
        }
        if !events.is_empty() {
            events.sort_by(|a, b| a.0.total_cmp(&b.0));
            let ch = out.channel("/network/events", "formation.NetworkEvent", EVENT)?;
            for (t, node, what) in events {
                let (ns, _) = stamp(t);
                out.put(ch, ns, &json!({"node": node, "t": t, "event": what}))?;
            }
        }
        // What network.json says of each node for the whole run, stamped
        // at its end, each object with its node's name.
        let (ns, _) = stamp(t_end);
        let named = |node: &String, v: &Value| {
            let mut v = v.clone();
            v["node"] = json!(node);
            v
        };
        let nodes: Vec<(&String, &Value)> = network["nodes"].as_object().into_iter().flatten().collect();
        let links: Vec<Value> = nodes
            .iter()
            .flat_map(|(node, n)| n["links"].as_array().into_iter().flatten().map(|l| named(node, l)))
            .collect();
        let clocks: Vec<Value> =
            nodes.iter().filter(|(_, n)| n["clock"].is_object()).map(|(node, n)| named(node, &n["clock"])).collect();
        for (topic, title, schema, items) in [
            ("/network/links", "formation.LinkStats", LINK, links),
            ("/network/clocks", "formation.ClockEstimate", CLOCK, clocks),
        ] {
            if !items.is_empty() {
                let ch = out.channel(topic, title, schema)?;
                for v in &items {
                    out.put(ch, ns, v)?;
                }
            }
        }
    }
    hearing(dir, &mut out)?;
    out.w.finish().map_err(err)?;
    Ok(())
}

pub const HEARD: &str = r#"{"title":"formation.Heard","type":"object","properties":{
"follower":{"type":"integer"},"source":{"type":"integer","description":"0: the leader"},
"t":{"type":"number"},"k":{"type":"integer"},"heard":{"type":"string","description":"age N, silent or removed"},
"age":{"type":["integer","null"],"description":"steps between the message used and the step"}}}"#;

/// `/hearing`: from the run folder's hearing record, one message each time
/// what a follower heard of a source changed (`formation replay`'s input).
fn hearing<W: Write + std::io::Seek>(dir: &Path, out: &mut Out<W>) -> std::io::Result<()> {
    let Ok(record) = crate::hearing::HearingRecord::read(dir) else { return Ok(()) };
    let dt = std::fs::read_to_string(dir.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<Value>(&t).ok())
        .and_then(|v| v["dt"].as_f64())
        .unwrap_or(f64::NAN);
    if !dt.is_finite() {
        return Ok(());
    }
    let mut changes: Vec<(u64, Value)> = Vec::new();
    for f in &record.followers {
        for seg in &f.segments {
            for (slot, runs) in seg.heard.slots.iter().enumerate() {
                let mut k = seg.first_k;
                for &(code, n) in runs {
                    let h = crate::hearing::Heard::from_code(code);
                    let age = match h {
                        crate::hearing::Heard::Age(a) => json!(a),
                        _ => Value::Null,
                    };
                    let t = k as f64 * dt;
                    let v = json!({"follower": f.id, "source": f.sources.get(slot), "t": t, "k": k, "heard": h.describe(), "age": age});
                    changes.push((k, v));
                    k += u64::from(n);
                }
            }
        }
    }
    if changes.is_empty() {
        return Ok(());
    }
    changes.sort_by_key(|c| c.0);
    let ch = out.channel("/hearing", "formation.Heard", HEARD)?;
    for (k, v) in changes {
        let (ns, _) = stamp(k as f64 * dt);
        out.put(ch, ns, &v)?;
    }
    Ok(())
}
