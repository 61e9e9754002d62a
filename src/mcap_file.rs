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

const POSE_IN_FRAME: &str = r#"{"title":"foxglove.PoseInFrame","type":"object","properties":{
"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},
"frame_id":{"type":"string"},
"pose":{"type":"object","properties":{
"position":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},
"orientation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}}}}}"#;

const EVENT: &str = r#"{"title":"formation.NetworkEvent","type":"object","properties":{
"node":{"type":"string"},"t":{"type":"number"},"event":{"type":"string"}}}"#;

/// A JSON schema of one object with a number per column.
fn columns_schema(title: &str, columns: &[&str]) -> String {
    let props: serde_json::Map<String, Value> =
        columns.iter().map(|c| (c.to_string(), json!({"type": ["number", "null"]}))).collect();
    json!({"title": title, "type": "object", "properties": props}).to_string()
}

/// A CSV file's header and its rows of numbers.
type Table = (Vec<String>, Vec<Vec<f64>>);

/// A CSV file's table, or None when it is absent.
fn read_csv(path: &Path) -> std::io::Result<Option<Table>> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(err(format_args!("reading {}: {e}", path.display()))),
    };
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().unwrap_or("").split(',').map(str::to_string).collect();
    let mut rows = Vec::new();
    for (n, line) in lines.enumerate() {
        let row: Result<Vec<f64>, _> = line.split(',').map(str::parse::<f64>).collect();
        let row = row.map_err(|e| err(format_args!("{} line {}: {e}", path.display(), n + 2)))?;
        if row.len() != header.len() {
            return Err(err(format_args!(
                "{} line {}: {} fields, header has {}",
                path.display(),
                n + 2,
                row.len(),
                header.len()
            )));
        }
        rows.push(row);
    }
    Ok(Some((header, rows)))
}

/// Run time t (s) as ns, and as Foxglove's {sec, nsec}.
fn stamp(t: f64) -> (u64, Value) {
    let ns = (t.max(0.0) * 1e9).round() as u64;
    (ns, json!({"sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000}))
}

fn pose_in_frame(stamp: &Value, x: f64, y: f64, theta: f64) -> Value {
    let (s, c) = (theta / 2.0).sin_cos();
    json!({
        "timestamp": stamp,
        "frame_id": "world",
        "pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": s, "w": c}},
    })
}

fn row_object(header: &[String], row: &[f64]) -> Value {
    Value::Object(header.iter().zip(row).map(|(h, v)| (h.clone(), json!(v))).collect())
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

    if let Some((header, rows)) = read_csv(&dir.join("leader.csv"))? {
        let cols: Vec<&str> = header.iter().map(String::as_str).collect();
        let pose = out.channel("/leader/pose", "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let state =
            out.channel("/leader/state", "formation.LeaderState", &columns_schema("formation.LeaderState", &cols))?;
        let at = |name: &str| header.iter().position(|h| h == name);
        let (t, x, y, th) = (at("t"), at("x"), at("y"), at("theta"));
        for row in &rows {
            let get = |i: Option<usize>| i.map_or(f64::NAN, |i| row[i]);
            let (ns, st) = stamp(get(t));
            out.put(pose, ns, &pose_in_frame(&st, get(x), get(y), get(th)))?;
            out.put(state, ns, &row_object(&header, row))?;
        }
    }
    for id in ids {
        let Some((header, rows)) = read_csv(&dir.join(format!("follower_{id}.csv")))? else { continue };
        let cols: Vec<&str> = header.iter().map(String::as_str).collect();
        let pose = out.channel(&format!("/follower_{id}/pose"), "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let estimate = out.channel(&format!("/follower_{id}/estimate"), "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let schema = columns_schema("formation.FollowerState", &cols);
        let state = out.channel(&format!("/follower_{id}/state"), "formation.FollowerState", &schema)?;
        let at = |name: &str| header.iter().position(|h| h == name);
        let idx = ["t", "x", "y", "theta", "x_ir", "y_ir", "theta_ir"].map(at);
        for row in &rows {
            let get = |i: Option<usize>| i.map_or(f64::NAN, |i| row[i]);
            let [t, x, y, th, xe, ye, the] = idx.map(get);
            let (ns, st) = stamp(t);
            out.put(pose, ns, &pose_in_frame(&st, x, y, th))?;
            out.put(estimate, ns, &pose_in_frame(&st, xe, ye, the))?;
            out.put(state, ns, &row_object(&header, row))?;
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
    }
    out.w.finish().map_err(err)?;
    Ok(())
}
