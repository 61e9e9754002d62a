//! `--foxglove ADDR`: the run live in Foxglove (issue 13). The monitor
//! serves the channels of `run.mcap` (`formation_record::mcap`) over the
//! Foxglove WebSocket protocol with the Foxglove SDK: same topics, same
//! schemas, same JSON messages, log time = run time. Open Foxglove, "Open
//! connection", Foxglove WebSocket, `ws://ADDR`.
//!
//! The live channels carry the rows as the monitor records them (in step
//! order per node), thinned to at most [`LIVE_HZ`] per channel and second
//! of run time (the final step always); `run.mcap` has every row. A message
//! is built only while some viewer subscribes to its channel, so the
//! server costs the monitor nothing when nobody watches, and the monitor is
//! on no control path: viewers cannot slow the run.
//!
//! The crate is built without its default features: no aws-lc (a C and
//! CMake build), no lz4, no derive macro; plain `ws://` only.

use formation_exit::Error;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use formation_leader::LeaderState;
use formation_scenario::Scenario;
use foxglove::{Context, PartialMetadata, RawChannel, Schema, WebSocketServerHandle};
use serde_json::json;

use formation_record::mcap::{columns_schema, names, pose_in_frame, stamp, EVENT, POSE_IN_FRAME};
use formation_record::{LiveSink, Row, FOLLOWER_HEADER, LEADER_HEADER};

/// At most this many messages per channel and second of run time.
pub const LIVE_HZ: f64 = 50.0;

/// A follower's channels.
struct FollowerChannels {
    pose: Arc<RawChannel>,
    estimate: Arc<RawChannel>,
    state: Arc<RawChannel>,
}

/// The live Foxglove server and the run's channels.
pub struct FoxgloveLive {
    /// The server holds only a weak reference to its context.
    _context: Arc<Context>,
    /// Taken to stop it.
    server: Mutex<Option<WebSocketServerHandle>>,
    port: u16,
    leader_pose: Arc<RawChannel>,
    leader_state: Arc<RawChannel>,
    followers: Vec<FollowerChannels>,
    events: Arc<RawChannel>,
    /// Send step k when k % every == 0 or k is the last step.
    every: u64,
    last_k: u64,
    dt_s: f64,
}

fn channel(ctx: &Arc<Context>, topic: &str, schema: &str, data: &str) -> Result<Arc<RawChannel>, Error> {
    ctx.channel_builder(topic)
        .message_encoding("json")
        .schema(Schema::new(schema.to_string(), "jsonschema", data.as_bytes().to_vec()))
        .build_raw()
        .map_err(|e| Error::Input(format!("foxglove channel {topic}: {e}")))
}

fn send(ch: &RawChannel, ns: u64, v: &serde_json::Value) {
    ch.log_with_meta(v.to_string().as_bytes(), PartialMetadata::with_log_time(ns));
}

impl FoxgloveLive {
    /// Serves the channels of `scenario`'s run at `addr` (port 0: any free port).
    pub async fn start(addr: SocketAddr, scenario: &Scenario, run: &str) -> Result<Self, Error> {
        let ctx = Context::new();
        let server = ctx
            .websocket_server()
            .name(format!("formation {run}"))
            .bind(addr.ip().to_string(), addr.port())
            .start()
            .await
            .map_err(|e| Error::Input(format!("--foxglove {addr}: {e}")))?;
        let port = server.port();
        let leader_names = names(LEADER_HEADER);
        let follower_names = names(FOLLOWER_HEADER);
        let leader_schema = columns_schema("formation.LeaderState", &leader_names);
        let follower_schema = columns_schema("formation.FollowerState", &follower_names);
        let leader_pose = channel(&ctx, "/leader/pose", "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let leader_state = channel(&ctx, "/leader/state", "formation.LeaderState", &leader_schema)?;
        let mut followers = Vec::new();
        for f in &scenario.followers {
            let id = f.id;
            followers.push(FollowerChannels {
                pose: channel(&ctx, &format!("/follower_{id}/pose"), "foxglove.PoseInFrame", POSE_IN_FRAME)?,
                estimate: channel(&ctx, &format!("/follower_{id}/estimate"), "foxglove.PoseInFrame", POSE_IN_FRAME)?,
                state: channel(&ctx, &format!("/follower_{id}/state"), "formation.FollowerState", &follower_schema)?,
            });
        }
        let events = channel(&ctx, "/network/events", "formation.NetworkEvent", EVENT)?;
        let every = ((1.0 / (LIVE_HZ * scenario.dt_s)).round() as u64).max(1);
        Ok(Self {
            _context: ctx,
            server: Mutex::new(Some(server)),
            port,
            leader_pose,
            leader_state,
            followers,
            events,
            every,
            last_k: scenario.steps(),
            dt_s: scenario.dt_s,
        })
    }

    /// The port it serves on.
    pub fn port(&self) -> u16 {
        self.port
    }

    fn wanted(&self, k: u64) -> bool {
        k % self.every == 0 || k == self.last_k
    }

    /// Stops the server and disconnects its viewers.
    pub async fn stop(&self) {
        let server = self.server.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let Some(s) = server {
            s.stop().wait().await;
        }
    }
}

/// The recorder's rows and events, as run.mcap's messages.
impl LiveSink for FoxgloveLive {
    /// The leader's state of step k, as `leader.csv`'s row.
    fn leader(&self, k: u64, l: &LeaderState) {
        if !self.wanted(k) || !(self.leader_pose.has_sinks() || self.leader_state.has_sinks()) {
            return;
        }
        let t = k as f64 * self.dt_s;
        let (ns, st) = stamp(t);
        if self.leader_pose.has_sinks() {
            send(&self.leader_pose, ns, &pose_in_frame(&st, l.pose.x, l.pose.y, l.pose.theta));
        }
        if self.leader_state.has_sinks() {
            let row = json!({"t": t, "x": l.pose.x, "y": l.pose.y, "theta": l.pose.theta, "v": l.v, "w": l.w});
            send(&self.leader_state, ns, &row);
        }
    }

    /// Follower `index`'s row of step k, as `follower_<id>.csv`'s.
    fn follower(&self, index: usize, k: u64, row: &Row) {
        let Some(c) = self.followers.get(index) else { return };
        if !self.wanted(k) {
            return;
        }
        let (ns, st) = stamp(row.t);
        if c.pose.has_sinks() {
            send(&c.pose, ns, &pose_in_frame(&st, row.x, row.y, row.theta));
        }
        if c.estimate.has_sinks() {
            send(&c.estimate, ns, &pose_in_frame(&st, row.x_ir, row.y_ir, row.theta_ir));
        }
        if c.state.has_sinks() {
            // The row straight to JSON text (its fields are the CSV's columns).
            if let Ok(bytes) = serde_json::to_vec(row) {
                c.state.log_with_meta(&bytes, PartialMetadata::with_log_time(ns));
            }
        }
    }

    /// A network event `node` noticed at step k (every one, not thinned).
    fn event(&self, node: &str, k: u64, what: &str) {
        if self.events.has_sinks() {
            let t = k as f64 * self.dt_s;
            send(&self.events, stamp(t).0, &json!({"node": node, "t": t, "event": what}));
        }
    }

    /// Viewers connected now.
    fn viewers(&self) -> usize {
        self.server.lock().unwrap_or_else(|p| p.into_inner()).as_ref().map_or(0, |s| s.client_count())
    }
}
