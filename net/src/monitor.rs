//! The monitor (the `monitor` binary): subscribes to every node's
//! telemetry, shows a live line of the formation error per follower and the
//! worst one, and writes the same run folder as `formation sim` (through
//! [`RunWriter`], [`MetricsAccumulator`] and [`Summary`], so a lock-step run
//! gives a byte-identical `summary.json`) plus `network.json` with each
//! node's message counters. Ctrl-C or SIGTERM: writes everything received
//! so far and exits with status 130 (SIGINT) or 143 (SIGTERM).

use std::collections::{BTreeMap, VecDeque};
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use formation_agent::LeaderState;
use formation_topology::Scenario;
use serde_json::json;
use tokio::sync::mpsc;

use crate::error::Error;

use crate::barrier;
use crate::codec;
use crate::counters::Counters;
use crate::names::{self, Keys, MONITOR};
use crate::node::NodeArgs;
use crate::startup;
use crate::telemetry::{Ack, ClockReport, Delivery, EventKind, LinkStats, NetEvent, Telemetry};
use crate::timing::LoopStats;
use crate::watch::Watch;
use formation_record::hearing::{Density, End, FollowerHearing, HearingRecord, Rescued, Resume, ScenarioSource};
use formation_record::{
    FollowerSample, Heard, MetricsAccumulator, RecordOptions, Row, RunWriter, Summary, HEARING_FILE,
};

/// `monitor` arguments.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct MonitorArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// Run folder to write [default: runs/<run name>]. Replaced if it is a run folder; any other existing folder is refused.
    #[cfg_attr(feature = "clap", arg(long, value_name = "DIR"))]
    pub out: Option<PathBuf>,
    /// Write every N-th sample to the CSVs (metrics always use every sample).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1, value_name = "N"))]
    pub every: u64,
    /// Also write run.mcap: the CSVs' rows as an MCAP recording that
    /// Foxglove and the mcap tools open (poses as foxglove.PoseInFrame, every
    /// column as numbers, network events). About 1.6 KB per follower row:
    /// combine with --every for long runs.
    #[cfg_attr(feature = "clap", arg(long))]
    pub mcap: bool,
    /// Give up when no telemetry arrives for this long (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 60.0, value_name = "SECONDS"))]
    pub idle_timeout: f64,
    /// No live line.
    #[cfg_attr(feature = "clap", arg(long, short))]
    pub quiet: bool,
    #[cfg_attr(feature = "clap", command(flatten))]
    pub web: WebArgs,
    /// Serve the live page on this Unix socket instead (the lab forwards a
    /// port of the machine's own namespace to it).
    #[cfg_attr(feature = "clap", arg(long, value_name = "PATH", hide = true, conflicts_with = "web"))]
    pub web_unix: Option<PathBuf>,
}

/// The live page's options (the monitor's, and `launch`'s and the lab's).
#[derive(Debug, Clone, Default)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct WebArgs {
    /// Serve a live page of the run at this address (open http://ADDR/ in a
    /// browser): the plane, errors against time, the network and its events.
    /// `--web` alone: 127.0.0.1:8765. Port 0: any free port (the line
    /// `live page: http://…` says which).
    #[cfg_attr(feature = "clap", arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8765"))]
    pub web: Option<std::net::SocketAddr>,
    /// With --web: keep the page served this long after the run ends, so
    /// that open pages get the end of the run.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 3.0, value_name = "SECONDS"))]
    pub web_linger: f64,
    /// Serve the run live to Foxglove (Foxglove WebSocket protocol) at this
    /// address: the channels of run.mcap (poses, estimates, every CSV
    /// column, network events) at up to 50 messages per channel and second
    /// of run time. In Foxglove: Open connection, Foxglove WebSocket,
    /// ws://ADDR. `--foxglove` alone: 127.0.0.1:8766; port 0: any free port.
    #[cfg_attr(feature = "clap", arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8766"))]
    pub foxglove: Option<std::net::SocketAddr>,
}

impl WebArgs {
    /// The same options on another node's command line.
    pub fn to_args(&self) -> Vec<String> {
        let mut args = match self.web {
            Some(addr) => vec!["--web".into(), addr.to_string(), "--web-linger".into(), self.web_linger.to_string()],
            None => Vec::new(),
        };
        if let Some(addr) = self.foxglove {
            args.extend(["--foxglove".to_string(), addr.to_string()]);
        }
        args
    }
}

pub use crate::watch::Ending;

#[derive(Default)]
struct NodeStats {
    messages: u64,
    bytes: u64,
    /// Steps recorded from this node's telemetry.
    samples: u64,
    /// The newest batch so far, as (incarnation, first step): counters and
    /// delivery figures are taken from it (a batch sent again is older).
    newest: Option<(u64, u64)>,
    counters: Counters,
    delivery: Delivery,
    loop_stats: Option<LoopStats>,
    /// The newest estimate of the leader's clock (followers).
    clock: Option<ClockReport>,
    /// The newest per-link latency and age (followers), at most one per source.
    links: Vec<LinkStats>,
    done: bool,
    /// What the network did to this node, as it noticed it.
    timeline: std::collections::BTreeSet<NetEvent>,
    /// When its last checked batch arrived.
    heard: Option<Instant>,
}

/// The live page names a node whose telemetry stopped this long ago (s).
const SILENT_NODE_S: f64 = 2.0;

/// Network events the live page lists.
const RECENT_EVENTS: usize = 50;

/// Rescued messages taken from one batch, and held in all.
const MAX_RESCUED_PER_BATCH: usize = 4096;
const MAX_RESCUED: usize = 1 << 20;

/// Events taken from one batch (a forged batch cannot fill the monitor's memory).
const MAX_EVENTS_PER_BATCH: usize = 256;

impl NodeStats {
    /// Files a checked batch's bookkeeping.
    fn note(
        &mut self,
        now: Instant,
        bytes: usize,
        first_k: u64,
        counters: Counters,
        done: bool,
        loop_stats: Option<LoopStats>,
        delivery: Delivery,
    ) {
        self.messages += 1;
        self.bytes += bytes as u64;
        self.heard = Some(now);
        self.done |= done;
        let at = (delivery.incarnation, first_k);
        if self.newest.is_none_or(|n| at >= n) {
            self.newest = Some(at);
            self.counters = counters;
            self.delivery = delivery;
        }
        // Non-finite timing would turn into nulls in network.json.
        let finite = |l: &LoopStats| {
            [
                l.period_error_p50_us,
                l.period_error_p99_us,
                l.period_error_max_us,
                l.lateness_p50_us,
                l.lateness_p99_us,
                l.lateness_max_us,
            ]
            .iter()
            .all(|x| x.is_finite())
        };
        self.loop_stats = loop_stats.filter(finite).or(self.loop_stats);
    }
}

/// Steps of one node that the monitor will never have.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Gap {
    /// Steps from..to.
    pub from: u64,
    pub to: u64,
    /// "restarted" (the node's process was replaced) or "dropped by the
    /// sender" (its store of unacknowledged telemetry overflowed).
    pub why: &'static str,
}

/// Batches that arrive ahead of the recorded end are held, up to about
/// this many bytes per node (at most 8192 batches, at least 16).
const MAX_AHEAD_BYTES: usize = 16 << 20;
/// Telemetry received and not yet filed, bytes: beyond this a message is
/// dropped and counted (its sender sends it again: it is not acknowledged).
const MAX_QUEUED_BYTES: usize = 64 << 20;

/// One node's telemetry put back in step order: batches may arrive late,
/// twice (sent again), out of order, or never (steps the sender says it
/// can no longer deliver become a [`Gap`]).
#[derive(Debug)]
struct Stream<T> {
    /// Every step below `end` is recorded or marked lost.
    end: u64,
    /// Batches that arrived ahead of `end`, by first step.
    ahead: BTreeMap<u64, Vec<T>>,
    gaps: Vec<Gap>,
    /// Batches that arrived ahead of a missing one and were held.
    reordered: u64,
    /// Batches that held nothing new (sent again after a lost acknowledgement).
    duplicates: u64,
    /// Batches given up because too many were held ahead.
    overflow: u64,
    /// Steps that came late and filled a hole (a batch sent again after an
    /// outage or a loss), as merged spans [from, to).
    recovered: Vec<(u64, u64)>,
    /// Steps at which a new process of the sender took over.
    restarts: Vec<u64>,
    /// The sender's process (see `Delivery::incarnation`).
    incarnation: Option<u64>,
    /// Most batches held ahead.
    max_ahead: usize,
}

impl<T> Default for Stream<T> {
    fn default() -> Self {
        Self::for_batches_of(1)
    }
}

impl<T> Stream<T> {
    /// A stream whose batches hold at most `batch` items: it holds at most
    /// [`MAX_AHEAD_BYTES`] of them ahead.
    fn for_batches_of(batch: usize) -> Self {
        let per_batch = batch.max(1) * std::mem::size_of::<T>().max(1);
        Self {
            max_ahead: (MAX_AHEAD_BYTES / per_batch).clamp(16, 8192),
            end: 0,
            ahead: BTreeMap::new(),
            gaps: Vec::new(),
            reordered: 0,
            duplicates: 0,
            overflow: 0,
            recovered: Vec::new(),
            restarts: Vec::new(),
            incarnation: None,
        }
    }

    /// Files a checked batch (items for steps first_k, first_k + 1, …) from
    /// a sender that can deliver nothing below `available_from`; appends to
    /// `out` every item now in order, with its step.
    fn file(&mut self, first_k: u64, items: Vec<T>, available_from: u64, incarnation: u64, out: &mut Vec<(u64, T)>) {
        let restarted = self.incarnation.is_some_and(|i| i != incarnation);
        if restarted {
            self.restarts.push(first_k);
        }
        self.incarnation = Some(incarnation);
        let end = first_k + items.len() as u64;
        if end <= self.end || items.is_empty() {
            self.duplicates += 1;
        } else if first_k > self.end {
            self.reordered += 1;
            if self.ahead.len() >= self.max_ahead {
                self.overflow += 1;
                if let Some(last) = self.ahead.keys().next_back().copied().filter(|&l| l > first_k) {
                    self.ahead.remove(&last);
                } else {
                    return;
                }
            }
            // Of two batches with one first step, keep the longer.
            match self.ahead.get(&first_k) {
                Some(held) if held.len() >= items.len() => {}
                _ => {
                    self.ahead.insert(first_k, items);
                }
            }
        } else {
            if !self.ahead.is_empty() {
                // A late batch fills the hole before held ones.
                match self.recovered.last_mut() {
                    Some(r) if r.1 >= first_k => r.1 = r.1.max(end),
                    _ => self.recovered.push((first_k, end)),
                }
            }
            self.take(first_k, items, out);
        }
        loop {
            // Held batches that now continue the stream.
            while let Some((&k, _)) = self.ahead.first_key_value().filter(|(&k, _)| k <= self.end) {
                if let Some(items) = self.ahead.remove(&k) {
                    self.take(k, items, out);
                }
            }
            // Steps the sender can no longer deliver: a gap up to what it can.
            if available_from <= self.end {
                break;
            }
            let to = self.ahead.keys().next().map_or(available_from, |&k| k.min(available_from));
            let why = if restarted { "restarted" } else { "dropped by the sender" };
            match self.gaps.last_mut() {
                Some(g) if g.to == self.end && g.why == why => g.to = to,
                _ => self.gaps.push(Gap { from: self.end, to, why }),
            }
            self.end = to;
        }
    }

    /// Appends the items of a batch beyond `end` (first_k ≤ end).
    fn take(&mut self, first_k: u64, items: Vec<T>, out: &mut Vec<(u64, T)>) {
        let skip = (self.end - first_k) as usize;
        let end = first_k + items.len() as u64;
        out.extend(items.into_iter().enumerate().skip(skip).map(|(i, x)| (first_k + i as u64, x)));
        self.end = self.end.max(end);
    }

    fn lost_steps(&self) -> u64 {
        self.gaps.iter().map(|g| g.to - g.from).sum()
    }
}

/// Checks a batch against a run of `steps` + 1 steps before anything is
/// filed: None if it reaches beyond the run's end; otherwise the items up
/// to the first that fails `ok(k, item)`, and whether it was cut there.
fn check_batch<T>(
    mut items: Vec<T>,
    first_k: u64,
    steps: u64,
    max_len: usize,
    ok: impl Fn(u64, &T) -> bool,
) -> Option<(Vec<T>, bool)> {
    if items.len() > max_len {
        return None;
    }
    match first_k.checked_add(items.len() as u64) {
        Some(last) if last <= steps + 1 => {}
        _ => return None,
    }
    let bad = items.iter().enumerate().position(|(i, x)| !ok(first_k + i as u64, x));
    if let Some(b) = bad {
        items.truncate(b);
    }
    Some((items, bad.is_some()))
}

struct FollowerTrack {
    id: u32,
    offset: [f64; 2],
    /// Samples with what the follower heard at their step.
    stream: Stream<(FollowerSample, Box<[Heard]>)>,
    /// The hearing record of the steps recorded.
    hearing: FollowerHearing,
    /// Samples in step order, waiting for the leader's state of their step.
    pending: VecDeque<FollowerSample>,
    /// Every step below this is a row or lost.
    next_k: u64,
    /// Samples whose leader state was lost (no row).
    unpaired: u64,
    metrics: MetricsAccumulator,
    formation_error: f64,
    /// The newest row and the leader state it was measured against (the live page).
    latest: Option<(Row, LeaderState)>,
}

/// The monitor's bookkeeping, independent of zenoh (fed with telemetry payloads).
pub struct Recorder {
    scenario: Scenario,
    writer: RunWriter,
    followers: Vec<FollowerTrack>,
    leader_stream: Stream<LeaderState>,
    /// Leader states of steps `leader_base`.. (None: lost).
    leader: VecDeque<Option<LeaderState>>,
    leader_base: u64,
    nodes: BTreeMap<u32, NodeStats>,
    malformed: u64,
    /// Of those, by the key they came on (`telemetry/<id>`; None: not a number).
    malformed_by_key: BTreeMap<Option<u32>, u64>,
    /// Puts from other processes on the run's control keys.
    pub control: crate::health::ControlWatch,
    /// The model's formation error per follower (or why it was not run):
    /// with it, `finish` writes network.json's `health`.
    model: Option<Result<BTreeMap<u32, Option<f64>>, String>>,
    /// Telemetry messages dropped on arrival (the queue was full).
    pub queue_dropped: u64,
    /// What every node's access control refused (crate::denials).
    pub denied: crate::denials::Table,
    /// Wall clock: the monitor's start to the leader's start, and the start
    /// to the end of the record (network.json's `wall`).
    startup_s: Option<f64>,
    run_s: Option<f64>,
    /// `--foxglove`: the rows and events as they are recorded.
    foxglove: Option<crate::foxglove::FoxgloveLive>,
    /// The leader's recorded steps, as spans [from, to).
    leader_spans: Vec<(u64, u64)>,
    /// Messages rescued by their receivers, by (sender, stamp).
    rescued: BTreeMap<(u32, u64), Rescued>,
    /// The scenario as the run loaded it: with it, `hearing.bin` is written.
    source: Option<ScenarioSource>,
    density: Density,
}

impl Recorder {
    pub fn new(scenario: &Scenario, opts: &RecordOptions) -> std::io::Result<Self> {
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        let writer = RunWriter::create(opts, &ids)?;
        let followers = scenario
            .followers
            .iter()
            .enumerate()
            .map(|(index, f)| FollowerTrack {
                id: f.id,
                offset: f.offset,
                stream: Stream::for_batches_of(scenario.network.telemetry_batch as usize),
                hearing: FollowerHearing::new(f.id, scenario.sources_of(index)),
                pending: VecDeque::new(),
                next_k: 0,
                unpaired: 0,
                metrics: MetricsAccumulator::for_scenario(scenario),
                formation_error: f64::NAN,
                latest: None,
            })
            .collect();
        let mut nodes = BTreeMap::new();
        nodes.insert(0, NodeStats::default());
        for id in ids {
            nodes.insert(id, NodeStats::default());
        }
        Ok(Self {
            scenario: scenario.clone(),
            writer,
            followers,
            leader_stream: Stream::for_batches_of(scenario.network.telemetry_batch as usize),
            leader: VecDeque::new(),
            leader_base: 0,
            nodes,
            malformed: 0,
            malformed_by_key: BTreeMap::new(),
            control: Default::default(),
            model: None,
            queue_dropped: 0,
            denied: Default::default(),
            startup_s: None,
            run_s: None,
            foxglove: None,
            leader_spans: Vec::new(),
            rescued: BTreeMap::new(),
            source: None,
            density: Density { every: opts.every.max(1), csv: opts.csv, mcap: opts.mcap },
        })
    }

    /// The scenario as loaded (file text and overrides): the run folder
    /// gets the hearing record (`hearing.bin`), which `formation replay` reads.
    pub fn set_source(&mut self, source: ScenarioSource) {
        self.source = Some(source);
    }

    /// A replay (`crate::replay`): the leader's state of step k, `None` if
    /// the run did not record it. Call in step order.
    pub fn replayed_leader(&mut self, k: u64, state: Option<&LeaderState>) -> std::io::Result<()> {
        self.file_leader(k, state)?;
        self.leader_stream.end = k + 1;
        Ok(())
    }

    /// The leader's state of step k, in step order (`None`: not recorded):
    /// its row, Foxglove, and the state the followers' rows of k pair with.
    fn file_leader(&mut self, k: u64, state: Option<&LeaderState>) -> std::io::Result<()> {
        if let Some(s) = state {
            match self.leader_spans.last_mut() {
                Some(span) if span.1 == k => span.1 = k + 1,
                _ => self.leader_spans.push((k, k + 1)),
            }
            if self.writer.wants(k, k == self.scenario.steps()) {
                self.writer.leader_row(k as f64 * self.scenario.dt_s, s)?;
            }
            if let Some(live) = &self.foxglove {
                live.leader(k, s);
            }
        }
        while self.leader_base + (self.leader.len() as u64) < k {
            self.leader.push_back(None);
        }
        self.leader.push_back(state.copied());
        Ok(())
    }

    /// A replay: follower `index`'s sample of step k and what it heard.
    pub fn replayed_follower(&mut self, index: usize, k: u64, sample: FollowerSample, heard: &[Heard]) {
        let f = &mut self.followers[index];
        f.stream.end = k + 1;
        f.hearing.push(k, heard);
        f.pending.push_back(sample);
    }

    /// A replay: follower `index`'s restarts and end, as the run recorded them.
    pub fn replayed_hearing(&mut self, index: usize, resumes: &[Resume], end: End) {
        let h = &mut self.followers[index].hearing;
        for r in resumes {
            h.resumed(*r);
        }
        h.end = end;
    }

    /// A replay: rows for every sample whose leader state is known.
    pub fn settle(&mut self) -> std::io::Result<()> {
        self.process()
    }

    /// Sends every row and network event from now on to `live` as well.
    pub fn set_foxglove(&mut self, live: crate::foxglove::FoxgloveLive) {
        self.foxglove = Some(live);
    }

    /// The Foxglove server, taken out to stop it.
    pub fn take_foxglove(&mut self) -> Option<crate::foxglove::FoxgloveLive> {
        self.foxglove.take()
    }

    /// Counts `n` refused telemetry messages (or steps of one) on `telemetry/<key_id>`.
    fn refuse(&mut self, key_id: Option<u32>, n: u64) {
        if n == 0 {
            return;
        }
        self.malformed += n;
        // Ids the scenario does not know are counted together (a forger's keys cannot fill memory).
        let key = key_id.filter(|&id| id == 0 || self.scenario.index_of(id).is_some());
        *self.malformed_by_key.entry(key).or_default() += n;
    }

    /// The model's formation error per follower, or why there is none: with
    /// it, `finish` judges the run's health (network.json's `health`).
    pub fn set_model(&mut self, model: Result<BTreeMap<u32, Option<f64>>, String>) {
        self.model = Some(model);
    }

    /// The run's health (None without [`Recorder::set_model`]).
    pub fn health(&self, summary: &Summary) -> Option<crate::health::Health> {
        let model = self.model.as_ref()?;
        let dt = self.scenario.dt_s;
        let mut e = crate::health::Evidence { steps: self.scenario.steps(), dt_s: dt, ..Default::default() };
        let mut invalid = 0;
        for (&id, n) in &self.nodes {
            invalid += n.counters.rejected.invalid();
            if id == 0 {
                continue;
            }
            let mut open = None;
            for ev in &n.timeline {
                match ev.what {
                    crate::telemetry::EventKind::Isolated => {
                        open.get_or_insert(ev.k);
                    }
                    crate::telemetry::EventKind::Rejoined => {
                        if let Some(from) = open.take() {
                            e.isolations.push((id, from, Some(ev.k)));
                        }
                    }
                    _ => {}
                }
            }
            if let Some(from) = open {
                e.isolations.push((id, from, None));
            }
            if let Some(c) = n.clock {
                let second = c.guard.second_clock_since_ns.map(|_| c.guard.worst_disagreement_ms);
                if c.steps > 0 || second.is_some() {
                    e.clocks.push((format!("follower {id}"), c.steps, second));
                }
            }
        }
        match model {
            Ok(m) => {
                e.errors = summary
                    .followers
                    .iter()
                    .map(|(&id, f)| (id, f.formation_rms_last10, m.get(&id).copied().flatten()))
                    .collect()
            }
            Err(why) => e.model_skipped = Some(why.clone()),
        }
        e.refused = vec![
            ("telemetry messages refused (malformed or on another's key)".into(), self.malformed),
            ("estimate messages refused by followers (malformed, forged or not a neighbour's)".into(), invalid),
            ("puts refused on control keys".into(), self.control.refused()),
            ("telemetry messages dropped by the monitor (queue full)".into(), self.queue_dropped),
            ("followers with a second sender on their key".into(), self.twins().len() as u64),
            ("messages refused by access control".into(), self.denied.rows().len() as u64),
        ];
        e.restarts = self
            .followers
            .iter()
            .filter(|f| !f.stream.restarts.is_empty())
            .map(|f| (format!("follower {}", f.id), f.stream.restarts.clone()))
            .collect();
        if !self.leader_stream.restarts.is_empty() {
            e.restarts.push(("the leader".into(), self.leader_stream.restarts.clone()));
        }
        let leader = self.nodes.get(&0).map(|n| n.counters).unwrap_or_default();
        e.time_queries = (leader.time_queries, leader.time_queries_peak_per_s, self.scenario.followers.len() as u64);
        Some(crate::health::judge(&e))
    }

    /// Files one telemetry message received on `telemetry/<key_id>` at `now`.
    pub fn telemetry(&mut self, key_id: Option<u32>, bytes: &[u8], now: Instant) -> std::io::Result<()> {
        let Some(t) = codec::decode::<Telemetry>(bytes) else {
            self.refuse(key_id, 1);
            return Ok(());
        };
        let steps = self.scenario.steps();
        // A sender's batches hold at most this many steps: a longer one is forged.
        let batch = self.scenario.network.telemetry_batch.max(1) as usize;
        match t {
            Telemetry::Leader { first_k, states, counters, done, loop_stats, delivery } => {
                if key_id != Some(0) {
                    self.refuse(key_id, 1);
                    return Ok(());
                }
                let Some((states, cut)) = check_batch(states, first_k, steps, batch, |_, s| s.is_finite()) else {
                    self.refuse(key_id, 1);
                    return Ok(());
                };
                self.refuse(key_id, u64::from(cut));
                let n = self.nodes.entry(0).or_default();
                n.note(now, bytes.len(), first_k, counters, done, loop_stats, delivery);
                let mut fresh = Vec::new();
                self.leader_stream.file(first_k, states, delivery.available_from, delivery.incarnation, &mut fresh);
                n.samples += fresh.len() as u64;
                for (k, s) in fresh {
                    self.file_leader(k, Some(&s))?;
                }
                while self.leader_base + (self.leader.len() as u64) < self.leader_stream.end {
                    self.leader.push_back(None);
                }
            }
            Telemetry::Follower {
                id,
                first_k,
                samples,
                counters,
                done,
                loop_stats,
                delivery,
                events,
                clock,
                links,
                heard,
                rescued,
                resumed,
                diverged,
            } => {
                let Some(index) = self.scenario.index_of(id).filter(|_| key_id == Some(id)) else {
                    self.refuse(key_id, 1);
                    return Ok(());
                };
                // The hearing record covers the batch's steps, one entry per source
                // (none with `network.hearing_record = false`).
                let slots = self.followers[index].hearing.sources.len();
                let recording = self.scenario.network.hearing_record;
                let (want_steps, want_slots) = if recording { (samples.len(), slots) } else { (0, 0) };
                if heard.steps as usize != want_steps || heard.slots.len() != want_slots || !heard.is_consistent() {
                    self.refuse(key_id, 1);
                    return Ok(());
                }
                // The batch's last step as sent (a diverged one is cut below).
                let last_k = first_k + samples.len().saturating_sub(1) as u64;
                let mut per_step = heard.expand().into_iter().map(Vec::into_boxed_slice);
                let samples: Vec<_> = samples.into_iter().map(|s| (s, per_step.next().unwrap_or_default())).collect();
                let ok = |k: u64, (s, _): &(FollowerSample, Box<[Heard]>)| s.k == k && s.is_finite();
                let Some((samples, cut)) = check_batch(samples, first_k, steps, batch, ok) else {
                    self.refuse(key_id, 1);
                    return Ok(());
                };
                self.refuse(key_id, u64::from(cut));
                let n = self.nodes.entry(id).or_default();
                n.note(now, bytes.len(), first_k, counters, done, loop_stats, delivery);
                if n.newest == Some((delivery.incarnation, first_k)) {
                    n.clock = clock.filter(|c| c.offset_ms.is_finite() && c.uncertainty_us.is_finite()).or(n.clock);
                    // A forged batch cannot fill the monitor's memory: one entry per source.
                    let g = &self.scenario.graph;
                    let sources = g.neighbours(index).len() + usize::from(g.hears_leader(index));
                    if links.len() <= sources {
                        n.links = links;
                    }
                }
                // A batch sent again repeats its events: a set keeps each once.
                for e in events.into_iter().take(MAX_EVENTS_PER_BATCH) {
                    if let (true, Some(live)) = (n.timeline.insert(e), &self.foxglove) {
                        live.event(&id.to_string(), e.k, &e.what.describe());
                    }
                }
                // Messages its sources sent (a forged batch cannot fill the monitor's memory).
                let sources = &self.followers[index].hearing.sources;
                for r in rescued.into_iter().take(MAX_RESCUED_PER_BATCH) {
                    let ok = sources.contains(&r.source) && r.stamp <= steps && r.state.is_finite();
                    if ok && self.rescued.len() < MAX_RESCUED {
                        self.rescued.entry((r.source, r.stamp)).or_insert(r);
                    }
                }
                let f = &mut self.followers[index];
                if let Some(r) = resumed.filter(|r| r.pose.iter().all(|x| x.is_finite()) && r.k <= steps) {
                    f.hearing.resumed(r);
                }
                let mut fresh = Vec::new();
                f.stream.file(first_k, samples, delivery.available_from, delivery.incarnation, &mut fresh);
                n.samples += fresh.len() as u64;
                if let Some(quantity) = diverged {
                    f.hearing.end = End::Diverged { k: last_k, quantity: quantity.chars().take(100).collect() };
                } else if done {
                    f.hearing.end = End::Completed;
                }
                for (k, (sample, heard)) in fresh {
                    if recording {
                        f.hearing.push(k, &heard);
                    }
                    f.pending.push_back(sample);
                }
            }
        }
        self.process()
    }

    /// Turns every follower sample whose leader state is known into a row.
    fn process(&mut self) -> std::io::Result<()> {
        let steps = self.scenario.steps();
        let dt = self.scenario.dt_s;
        let leader_end = self.leader_base + self.leader.len() as u64;
        for (index, f) in self.followers.iter_mut().enumerate() {
            while f.pending.front().is_some_and(|s| s.k < leader_end) {
                let Some(sample) = f.pending.pop_front() else { break };
                let k = sample.k;
                f.next_k = k + 1;
                let Some(l) = self.leader.get((k - self.leader_base) as usize).copied().flatten() else {
                    f.unpaired += 1;
                    continue;
                };
                let row = Row::new(&sample, &l, f.offset, dt);
                f.metrics.push(k, &row);
                f.formation_error = row.formation_error;
                f.latest = Some((row, l));
                if self.writer.wants(k, k == steps) {
                    self.writer.follower_row(index, &row)?;
                }
                if let Some(live) = &self.foxglove {
                    live.follower(index, k, &row);
                }
            }
            if f.pending.is_empty() {
                f.next_k = f.next_k.max(f.stream.end.min(leader_end));
            }
        }
        // Leader states every follower has used are no longer needed.
        let used =
            self.followers.iter().map(|f| f.pending.front().map_or(f.next_k, |s| s.k)).min().unwrap_or(leader_end);
        while self.leader_base < used && !self.leader.is_empty() {
            self.leader.pop_front();
            self.leader_base += 1;
        }
        Ok(())
    }

    /// Per node (0: the leader), the first step the monitor does not hold.
    pub fn ack(&self) -> Ack {
        let mut next_k = vec![(0, self.leader_stream.end)];
        next_k.extend(self.followers.iter().map(|f| (f.id, f.stream.end)));
        Ack { fingerprint: barrier::fingerprint(&self.scenario), next_k }
    }

    /// Steps of any node that will never be recorded (lost, or left without a leader state).
    pub fn lost_steps(&self) -> u64 {
        self.leader_stream.lost_steps() + self.followers.iter().map(|f| f.stream.lost_steps() + f.unpaired).sum::<u64>()
    }

    /// Removes the folder being written (a run that never started).
    pub fn discard(self) {
        self.writer.discard();
    }

    /// Appends the buffered CSV rows to the (partial) folder.
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.writer.flush()
    }

    /// Whether every node has reported its final step and all of it is recorded
    /// or marked lost.
    /// (Gaps included: see [`Recorder::lost_steps`].)
    pub fn complete(&self) -> bool {
        let steps = self.scenario.steps();
        self.nodes.values().all(|n| n.done)
            && self.leader_stream.end == steps + 1
            && self.followers.iter().all(|f| f.next_k == steps + 1 && f.pending.is_empty())
    }

    /// Steps recorded by every follower.
    pub fn recorded_steps(&self) -> u64 {
        self.followers.iter().map(|f| f.next_k).min().unwrap_or(0)
    }

    /// Nodes that have not reported their final step.
    pub fn unfinished(&self) -> Vec<String> {
        self.nodes
            .iter()
            .filter(|(_, n)| !n.done)
            .map(|(&id, _)| if id == 0 { "leader".to_string() } else { format!("follower {id}") })
            .collect()
    }

    /// The live line: latest formation error per follower and the worst.
    pub fn status_line(&self) -> String {
        let k = self.recorded_steps();
        let mut line = format!("t = {:>7.3} s |", k as f64 * self.scenario.dt_s);
        let mut worst: Option<(u32, f64)> = None;
        for f in &self.followers {
            if self.followers.len() <= 8 {
                line += &format!(" F{} {:.4}", f.id, f.formation_error);
            }
            if f.formation_error.is_finite() && worst.is_none_or(|(_, w)| f.formation_error > w) {
                worst = Some((f.id, f.formation_error));
            }
        }
        match worst {
            Some((id, w)) => line += &format!(" | worst F{id} {w:.4} m"),
            None => line += " | waiting for telemetry",
        }
        line
    }

    /// The live page's scene: what does not change during the run.
    pub fn scene_json(s: &Scenario, run: &str) -> String {
        let g = &s.graph;
        let mut edges = Vec::new();
        for i in 0..g.len() {
            for &j in g.neighbours(i) {
                if i < j {
                    edges.push([g.id(i), g.id(j)]);
                }
            }
        }
        let leader_links: Vec<u32> = (0..g.len()).filter(|&i| g.hears_leader(i)).map(|i| g.id(i)).collect();
        let mode = match s.timing {
            formation_topology::Timing::Lockstep => "lockstep",
            formation_topology::Timing::Realtime => "realtime",
        };
        json!({
            "run": run,
            "scenario": s.name,
            "dt": s.dt_s,
            "steps": s.steps(),
            "duration": s.duration_s,
            "mode": mode,
            "followers": s.followers.iter().map(|f| json!({"id": f.id, "offset": f.offset})).collect::<Vec<_>>(),
            "edges": edges,
            "leader_links": leader_links,
        })
        .to_string()
    }

    /// One frame of the live page (see [`crate::web`]): every follower's
    /// newest row, the nodes' counters and what the network did; and the
    /// same frame for the history, without the nodes and events (a late
    /// viewer needs those only from the newest frame).
    pub fn live_frame(&self, now: Instant, seq: u64, wall_s: f64, state: &str, viewers: usize) -> (String, String) {
        let dt = self.scenario.dt_s;
        let steps = self.scenario.steps();
        let k = self.recorded_steps();
        let t = k.saturating_sub(1) as f64 * dt;
        let running = state == "running";
        let finite = |x: f64| if x.is_finite() { json!(x) } else { serde_json::Value::Null };
        // The leader as the least advanced follower saw it (the frame's t).
        let leader = self
            .followers
            .iter()
            .filter_map(|f| f.latest.as_ref())
            .min_by(|a, b| a.0.t.total_cmp(&b.0.t))
            .map(|(_, l)| json!([l.pose.x, l.pose.y, l.pose.theta]));
        let followers: Vec<_> = self
            .followers
            .iter()
            .map(|f| match &f.latest {
                Some((r, _)) => json!({
                    "id": f.id, "k": (r.t / dt).round() as u64, "t": r.t,
                    "pose": [r.x, r.y, r.theta], "estimate": [r.x_ir, r.y_ir],
                    "ef": finite(r.formation_error), "ee": finite(r.estimator_error),
                }),
                None => {
                    json!({"id": f.id, "k": null, "t": null, "pose": null, "estimate": null, "ef": null, "ee": null})
                }
            })
            .collect();
        let name = |id: u32| if id == 0 { "leader".to_string() } else { format!("follower {id}") };
        let mut gone = Vec::new();
        let mut recent: Vec<(u64, u32, String)> = Vec::new();
        let nodes: Vec<_> = self
            .nodes
            .iter()
            .map(|(&id, n)| {
                let heard_s = n.heard.map(|h| now.duration_since(h).as_secs_f64());
                if running && !n.done && heard_s.is_none_or(|h| h > SILENT_NODE_S) {
                    gone.push(match heard_s {
                        Some(h) => format!("no telemetry from {} for {h:.1} s", name(id)),
                        None => format!("no telemetry from {} yet", name(id)),
                    });
                }
                // The sources this node counts as silent now: the newest event about each.
                let mut silent = std::collections::BTreeSet::new();
                for e in &n.timeline {
                    match e.what {
                        EventKind::Silent(s) => {
                            silent.insert(s);
                        }
                        EventKind::Heard(s) => {
                            silent.remove(&s);
                        }
                        _ => {}
                    }
                }
                recent.extend(n.timeline.iter().rev().take(RECENT_EVENTS).map(|e| (e.k, id, e.what.describe())));
                let c = &n.counters;
                json!({
                    "id": id, "name": name(id), "heard_s": heard_s, "done": n.done,
                    "sent": c.sent, "received": c.received, "late": c.late, "rejected": c.rejected.invalid(),
                    "silent": c.silent, "fault_lost": c.fault_lost, "silent_sources": silent,
                    "clock": n.clock,
                    "links": n.links,
                })
            })
            .collect();
        let events: usize = self.nodes.values().map(|n| n.timeline.len()).sum();
        recent.sort();
        let recent: Vec<_> = recent[recent.len().saturating_sub(RECENT_EVENTS)..]
            .iter()
            .map(|(k, id, what)| json!({"t": *k as f64 * dt, "node": name(*id), "what": what}))
            .collect();
        let message = match gone.len() {
            0 => None,
            1..=3 => Some(gone.join("; ")),
            n => Some(format!("{}; and {} more nodes", gone[..3].join("; "), n - 3)),
        };
        let mut frame = json!({
            "seq": seq, "wall": wall_s, "k": k, "t": t,
            "progress": k as f64 / (steps + 1) as f64,
            "state": state, "viewers": viewers,
            "leader": leader, "followers": followers, "nodes": nodes,
            "events": events, "recent_events": recent, "message": message,
            "alerts": self.alerts(),
        });
        let full = frame.to_string();
        if let Some(f) = frame.as_object_mut() {
            f.insert("nodes".into(), json!([]));
            f.insert("recent_events".into(), json!([]));
        }
        (full, frame.to_string())
    }

    /// Followers flagged as twinned by a neighbour: who, seen by whom, since
    /// when (run time, s), and how many messages showed it.
    pub fn twins(&self) -> Vec<serde_json::Value> {
        let mut by: BTreeMap<u32, (Vec<u32>, u64, u64)> = BTreeMap::new();
        for (&receiver, n) in &self.nodes {
            for l in n.links.iter().filter(|l| l.twin_since.is_some()) {
                let e = by.entry(l.source).or_insert((Vec::new(), u64::MAX, 0));
                e.0.push(receiver);
                e.1 = e.1.min(l.twin_since.unwrap_or(u64::MAX));
                e.2 += l.twin_messages;
            }
        }
        by.into_iter()
            .map(|(source, (seen_by, since, messages))| {
                json!({ "follower": source, "seen_by": seen_by, "since_t": since as f64 * self.scenario.dt_s,
                        "messages": messages })
            })
            .collect()
    }

    /// One line per thing the live page must say at once: twinned
    /// followers and access-control denials.
    fn alerts(&self) -> Vec<String> {
        let mut out: Vec<String> = self
            .twins()
            .iter()
            .map(|t| {
                format!(
                    "follower {}: a second sender on its key since t = {:.2} s (seen by {}; {} messages)",
                    t["follower"],
                    t["since_t"].as_f64().unwrap_or(0.0),
                    t["seen_by"],
                    t["messages"]
                )
            })
            .collect();
        out.extend(self.denied.summary());
        // A second clock on control/time, as each follower saw it.
        for (id, n) in &self.nodes {
            if let Some(g) = n.clock.map(|c| c.guard).filter(|g| g.second_clock_since_ns.is_some()) {
                out.push(format!(
                    "follower {id}: a second clock answers on control/time, {:.1} ms from the leader's; \
                     {} answers refused",
                    g.worst_disagreement_ms, g.refused_answers
                ));
            }
        }
        out
    }

    /// `network.json`: per-node message counts and loop timing.
    pub fn network_json(&self, ending: Ending) -> String {
        self.network_json_with(ending, None)
    }

    fn network_json_with(&self, ending: Ending, health: Option<&crate::health::Health>) -> String {
        let nodes: serde_json::Map<String, serde_json::Value> = self
            .nodes
            .iter()
            .map(|(&id, n)| {
                let name = if id == 0 { "leader".to_string() } else { id.to_string() };
                let c = &n.counters;
                let follower = self.scenario.index_of(id).filter(|_| id != 0).map(|i| &self.followers[i]);
                // Steps this follower's record has reached (followers can be ahead of the slowest one).
                let recorded = follower.map(|f| f.next_k);
                let stream = follower.map_or(
                    (
                        &self.leader_stream.gaps,
                        self.leader_stream.reordered,
                        self.leader_stream.duplicates,
                        &self.leader_stream.recovered,
                        &self.leader_stream.restarts,
                    ),
                    |f| {
                        (
                            &f.stream.gaps,
                            f.stream.reordered,
                            f.stream.duplicates,
                            &f.stream.recovered,
                            &f.stream.restarts,
                        )
                    },
                );
                let dt = self.scenario.dt_s;
                // The node's own events, and the monitor's: telemetry that
                // came late and filled a hole, and steps lost for good.
                let mut timeline: Vec<(u64, String)> = n.timeline.iter().map(|e| (e.k, e.what.describe())).collect();
                timeline.extend(stream.3.iter().map(|&(a, b)| {
                    (a, format!("telemetry for t = {:.3}–{:.3} s recovered late", a as f64 * dt, b as f64 * dt))
                }));
                timeline.extend(stream.0.iter().map(|g| {
                    (
                        g.from,
                        format!(
                            "telemetry for t = {:.3}–{:.3} s lost ({})",
                            g.from as f64 * dt,
                            g.to as f64 * dt,
                            g.why
                        ),
                    )
                }));
                timeline.extend(stream.4.iter().map(|&k| (k, "a new process took over (restarted)".to_string())));
                timeline.sort_by_key(|e| e.0);
                let d = &n.delivery;
                (
                    name,
                    json!({
                        "telemetry_messages": n.messages,
                        "telemetry_bytes": n.bytes,
                        "telemetry_samples": n.samples,
                        "telemetry_reordered": stream.1,
                        "telemetry_duplicates": stream.2,
                        "telemetry_resent": d.courier.resent,
                        "telemetry_dropped_by_sender": d.courier.lost_steps,
                        "telemetry_peak_unacknowledged_bytes": d.courier.peak_held_bytes,
                        "gaps": stream.0,
                        "recovered": stream.3.iter().map(|&(from, to)| json!({"from": from, "to": to})).collect::<Vec<_>>(),
                        "timeline": timeline.iter().map(|(k, what)| json!({
                            "t": *k as f64 * dt,
                            "event": what,
                        })).collect::<Vec<_>>(),
                        "unpaired": follower.map(|f| f.unpaired),
                        "done": n.done,
                        "recorded_steps": recorded,
                        "estimates_sent": c.sent,
                        "republished": c.republished,
                        "received": c.received,
                        "late": c.late,
                        "silent": c.silent,
                        "older": c.older,
                        "fault_lost": c.fault_lost,
                        "rejected": c.rejected,
                        "rejected_invalid": c.rejected.invalid(),
                        // (The leader) questions on control/time, and the most in one second.
                        "time_queries": (id == 0).then_some(c.time_queries),
                        "time_queries_peak_per_s": (id == 0).then_some(c.time_queries_peak_per_s),
                        "loop": n.loop_stats,
                        "clock": n.clock,
                        "links": n.links,
                    }),
                )
            })
            .collect();
        let lost = self.lost_steps();
        let v = json!({
            "scenario": self.scenario.name,
            // The scenario as the nodes loaded it (hearing.bin carries the same).
            "fingerprint": format!("{:016x}", barrier::fingerprint(&self.scenario)),
            "timing": formation_record::name(&self.scenario.timing),
            // Every step of every node recorded, none lost.
            "complete": ending == Ending::Complete && lost == 0,
            // Both signals interrupt the run; `signal` says which.
            "ending": match ending {
                Ending::Complete if lost > 0 => "finished with gaps",
                Ending::Complete => "complete",
                Ending::Interrupted | Ending::Terminated => "interrupted",
                Ending::Idle => "idle",
            },
            "signal": match ending {
                Ending::Interrupted => Some("SIGINT"),
                Ending::Terminated => Some("SIGTERM"),
                _ => None,
            },
            "steps": self.scenario.steps(),
            "recorded_steps": self.recorded_steps(),
            "lost_steps": lost,
            "malformed_telemetry": self.malformed,
            "malformed_telemetry_by_key": self.malformed_by_key.iter().map(|(k, n)| {
                let key = k.map_or("telemetry/(not a node of the run)".to_string(), |id| format!("telemetry/{id}"));
                (key, json!(n))
            }).collect::<serde_json::Map<_, _>>(),
            // Puts from other processes on the run's control keys: per key, how
            // many and how many were refused (foreign fingerprint, garbage).
            "control_puts": self.control.keys.iter().map(|(k, (n, bad))| {
                (k.clone(), json!({"puts": n, "refused": bad}))
            }).collect::<serde_json::Map<_, _>>(),
            // How healthy the run was (crate::health): written by the monitor node.
            "health": health,
            // Telemetry dropped on arrival: more than MAX_QUEUED_BYTES waited to be filed.
            "telemetry_dropped_queue_full": self.queue_dropped,
            // Followers whose key carried a second sender (another process
            // with the same identity), as their neighbours saw it.
            "twins": self.twins(),
            // Messages zenoh's access control refused, by the node that refused them.
            "access_denied": self.denied.rows(),
            // Start-up (every node ready, from the monitor's start) and the
            // run itself, wall clock.
            "wall": {
                "startup_s": self.startup_s,
                "run_s": self.run_s,
                "steps_per_s": self.run_s.filter(|&r| r > 0.0).map(|r| self.recorded_steps() as f64 / r),
            },
            "nodes": nodes,
        });
        serde_json::to_string_pretty(&v).unwrap_or_default() + "\n"
    }

    /// Writes `network.json` and `summary.json` (metrics of what was
    /// received) and moves the folder into place.
    /// The wall-clock figures of network.json's `wall`.
    pub fn set_wall(&mut self, startup_s: Option<f64>, run_s: Option<f64>) {
        self.startup_s = startup_s;
        self.run_s = run_s;
    }

    /// The hearing record of what has been received (with the scenario set
    /// by [`Recorder::set_source`]).
    pub fn hearing_record(&self) -> Option<HearingRecord> {
        if !self.scenario.network.hearing_record {
            return None;
        }
        Some(HearingRecord {
            format: formation_record::hearing::HEARING_FORMAT,
            scenario: self.source.clone()?,
            fingerprint: barrier::fingerprint(&self.scenario),
            density: self.density,
            leader: self.leader_spans.clone(),
            followers: self.followers.iter().map(|f| f.hearing.clone()).collect(),
            rescued: self.rescued.values().copied().collect(),
        })
    }

    pub fn finish(self, ending: Ending) -> std::io::Result<(Summary, PathBuf)> {
        self.finish_judged(ending).map(|(s, d, _)| (s, d))
    }

    /// [`Recorder::finish`], with the run's health when a model was set.
    pub fn finish_judged(self, ending: Ending) -> std::io::Result<(Summary, PathBuf, Option<crate::health::Health>)> {
        let metrics = self.followers.iter().map(|f| (f.id, f.metrics.finish())).collect();
        let outages = self.followers.iter().map(|f| (f.id, f.metrics.outages())).collect();
        let summary = Summary::new(&self.scenario, metrics).with_outages(&self.scenario, &outages);
        let health = self.health(&summary);
        self.writer.write_file("network.json", &self.network_json_with(ending, health.as_ref()))?;
        if let Some(record) = self.hearing_record() {
            self.writer.write_bytes(HEARING_FILE, &record.encode())?;
        }
        let dir = self.writer.finish(&summary)?;
        Ok((summary, dir, health))
    }
}

/// The model runs at the end of a run only up to this many follower-steps
/// (the paper's 4 followers for 30 s are 120,004: 0.3 s).
const MODEL_MAX_FOLLOWER_STEPS: u64 = 3_000_000;

/// Each follower's formation error over the last 10 s in the model of the
/// run (the simulator on the same scenario: delay, loss and fault table),
/// or why the model was not run.
pub fn model_errors(scenario: &Scenario) -> Result<BTreeMap<u32, Option<f64>>, String> {
    let n = scenario.followers.len() as u64 * (scenario.steps() + 1);
    if n > MODEL_MAX_FOLLOWER_STEPS {
        return Err(format!(
            "not run at the end of the run: {n} follower-steps (above {MODEL_MAX_FOLLOWER_STEPS}); \
             formation replay RUN_DIR --explain compares the run with its model"
        ));
    }
    let mut sim = formation_sim::Simulation::new(scenario);
    match sim.run(&mut formation_sim::NoRecord, |_| {}) {
        Ok(metrics) => {
            Ok(scenario.followers.iter().zip(metrics).map(|(f, m)| (f.id, m.formation_rms_last10)).collect())
        }
        Err(e) => Err(format!("the model did not finish: {e}")),
    }
}

/// How often the monitor acknowledges what it holds.
const ACK_PERIOD: Duration = Duration::from_millis(100);

/// Runs the monitor to the end of the run (or Ctrl-C / SIGTERM / idle timeout).
/// Returns how the run ended (`Idle` is an error) and its health's verdict.
pub async fn run(args: &MonitorArgs) -> Result<(Ending, Option<crate::health::Verdict>), Error> {
    let began = Instant::now();
    let (scenario, keys) = args.node.load(crate::names::MONITOR)?;
    if !args.idle_timeout.is_finite() || args.idle_timeout <= 0.0 {
        return Err(Error::Input("--idle-timeout must be positive".into()));
    }
    let dir = args.out.clone().unwrap_or_else(|| PathBuf::from("runs").join(&keys.run));
    let opts = RecordOptions { dir, every: args.every.max(1), csv: true, mcap: args.mcap };
    if !(args.web.web_linger.is_finite() && args.web.web_linger >= 0.0) {
        return Err(Error::Input(format!("--web-linger must be 0 or more seconds, not {}", args.web.web_linger)));
    }
    let bind = match (args.web.web, &args.web_unix) {
        (Some(addr), _) => Some(crate::web::Bind::Tcp(addr)),
        (None, Some(path)) => Some(crate::web::Bind::Unix(path.clone())),
        (None, None) => None,
    };
    let web = match bind {
        Some(bind) => {
            let live = crate::web::Live::new(Recorder::scene_json(&scenario, &keys.run));
            let at = crate::web::serve(bind, live.clone()).await?;
            if args.web_unix.is_none() {
                crate::node::say(&format!("live page: {at}"));
            }
            Some(live)
        }
        None => None,
    };
    let foxglove = match args.web.foxglove {
        Some(addr) => {
            let live = crate::foxglove::FoxgloveLive::start(addr, &scenario, &keys.run).await?;
            crate::node::say(&format!("foxglove: ws://{}:{}", addr.ip(), live.port()));
            Some(live)
        }
        None => None,
    };
    let mut recorder =
        Recorder::new(&scenario, &opts).map_err(|e| Error::Run(format!("creating the run folder: {e}")))?;
    if let Some(live) = foxglove {
        recorder.set_foxglove(live);
    }
    // The hearing record carries the scenario as loaded (`formation replay`
    // checks it against the run's fingerprint).
    if let Ok(text) = std::fs::read_to_string(&args.node.scenario) {
        recorder.set_source(ScenarioSource {
            label: args.node.scenario.display().to_string(),
            text,
            overrides: args.node.overrides.clone(),
        });
    }
    let session = match args.node.open(crate::names::MONITOR, &scenario).await {
        Ok(s) => s,
        Err(e) => {
            // Nothing was recorded: leave no empty `<out>.partial` behind.
            recorder.discard();
            return Err(e);
        }
    };
    let result = monitor(&session, &scenario, &keys, recorder, args, began, web.as_deref()).await;
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    result
}

/// Bytes of telemetry received and not yet filed, and what was dropped.
#[derive(Default)]
struct Queued {
    bytes: std::sync::atomic::AtomicUsize,
    dropped: std::sync::atomic::AtomicU64,
}

impl Queued {
    /// Whether a message of `len` bytes fits under [`MAX_QUEUED_BYTES`] (then it is counted in).
    fn admit(&self, len: usize) -> bool {
        use std::sync::atomic::Ordering::Relaxed;
        let fits =
            self.bytes.fetch_update(Relaxed, Relaxed, |b| (b + len <= MAX_QUEUED_BYTES).then_some(b + len)).is_ok();
        if !fits {
            self.dropped.fetch_add(1, Relaxed);
        }
        fits
    }

    fn release(&self, len: usize) {
        self.bytes.fetch_sub(len, std::sync::atomic::Ordering::Relaxed);
    }

    fn dropped(&self) -> u64 {
        self.dropped.load(std::sync::atomic::Ordering::Relaxed)
    }
}

async fn monitor(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    mut recorder: Recorder,
    args: &MonitorArgs,
    began: Instant,
    web: Option<&crate::web::Live>,
) -> Result<(Ending, Option<crate::health::Verdict>), Error> {
    // Bounded in bytes: a sender that floods the monitor loses its own
    // messages (counted), never the monitor's memory.
    let (tx, mut rx) = mpsc::unbounded_channel::<(Option<u32>, Vec<u8>)>();
    let queue = std::sync::Arc::new(Queued::default());
    let q = std::sync::Arc::clone(&queue);
    let _sub = session
        .declare_subscriber(keys.telemetry_all())
        .callback(move |s| {
            let len = s.payload().len();
            if !q.admit(len) {
                return;
            }
            let id = names::last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
            let _ = tx.send((id, s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(|e| Error::Run(format!("declaring the telemetry subscriber: {e}")))?;
    // What each node's access control refused.
    let (dtx, mut denied_rx) = mpsc::channel::<(String, Vec<u8>)>(64);
    let _denied_sub = session
        .declare_subscriber(keys.denied_all())
        .callback(move |s| {
            let node = names::last_chunk(s.key_expr().as_str()).to_string();
            let _ = dtx.try_send((node, s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(|e| Error::Run(format!("declaring the access-control report subscriber: {e}")))?;
    tokio::spawn(crate::denials::report(session.clone(), MONITOR.to_string(), Some(keys.run.clone())));
    // Every put on the run's control keys from another process, counted per key.
    let control = Arc::new(std::sync::Mutex::new(crate::health::ControlWatch::default()));
    let _control_sub = {
        let (control, prefix, fingerprint) =
            (control.clone(), names::key(&keys.run, ""), barrier::fingerprint(scenario));
        session
            .declare_subscriber(names::key(&keys.run, "control/**"))
            .allowed_origin(zenoh::sample::Locality::Remote)
            .callback(move |s| {
                let rel = s.key_expr().as_str().strip_prefix(prefix.as_str()).unwrap_or("").to_string();
                let bytes = s.payload().to_bytes();
                control.lock().unwrap_or_else(|p| p.into_inner()).note(&rel, &bytes, fingerprint);
            })
            .await
            .map_err(|e| Error::Run(format!("declaring the control-key watch: {e}")))?
    };
    // Acknowledgements: what the monitor holds, so senders forget it and
    // send again what it lacks (droppable: the next one says the same).
    let acks = session
        .declare_publisher(keys.ack())
        .congestion_control(zenoh::qos::CongestionControl::Drop)
        .priority(crate::node::priority::ACK)
        .express(true)
        .await
        .map_err(|e| Error::Run(format!("declaring the acknowledgement publisher: {e}")))?;
    let mut ack_tick = tokio::time::interval(ACK_PERIOD);

    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| Error::Run(format!("installing the SIGTERM handler: {e}")))?;
    // A stream created once, so that a signal arriving between two polls is not lost.
    let mut sigint = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
        .map_err(|e| Error::Run(format!("installing the SIGINT handler: {e}")))?;
    let mut needs: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
    needs.push(names::LEADER_NODE.to_string());
    let barrier = startup::wait_for_start(session, keys, MONITOR, &needs, scenario);
    tokio::pin!(barrier);
    let mut watch = Watch::new(began, Instant::now(), Duration::from_secs_f64(args.idle_timeout));
    let tty = std::io::stderr().is_terminal();
    let mut status = tokio::time::interval(if tty { Duration::from_millis(250) } else { Duration::from_secs(2) });
    let live = !args.quiet;
    let mut frames = tokio::time::interval(crate::web::FRAME_PERIOD);
    frames.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut seq = 0u64;
    let mut publish = |recorder: &Recorder, watch: &Watch, state: &str| {
        if let Some(w) = web {
            seq += 1;
            let now = Instant::now();
            let (frame, past) = recorder.live_frame(now, seq, watch.wall_s(now), state, w.viewers());
            w.publish(frame, past);
        }
    };
    let written = |e: std::io::Error| Error::Run(format!("writing the run folder: {e}"));
    let ending = loop {
        tokio::select! {
            r = &mut barrier, if !watch.started() => {
                if let Err(e) = r {
                    // A start that failed (another scenario, nodes missing)
                    // leaves no folder behind: nothing was recorded.
                    recorder.discard();
                    return Err(e);
                }
                let startup = watch.on_start(Instant::now());
                if live {
                    crate::node::say(&format!(
                        "started: all {} nodes ready {startup:.1} s after the monitor's start",
                        needs.len() + 1
                    ));
                }
            }
            m = rx.recv() => {
                let Some((id, bytes)) = m else { break Ending::Idle };
                queue.release(bytes.len());
                recorder.queue_dropped = queue.dropped();
                let now = Instant::now();
                recorder.telemetry(id, &bytes, now).map_err(written)?;
                if let Some(end) = watch.on_telemetry(now, recorder.complete()) {
                    break end;
                }
            }
            Some((node, bytes)) = denied_rx.recv() => {
                recorder.denied.file(&node, &bytes);
            }
            _ = ack_tick.tick(), if watch.started() => {
                let _ = acks.put(codec::encode(&recorder.ack())).await;
            }
            _ = frames.tick(), if web.is_some() => {
                publish(&recorder, &watch, if watch.started() { "running" } else { "waiting" });
            }
            _ = sigint.recv() => break Ending::Interrupted,
            _ = sigterm.recv() => break Ending::Terminated,
            _ = status.tick() => {
                if let Some(end) = watch.on_tick(Instant::now()) {
                    break end;
                }
                recorder.flush().map_err(written)?;
                if live && watch.started() {
                    let line = recorder.status_line();
                    let mut err = std::io::stderr().lock();
                    let _ = if tty { write!(err, "\r{line}\x1b[K") } else { writeln!(err, "{line}") };
                }
            }
        }
    };
    let run_s = watch.run_s(Instant::now());
    publish(&recorder, &watch, ending.name());
    if matches!(ending, Ending::Interrupted | Ending::Terminated) {
        // Keep what already arrived (stop listening first, so this ends).
        drop(_sub);
        while let Ok((id, bytes)) = rx.try_recv() {
            recorder.telemetry(id, &bytes, Instant::now()).map_err(written)?;
        }
    }
    if ending == Ending::Complete {
        // The senders' last batches are acknowledged only now: say so a few
        // times, so they can stop without waiting for their drain limit.
        for _ in 0..5 {
            let _ = acks.put(codec::encode(&recorder.ack())).await;
            tokio::time::sleep(ACK_PERIOD / 2).await;
        }
    }
    // Access-control reports that came in meanwhile.
    while let Ok((node, bytes)) = denied_rx.try_recv() {
        recorder.denied.file(&node, &bytes);
    }
    if live && tty {
        eprintln!();
    }
    let recorded = recorder.recorded_steps();
    let unfinished = recorder.unfinished();
    let foxglove = recorder.take_foxglove();
    recorder.set_wall(watch.startup_s(), run_s);
    recorder.control = control.lock().unwrap_or_else(|p| p.into_inner()).clone();
    recorder.set_model(model_errors(scenario));
    let (summary, dir, health) =
        recorder.finish_judged(ending).map_err(|e| Error::Run(format!("writing the run folder: {e}")))?;
    let verdict = health.as_ref().map(|h| h.verdict);
    let result = match ending {
        Ending::Complete => {
            if !args.quiet {
                print!("{}", summary.table());
                if let Some(h) = &health {
                    println!("{}", h.line());
                }
                println!("wrote {}", dir.display());
            }
            Ok((Ending::Complete, verdict))
        }
        Ending::Interrupted | Ending::Terminated => {
            let short = summary.shortfall_text().map(|s| format!(" (incomplete: {s})")).unwrap_or_default();
            let how = if ending == Ending::Terminated { "terminated" } else { "interrupted" };
            eprintln!("{how}: wrote the {recorded} steps received to {}{short}", dir.display());
            Ok((ending, verdict))
        }
        Ending::Idle => Err(Error::Run(format!(
            "no telemetry for {} s; still running: {}; wrote the {recorded} steps received to {}",
            args.idle_timeout,
            unfinished.join(", "),
            dir.display()
        ))),
    };
    let watched = web.is_some_and(|w| w.viewers() > 0) || foxglove.as_ref().is_some_and(|f| f.viewers() > 0);
    if watched && matches!(ending, Ending::Complete | Ending::Idle) {
        // Open pages get the final frame before the server ends with the process.
        tokio::time::sleep(Duration::from_secs_f64(args.web.web_linger)).await;
    }
    if let Some(f) = foxglove {
        f.stop().await;
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_record::HeardRuns;

    #[test]
    fn batches_are_checked_before_anything_is_recorded() {
        let ok = |_: u64, x: &f64| x.is_finite();
        // Beyond the run's end: refused whole.
        assert_eq!(check_batch(vec![1.0; 3], 9, 10, 50, ok), None);
        assert_eq!(check_batch(vec![1.0; 1], u64::MAX, 10, 50, ok), None);
        // Cut at the first non-finite item.
        assert_eq!(check_batch(vec![1.0, f64::NAN, 3.0], 4, 10, 50, ok), Some((vec![1.0], true)));
        assert_eq!(check_batch(vec![1.0, 2.0], 9, 10, 50, ok), Some((vec![1.0, 2.0], false)));
        // Longer than the run's batches: forged.
        assert_eq!(check_batch(vec![1.0; 51], 0, 1000, 50, ok), None);
    }

    /// Files batches into a stream; the steps that came out, in order.
    fn file(s: &mut Stream<u64>, first_k: u64, n: u64, available_from: u64, incarnation: u64) -> Vec<u64> {
        let mut out = Vec::new();
        s.file(first_k, (first_k..first_k + n).collect(), available_from, incarnation, &mut out);
        assert!(out.iter().all(|(k, x)| k == x), "{out:?}");
        out.into_iter().map(|(k, _)| k).collect()
    }

    #[test]
    fn a_stream_puts_late_repeated_and_overlapping_batches_back_in_order() {
        let mut s = Stream::default();
        assert_eq!(file(&mut s, 0, 5, 0, 1), (0..5).collect::<Vec<_>>());
        // 10..15 and 15..20 arrive before 5..10: held, then released in order.
        assert!(file(&mut s, 10, 5, 0, 1).is_empty());
        assert!(file(&mut s, 15, 5, 5, 1).is_empty());
        assert_eq!(s.reordered, 2);
        assert_eq!(file(&mut s, 5, 5, 5, 1), (5..20).collect::<Vec<_>>());
        // Sent again: nothing new. Overlapping: only what is new.
        assert!(file(&mut s, 10, 5, 5, 1).is_empty());
        assert_eq!(s.duplicates, 1);
        assert_eq!(file(&mut s, 18, 4, 18, 1), vec![20, 21]);
        assert!(s.gaps.is_empty());
        assert_eq!(s.end, 22);
    }

    #[test]
    fn steps_the_sender_can_no_longer_deliver_become_a_marked_gap() {
        let mut s = Stream::default();
        file(&mut s, 0, 10, 0, 1);
        // The sender dropped 10..30 from a full store; 40..45 came before 30..40.
        assert!(file(&mut s, 40, 5, 30, 1).is_empty());
        assert_eq!(s.gaps, vec![Gap { from: 10, to: 30, why: "dropped by the sender" }]);
        assert_eq!(file(&mut s, 30, 10, 30, 1), (30..45).collect::<Vec<_>>());
        // A restarted process (new incarnation) resumes at step 60.
        assert_eq!(file(&mut s, 60, 5, 60, 2), (60..65).collect::<Vec<_>>());
        assert_eq!(s.gaps[1], Gap { from: 45, to: 60, why: "restarted" });
        assert_eq!(s.lost_steps(), 35);
    }

    fn sample(k: u64) -> FollowerSample {
        FollowerSample {
            k,
            pose: Default::default(),
            velocity: Default::default(),
            velocity_estimate: Default::default(),
            estimate: Default::default(),
            command: Default::default(),
            torque_l: 0.0,
            torque_r: 0.0,
        }
    }

    /// A recorder of the paper scenario cut to 10 steps, in a temporary folder.
    fn paper_recorder() -> (tempfile::TempDir, Scenario, Recorder) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        let scenario = Scenario::load(&path, &["duration=0.01".to_string()]).expect("scenario");
        let dir = tempfile::tempdir().expect("tempdir");
        let opts = RecordOptions { dir: dir.path().join("run"), every: 1, csv: true, mcap: false };
        let r = Recorder::new(&scenario, &opts).expect("recorder");
        (dir, scenario, r)
    }

    #[test]
    fn a_forged_batch_of_another_length_does_not_desynchronise_the_recorder() {
        let (_dir, scenario, mut r) = paper_recorder();
        let steps = scenario.steps();
        let leader = |first_k: u64, n: u64, done: bool| {
            codec::encode(&Telemetry::Leader {
                first_k,
                states: vec![LeaderState::default(); n as usize],
                counters: Counters::default(),
                done,
                loop_stats: None,
                delivery: Delivery::default(),
            })
        };
        let slots = |id: u32| scenario.sources_of(scenario.index_of(id).expect("a follower")).len();
        let follower = |id: u32, first_k: u64, samples: Vec<FollowerSample>, done: bool| {
            codec::encode(&Telemetry::Follower {
                id,
                first_k,
                heard: HeardRuns::uniform(slots(id), samples.len() as u32, Heard::Age(0)),
                rescued: Vec::new(),
                resumed: None,
                diverged: None,
                samples,
                counters: Counters::default(),
                done,
                loop_stats: None,
                delivery: Delivery::default(),
                events: Vec::new(),
                clock: None,
                links: Vec::new(),
            })
        };
        r.telemetry(Some(0), &leader(0, steps + 1, true), Instant::now()).unwrap();
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        // Forged: the expected first step, but 2 samples instead of the whole batch; then a NaN sample.
        r.telemetry(Some(ids[0]), &follower(ids[0], 0, (0..2).map(sample).collect(), false), Instant::now()).unwrap();
        let mut nan = sample(2);
        nan.torque_l = f64::NAN;
        r.telemetry(Some(ids[0]), &follower(ids[0], 2, vec![nan], false), Instant::now()).unwrap();
        // Forged: beyond the run's end, claiming done.
        r.telemetry(
            Some(ids[0]),
            &follower(ids[0], steps, (steps..steps + 3).map(sample).collect(), true),
            Instant::now(),
        )
        .unwrap();
        assert_eq!(r.malformed, 2);
        assert_eq!(r.followers[0].next_k + r.followers[0].pending.len() as u64, 2);
        assert!(!r.nodes[&ids[0]].done, "a rejected batch must not set done");
        // The genuine batches, overlapping the forged one, still complete the run.
        for &id in &ids {
            r.telemetry(Some(id), &follower(id, 0, (0..=steps).map(sample).collect(), true), Instant::now()).unwrap();
        }
        assert!(r.complete());
        assert_eq!(r.recorded_steps(), steps + 1);
    }

    #[test]
    fn an_interrupted_run_writes_a_summary_that_says_who_is_short() {
        let (_dir, scenario, mut r) = paper_recorder();
        let steps = scenario.steps();
        let states = vec![LeaderState::default(); steps as usize + 1];
        let leader = Telemetry::Leader {
            first_k: 0,
            states,
            counters: Counters::default(),
            done: true,
            loop_stats: None,
            delivery: Delivery::default(),
        };
        r.telemetry(Some(0), &codec::encode(&leader), Instant::now()).unwrap();
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        // The third follower stops after 4 of the steps + 1 samples.
        for &id in &ids {
            let n = if id == ids[2] { 4 } else { steps + 1 };
            let samples = (0..n).map(sample).collect();
            let slots = scenario.sources_of(scenario.index_of(id).expect("a follower")).len();
            let batch = Telemetry::Follower {
                id,
                first_k: 0,
                heard: HeardRuns::uniform(slots, n as u32, Heard::Age(0)),
                rescued: Vec::new(),
                resumed: None,
                diverged: None,
                samples,
                counters: Counters::default(),
                done: false,
                loop_stats: None,
                delivery: Delivery::default(),
                events: Vec::new(),
                clock: None,
                links: Vec::new(),
            };
            r.telemetry(Some(id), &codec::encode(&batch), Instant::now()).unwrap();
        }
        let (summary, dir) = r.finish(Ending::Interrupted).expect("partial run written");
        assert!(!summary.complete);
        let short: Vec<_> = summary.incomplete.iter().map(|(&id, s)| (id, s.recorded, s.expected)).collect();
        assert_eq!(short, vec![(ids[2], 4, steps + 1)], "followers short (id, recorded, expected)");
        let m = &summary.followers[&ids[2]];
        assert_eq!((m.formation_final, m.estimator_error_final), (None, None), "no sample at t = T: {m:?}");
        assert!(summary.followers[&ids[0]].formation_final.is_some(), "{:?}", summary.followers[&ids[0]]);
        let json = std::fs::read_to_string(dir.join("summary.json")).unwrap();
        assert!(json.contains("\"complete\": false"), "{json}");
    }
}
