//! A networked run's record ([`Recorder`]), independent of zenoh: fed
//! telemetry payloads and the time (the monitor), or a run's steps
//! re-computed (a replay, a playback), it puts each node's batches back in
//! step order, pairs every follower's sample with the leader's state of
//! its step, and writes the run folder (rows, `summary.json`,
//! `network.json`, `hearing.bin`). The rows go to its viewers as well,
//! through [`LiveSink`] (the Foxglove server): it knows no server.
//!
//! | module | its job |
//! | --- | --- |
//! | `stream` | one node's batches put back in step order, and checked |
//! | `network_json` | `network.json` |
//! | `live` | the monitor's live line and the live page's JSON |
//! | [`health`] | the run's verdict: healthy, degraded, and why |
//! | [`watch`] | when the run started, when it is over and how it ended |
//! | [`period`] | whether a real-time run kept its period (judged or not) |
//!
//! It never imports a node (the monitor, the agent, the leader), zenoh or
//! tokio: `formation replay` writes its folder with the same code, without
//! a network stack.
//!
//! # Examples
//!
//! When a monitored run is over ([`watch::Watch`]): complete once the
//! record holds every node's last step; idle only after its timeout of
//! silence, where a gap between two looks counts at most [`watch::LOOK_CAP`]
//! (a monitor that was not scheduled for a minute says nothing of the others).
//!
//! ```
//! use std::time::{Duration, Instant};
//! use formation_recorder::watch::{Ending, Watch};
//!
//! let t0 = Instant::now();
//! let s = |secs: f64| t0 + Duration::from_secs_f64(secs);
//! let mut watch = Watch::new(t0, t0, Duration::from_secs(10));
//! assert_eq!(watch.on_start(s(1.5)), 1.5, "startup_s");
//! assert_eq!(watch.on_tick(s(61.5)), None, "a minute unscheduled counts 4 s");
//! assert_eq!(watch.on_tick(s(65.0)), None);
//! assert_eq!(watch.on_tick(s(69.0)), Some(Ending::Idle), "11.5 s of silence");
//! assert_eq!(watch.on_telemetry(s(70.0), true), Some(Ending::Complete));
//! ```

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use formation_control::Slots;
use formation_leader::LeaderState;
use formation_plant::Pose;
use formation_record::hearing::{Density, End, FollowerHearing, HearingRecord, Rescued, Resume, ScenarioSource};
use formation_record::{
    FollowerSample, Heard, LiveSink, MetricsAccumulator, Proximity, RecordOptions, Row, RunWriter, Summary,
    HEARING_FILE,
};

/// A live leader's steps kept for the model of its run (48 bytes each):
/// beyond, the run is not judged against a model (a model that long is not
/// run at the run's end either).
const LIVE_MODEL_STEPS: u64 = 3_000_001;

/// A step some follower's pose is missing from is measured with the poses
/// that are in once it is this far behind the newest.
const PROXIMITY_BEHIND: u64 = 10_000;
use formation_scenario::Scenario;
use serde_json::json;

use crate::health::{ControlWatch, Evidence, Health, HearingEvidence};
use crate::watch::Ending;
use formation_protocol::barrier;
use formation_protocol::codec;
use formation_protocol::counters::Counters;
use formation_protocol::loop_timing::LoopStats;
use formation_protocol::telemetry::{
    Ack, ClockReport, Delivery, EventKind, Handover, Left, LinkStats, NetEvent, Telemetry, Term, MAX_LEFT_WHY,
};
use stream::{check_batch, Stream};

pub mod health;
mod live;
mod network_json;
pub mod period;
mod stream;
pub mod watch;

pub use stream::Gap;

/// What the monitor knows of one node (0: the leader) from its telemetry.
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
    timeline: BTreeSet<NetEvent>,
    /// When its last checked batch arrived.
    heard: Option<Instant>,
}

/// Rescued messages taken from one batch, and held in all.
const MAX_RESCUED_PER_BATCH: usize = 4096;
const MAX_RESCUED: usize = 1 << 20;

/// Events taken from one batch (a forged batch cannot fill the monitor's memory).
const MAX_EVENTS_PER_BATCH: usize = 256;
/// The most handovers a monitor keeps (a forger's flood of them is cut).
const MAX_HANDOVERS: usize = 16;

/// One leader's term as the monitor heard it (docs/model.md §14): the steps
/// its telemetry covered, whether a standby led it (the handover), and the
/// step at which it stood down, having heard a higher term.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TermRecord {
    pub number: u32,
    pub first_k: u64,
    /// One past the last step its telemetry held.
    pub end_k: u64,
    pub handover: Option<Handover>,
    pub stood_down_at: Option<u64>,
}

impl Recorder {
    /// Notes a leader batch's term; whether its states are to be filed:
    /// not those of a term lower than one heard (a leader that a standby
    /// took the run over from, its record arriving late; the states of a
    /// step are the same from either, bit for bit, as the trajectory is).
    fn note_term(&mut self, term: Term, first_k: u64, end_k: u64, handover: Option<Handover>) -> bool {
        let highest = self.terms.iter().map(|t| t.number).max().unwrap_or(0);
        let room = self.terms.len() < MAX_HANDOVERS;
        match self.terms.iter_mut().find(|t| t.number == term.number) {
            Some(t) => {
                (t.first_k, t.end_k) = (t.first_k.min(first_k), t.end_k.max(end_k));
                t.handover = t.handover.or(handover);
                t.stood_down_at = t.stood_down_at.or(term.stood_down_at);
            }
            None if room => {
                let stood_down_at = term.stood_down_at;
                self.terms.push(TermRecord { number: term.number, first_k, end_k, handover, stood_down_at });
                self.terms.sort_by_key(|t| t.number);
            }
            None => {}
        }
        if let Some(k) = term.stood_down_at {
            let line = format!(
                "the leader of term {} stood down at t = {:.3} s, having heard a higher term",
                term.number,
                k as f64 * self.scenario.dt_s
            );
            if !self.news.contains(&line) {
                self.news.push(line);
            }
        }
        term.number >= highest
    }
}

/// A checked batch's bookkeeping: what every node's telemetry carries
/// besides its steps.
struct Batch {
    /// When it arrived.
    now: Instant,
    /// Its size on the wire.
    bytes: usize,
    first_k: u64,
    counters: Counters,
    done: bool,
    loop_stats: Option<LoopStats>,
    delivery: Delivery,
}

impl NodeStats {
    /// Files a checked batch's bookkeeping.
    fn note(&mut self, b: &Batch) {
        self.messages += 1;
        self.bytes += b.bytes as u64;
        self.heard = Some(b.now);
        self.done |= b.done;
        let at = (b.delivery.incarnation, b.first_k);
        if self.newest.is_none_or(|n| at >= n) {
            self.newest = Some(at);
            self.counters = b.counters;
            self.delivery = b.delivery;
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
        self.loop_stats = b.loop_stats.filter(finite).or(self.loop_stats);
    }
}

/// One follower's record: its samples in step order, paired with the
/// leader's state of their step.
struct FollowerTrack {
    id: u32,
    /// Its offsets over the run (in the scenario's `control.frame`).
    slots: Slots,
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
    /// The robot's last recorded pose (with `[safety]`): where one that left stands.
    last_pose: Option<Pose>,
    /// Where a killed one stands (its pose of L − 2, as the others heard
    /// it; its telemetry may end earlier), preferred to `last_pose`.
    stands: Option<Pose>,
    /// It left the run for good before this step, and why (its last batch said).
    left: Option<Left>,
}

/// The leader's states kept for a follower absent from the start, which
/// may join with its first batch: this many seconds behind the newest (s).
const JOIN_WINDOW_S: f64 = 5.0;

/// Why a follower absent from a quorum start "left" (before step 0).
pub const ABSENT: &str = "absent at the start";

/// Why a follower killed in lock-step left (formation_protocol::died).
pub const KILLED: &str = "killed: its process ended unannounced";

impl FollowerTrack {
    /// One past the last step it takes: the run's, or the one it left before.
    fn end_k(&self, steps: u64) -> u64 {
        self.left.as_ref().map_or(steps + 1, |l| l.at_k.min(steps + 1))
    }
}

/// The monitor's bookkeeping, independent of zenoh (fed with telemetry payloads).
/// `network_json` writes its `network.json`, `live` its
/// live page's frames.
pub struct Recorder {
    scenario: Scenario,
    writer: RunWriter,
    followers: Vec<FollowerTrack>,
    leader_stream: Stream<LeaderState>,
    /// Standby leaders that took the run over (docs/model.md §14).
    pub(crate) handovers: Vec<Handover>,
    /// The leaders' terms heard, lowest first (docs/model.md §14).
    pub(crate) terms: Vec<TermRecord>,
    /// Who came and went, as it was learnt: one line each, until taken.
    news: Vec<String>,
    /// Followers taken for gone after `network.gone_after` of silence.
    gone: BTreeSet<u32>,
    /// Lock-step: followers killed, and the step their links are cut from
    /// (named by the monitor, formation_protocol::died).
    died: BTreeMap<u32, u64>,
    /// Followers absent at the start (a quorum start).
    absent_at_start: Vec<u32>,
    /// Absent followers that joined later (real time): id, the first step
    /// they took.
    pub(crate) joined: Vec<(u32, u64)>,
    /// Leader states of steps `leader_base`.. (None: lost).
    leader: VecDeque<Option<LeaderState>>,
    leader_base: u64,
    /// The leader as its scenario steps it, at step `model_k`: the state a
    /// follower's row pairs with where the leader's own is missing (the
    /// leader killed, a gap in its telemetry). The leader is a trajectory,
    /// so this is the state it had or would have had; before, those rows
    /// were dropped though their samples had arrived.
    model_leader: formation_leader::Leader,
    /// A leader steered live: its states from step 0, as far as none is missing.
    live_leader: Vec<LeaderState>,
    model_k: u64,
    nodes: BTreeMap<u32, NodeStats>,
    malformed: u64,
    /// Of those, by the key they came on (`telemetry/<id>`; None: not a number).
    malformed_by_key: BTreeMap<Option<u32>, u64>,
    /// Puts from other processes on the run's control keys.
    pub control: ControlWatch,
    /// The model's formation error per follower (or why it was not run):
    /// with it, `finish` writes network.json's `health`.
    model: Option<Result<BTreeMap<u32, Option<f64>>, String>>,
    /// Telemetry messages dropped on arrival (the queue was full).
    pub queue_dropped: u64,
    /// What every node's access control refused (formation_protocol::denied).
    pub denied: formation_protocol::denied::Table,
    /// Wall clock: the monitor's start to the leader's start, and the start
    /// to the end of the record (network.json's `wall`).
    startup_s: Option<f64>,
    run_s: Option<f64>,
    /// Viewers of the rows and events as they are recorded (`--foxglove`).
    sinks: Vec<Arc<dyn LiveSink>>,
    /// The leader's recorded steps, as spans [from, to).
    leader_spans: Vec<(u64, u64)>,
    /// Messages rescued by their receivers, by (sender, stamp).
    rescued: BTreeMap<(u32, u64), Rescued>,
    /// The scenario as the run loaded it: with it, `hearing.bin` is written.
    source: Option<ScenarioSource>,
    density: Density,
    /// How close the robots came (a scenario with `safety.distance`), and
    /// each step's poses until every follower's is in.
    pub(crate) proximity: Option<Proximity>,
    step_poses: BTreeMap<u64, Vec<Option<Pose>>>,
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
                slots: scenario.slots(index),
                stream: Stream::for_batches_of(scenario.network.telemetry_batch as usize),
                hearing: FollowerHearing::new(f.id, scenario.sources_of(index)),
                pending: VecDeque::new(),
                next_k: 0,
                unpaired: 0,
                metrics: MetricsAccumulator::for_scenario(scenario),
                formation_error: f64::NAN,
                latest: None,
                last_pose: None,
                stands: None,
                left: None,
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
            handovers: Vec::new(),
            terms: Vec::new(),
            news: Vec::new(),
            gone: BTreeSet::new(),
            died: BTreeMap::new(),
            absent_at_start: Vec::new(),
            joined: Vec::new(),
            leader: VecDeque::new(),
            leader_base: 0,
            model_leader: scenario.leader(),
            live_leader: Vec::new(),
            model_k: 0,
            nodes,
            malformed: 0,
            malformed_by_key: BTreeMap::new(),
            control: Default::default(),
            model: None,
            queue_dropped: 0,
            denied: Default::default(),
            startup_s: None,
            run_s: None,
            sinks: Vec::new(),
            leader_spans: Vec::new(),
            rescued: BTreeMap::new(),
            source: None,
            density: Density { every: opts.every.max(1), csv: opts.csv, mcap: opts.mcap },
            proximity: scenario.safety_distance.map(|d| {
                Proximity::new(d, scenario.control.guard.safety.is_some())
                    .with_shape_changes(scenario.shapes.iter().map(|c| c.at_s))
            }),
            step_poses: BTreeMap::new(),
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
        if let (Some(s), true) = (state, self.scenario.leader_profile.is_live()) {
            // The model of a live leader's run is its record (docs/model.md §18).
            if self.live_leader.len() as u64 == k && k < LIVE_MODEL_STEPS {
                self.live_leader.push(*s);
            }
        }
        if let Some(s) = state {
            match self.leader_spans.last_mut() {
                Some(span) if span.1 == k => span.1 = k + 1,
                _ => self.leader_spans.push((k, k + 1)),
            }
            // A live leader's every row: its record is what plays the run again (§18).
            let live = self.scenario.leader_profile.is_live();
            if self.writer.wants(k, k == self.scenario.steps()) || (live && self.writer.csv()) {
                self.writer.leader_row(k as f64 * self.scenario.dt_s, s)?;
            }
            for sink in &self.sinks {
                sink.leader(k, s);
            }
        }
        while self.leader_base + (self.leader.len() as u64) < k {
            self.push_leader(None);
        }
        self.push_leader(state.copied());
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
        let f = &mut self.followers[index];
        for r in resumes {
            f.hearing.resumed(*r);
        }
        // A follower that left (or was absent) is one in the replay too;
        // one killed, with the steps lost with its process in a gap.
        if let End::Left { k, why } = &end {
            f.left = Some(Left { at_k: *k, why: why.clone() });
            if why == KILLED {
                f.metrics.gap_to(*k);
                self.died.insert(f.id, *k);
            }
        }
        f.hearing.end = end;
    }

    /// A replay: where killed follower `index`'s robot stands (its pose of
    /// L − 2, which the replay computed), as the run's monitor heard it.
    pub fn replayed_stands(&mut self, index: usize, pose: Pose) {
        self.followers[index].stands = Some(pose);
    }

    /// A replay: the followers that joined late, as the run recorded them.
    pub fn replayed_joins(&mut self, joins: &[(u32, u64)]) {
        self.joined = joins.to_vec();
    }

    /// A replay: rows for every sample whose leader state is known.
    pub fn settle(&mut self) -> std::io::Result<()> {
        self.process()
    }

    /// Sends every row and network event from now on to `sink` as well.
    pub fn add_sink(&mut self, sink: Arc<dyn LiveSink>) {
        self.sinks.push(sink);
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
    pub fn health(&self, summary: &Summary) -> Option<Health> {
        let model = self.model.as_ref()?;
        let dt = self.scenario.dt_s;
        let mut e = Evidence { steps: self.scenario.steps(), dt_s: dt, ..Default::default() };
        e.too_close = summary.safety.as_ref().and_then(Proximity::violation_text);
        let left = self.left();
        // A follower that left is short only of what it took before leaving.
        let expected = |id: u32, s: &formation_record::Shortfall| {
            left.iter().find(|l| l.0 == id).map_or(s.expected, |l| l.1.min(s.expected))
        };
        e.short = summary
            .incomplete
            .iter()
            .filter(|(&id, s)| s.recorded + s.in_gaps < expected(id, s))
            .map(|(&id, s)| s.describe(id, dt, self.scenario.duration_s))
            .collect();
        let gone: Vec<u32> = left.iter().map(|l| l.0).collect();
        e.cut_off = if gone.is_empty() { Vec::new() } else { self.scenario.graph.unreachable_without(&gone) };
        e.left = left.into_iter().map(|(id, k, why)| (id, k as f64 * dt, why)).collect();
        e.joined = self.joined.iter().map(|&(id, k)| (id, k as f64 * dt)).collect();
        self.realtime_evidence(&mut e);
        let mut invalid = 0;
        for (&id, n) in &self.nodes {
            invalid += n.counters.rejected.invalid();
            if id == 0 {
                continue;
            }
            let mut open = None;
            for ev in &n.timeline {
                match ev.what {
                    EventKind::Isolated => {
                        open.get_or_insert(ev.k);
                    }
                    EventKind::Rejoined => {
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
                e.clock_uncertainty_us.push((id, c.uncertainty_us));
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
        // What the health line says after the count, for 1 and for more.
        e.refused = self.refused_counts(invalid);
        e.restarts = self
            .followers
            .iter()
            .filter(|f| !f.stream.restarts.is_empty())
            .map(|f| (format!("follower {}", f.id), f.stream.restarts.clone()))
            .collect();
        // A handover is a new leader process too: said once, as a handover.
        if self.leader_stream.restarts.len() > self.handovers.len() {
            e.restarts.push(("the leader".into(), self.leader_stream.restarts.clone()));
        }
        e.handovers = self.handovers.iter().map(|h| (h.heard, h.at_k)).collect();
        let leader = self.nodes.get(&0).map(|n| n.counters).unwrap_or_default();
        e.time_queries = (leader.time_queries, leader.time_queries_peak_per_s, self.scenario.followers.len() as u64);
        Some(crate::health::judge(&e))
    }

    /// Real time: a quarter step (the clocks' allowance) and, with a delay
    /// and no fault table, how the followers' hearing departed from the model.
    fn realtime_evidence(&self, e: &mut Evidence) {
        let (dt, delay_steps) = (self.scenario.dt_s, self.scenario.network.delay_steps);
        if self.scenario.timing == formation_scenario::Timing::Realtime {
            // As each follower judges its own (net's agent).
            let scale = formation_protocol::barrier::positive_scale(self.scenario.network.time_scale);
            e.quarter_step_us = dt / scale * 1e6 / 4.0;
            // Without a delay, real time mixes a neighbour's message of the
            // step and of the one before, which no model does (docs/lab.md).
            // With a fault table the followers' counts include what the
            // model loses too (`replay --explain` tells them apart).
            if delay_steps > 0 && self.scenario.faults.is_empty() {
                let g = &self.scenario.graph;
                let sources: u64 =
                    (0..g.len()).map(|i| g.neighbours(i).len() as u64 + u64::from(g.hears_leader(i))).sum();
                let followers = self.nodes.iter().filter(|(&id, _)| id != 0).map(|(_, n)| n.counters);
                let (older, silent) = followers.fold((0, 0), |(o, s), c| (o + c.older, s + c.silent));
                e.hearing = Some(HearingEvidence {
                    older,
                    silent,
                    link_steps: sources * (self.scenario.steps() + 1),
                    delay_steps,
                });
                let heard: Vec<&FollowerHearing> = self.followers.iter().map(|f| &f.hearing).collect();
                e.stalls = formation_record::stall::stalls(&heard, delay_steps);
            }
        }
    }

    /// The counts of what was refused or dropped on the way, as the health line names them.
    fn refused_counts(&self, invalid: u64) -> Vec<(String, u64)> {
        let counted = |n: u64, one: &str, more: &str| (if n == 1 { one } else { more }.to_string(), n);
        vec![
            counted(
                self.malformed,
                "telemetry message refused (malformed or on another's key)",
                "telemetry messages refused (malformed or on another's key)",
            ),
            counted(
                invalid,
                "estimate message refused by followers (malformed, forged or not a neighbour's)",
                "estimate messages refused by followers (malformed, forged or not a neighbour's)",
            ),
            counted(self.control.refused(), "put refused on control keys", "puts refused on control keys"),
            counted(
                self.queue_dropped,
                "telemetry message dropped by the monitor (queue full)",
                "telemetry messages dropped by the monitor (queue full)",
            ),
            counted(
                self.twins().len() as u64,
                "follower with a second sender on its key",
                "followers with a second sender on their key",
            ),
            counted(
                self.denied.rows().len() as u64,
                "message refused by access control",
                "messages refused by access control",
            ),
        ]
    }

    /// Files one telemetry message received on `telemetry/<key_id>` at `now`.
    pub fn telemetry(&mut self, key_id: Option<u32>, bytes: &[u8], now: Instant) -> std::io::Result<()> {
        let Some(t) = codec::decode::<Telemetry>(bytes) else {
            self.refuse(key_id, 1);
            return Ok(());
        };
        let bytes = bytes.len();
        match t {
            Telemetry::Leader { first_k, states, counters, done, loop_stats, delivery, handover, term } => {
                if let Some(h) = handover.filter(|h| key_id == Some(0) && h.at_k <= self.scenario.steps()) {
                    if !self.handovers.iter().any(|x| x.at_k == h.at_k) && self.handovers.len() < MAX_HANDOVERS {
                        self.handovers.push(h);
                        self.news.push(crate::health::handover_line(h.heard, h.at_k, self.scenario.dt_s));
                    }
                }
                // Each handover makes one more term: none beyond (a forger's).
                let genuine = (1..=1 + self.handovers.len() as u32).contains(&term.number);
                if key_id == Some(0) && !genuine {
                    self.refuse(key_id, 1);
                    return self.process();
                }
                let end_k = first_k.saturating_add(states.len() as u64);
                let current = key_id == Some(0) && self.note_term(term, first_k, end_k, handover);
                if key_id == Some(0) && !current {
                    // An old term's record: its bookkeeping, not its states.
                    return self.process();
                }
                let batch = Batch { now, bytes, first_k, counters, done, loop_stats, delivery };
                self.leader_batch(key_id, batch, states)?;
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
                left,
            } => {
                let Some(index) = self.scenario.index_of(id).filter(|_| key_id == Some(id)) else {
                    self.refuse(key_id, 1);
                    return Ok(());
                };
                // The batch's last step as sent (a diverged one is cut below).
                let last_k = first_k + samples.len().saturating_sub(1) as u64;
                let Some((samples, cut)) = self.check_follower_batch(index, first_k, samples, heard) else {
                    self.refuse(key_id, 1);
                    return Ok(());
                };
                self.refuse(key_id, u64::from(cut));
                self.back_from_gone(index);
                let joined_at = resumed.as_ref().map_or(first_k, |r| r.k).min(self.scenario.steps());
                self.join_if_absent(index, joined_at);
                let batch = Batch { now, bytes, first_k, counters, done, loop_stats, delivery };
                self.note_follower(index, &batch, clock, links);
                self.file_events(id, events);
                self.file_rescued(index, rescued);
                let steps = self.scenario.steps();
                let f = &mut self.followers[index];
                if let Some(r) = resumed.filter(|r| r.pose.iter().all(|x| x.is_finite()) && r.k <= steps) {
                    f.hearing.resumed(r);
                }
                // A leave is said once, with the last batch: its step within the run.
                let left = left.filter(|l| done && l.at_k <= steps && f.left.is_none());
                let mut said = None;
                if let Some(quantity) = diverged {
                    f.hearing.end = End::Diverged { k: last_k, quantity: quantity.chars().take(100).collect() };
                } else if let Some(l) = left {
                    let why: String = l.why.chars().filter(|c| !c.is_control()).take(MAX_LEFT_WHY).collect();
                    f.hearing.end = End::Left { k: l.at_k, why: why.clone() };
                    f.left = Some(Left { at_k: l.at_k, why: why.clone() });
                    said = Some((l.at_k, why));
                } else if done {
                    f.hearing.end = End::Completed;
                }
                if let Some((at_k, why)) = said {
                    let line = self.leave_line(id, at_k, &why);
                    self.news.push(line);
                }
                self.file_samples(index, &batch, samples);
            }
        }
        self.process()
    }

    /// A leader batch: its states filed in step order.
    fn leader_batch(&mut self, key_id: Option<u32>, b: Batch, states: Vec<LeaderState>) -> std::io::Result<()> {
        let steps = self.scenario.steps();
        // A sender's batches hold at most this many steps: a longer one is forged.
        let most = self.scenario.network.telemetry_batch.max(1) as usize;
        if key_id != Some(0) {
            self.refuse(key_id, 1);
            return Ok(());
        }
        let Some((states, cut)) = check_batch(states, b.first_k, steps, most, |_, s| s.is_finite()) else {
            self.refuse(key_id, 1);
            return Ok(());
        };
        self.refuse(key_id, u64::from(cut));
        let n = self.nodes.entry(0).or_default();
        n.note(&b);
        let mut fresh = Vec::new();
        self.leader_stream.file(b.first_k, states, b.delivery.available_from, b.delivery.incarnation, &mut fresh);
        n.samples += fresh.len() as u64;
        for (k, s) in fresh {
            self.file_leader(k, Some(&s))?;
        }
        while self.leader_base + (self.leader.len() as u64) < self.leader_stream.end {
            self.push_leader(None);
        }
        Ok(())
    }

    /// The next step's leader state for the followers' rows to pair with:
    /// its own, or where it has none, the scenario's ([`Recorder::model_leader`]).
    fn push_leader(&mut self, state: Option<LeaderState>) {
        if self.scenario.leader_profile.is_live() {
            // A leader steered live has no model: a step it did not
            // deliver stays unknown, and its followers' rows unpaired.
            self.leader.push_back(state);
            return;
        }
        let k = self.leader_base + self.leader.len() as u64;
        let dt = self.scenario.dt_s;
        while self.model_k < k {
            let s = self.model_leader.state(self.model_k as f64 * dt);
            self.model_leader.advance(&s, dt);
            self.model_k += 1;
        }
        let state = state.unwrap_or_else(|| self.model_leader.state(k as f64 * dt));
        self.leader.push_back(Some(state));
    }

    /// At the end: the followers' samples past the leader's last step (a
    /// leader that stopped before them) pair with the scenario's leader, a
    /// bounded number of steps at a time (a long run's leader that died
    /// early must not hold a state per remaining step at once).
    pub fn pair_past_the_leader(&mut self) -> std::io::Result<()> {
        const CHUNK: u64 = 65_536;
        let Some(last) = self.followers.iter().filter_map(|f| f.pending.back().map(|s| s.k)).max() else {
            return Ok(());
        };
        while self.leader_base + (self.leader.len() as u64) <= last {
            let to = (self.leader_base + self.leader.len() as u64 + CHUNK).min(last + 1);
            while self.leader_base + (self.leader.len() as u64) < to {
                self.push_leader(None);
            }
            self.process()?;
            // Nothing more arrives: a state no pending sample needs goes
            // (`process` keeps those a follower that stopped early might).
            let need = self.followers.iter().filter_map(|f| f.pending.front().map(|s| s.k)).min().unwrap_or(to);
            while self.leader_base < need && !self.leader.is_empty() {
                self.leader.pop_front();
                self.leader_base += 1;
            }
        }
        Ok(())
    }

    /// Follower `index`'s samples, each with what it heard, checked against
    /// the run (None: refused whole) and cut at the first bad one (`true`
    /// with the samples kept); the number of samples as sent is the
    /// length before the cut.
    #[allow(clippy::type_complexity)]
    fn check_follower_batch(
        &self,
        index: usize,
        first_k: u64,
        samples: Vec<FollowerSample>,
        heard: formation_record::HeardRuns,
    ) -> Option<(Vec<(FollowerSample, Box<[Heard]>)>, bool)> {
        // The hearing record covers the batch's steps, one entry per source
        // (none with `network.hearing_record = false`).
        let slots = self.followers[index].hearing.sources.len();
        let (want_steps, want_slots) =
            if self.scenario.network.hearing_record { (samples.len(), slots) } else { (0, 0) };
        if heard.steps as usize != want_steps || heard.slots.len() != want_slots || !heard.is_consistent() {
            return None;
        }
        let mut per_step = heard.expand().into_iter().map(Vec::into_boxed_slice);
        let samples: Vec<_> = samples.into_iter().map(|s| (s, per_step.next().unwrap_or_default())).collect();
        let ok = |k: u64, (s, _): &(FollowerSample, Box<[Heard]>)| s.k == k && s.is_finite();
        let most = self.scenario.network.telemetry_batch.max(1) as usize;
        check_batch(samples, first_k, self.scenario.steps(), most, ok)
    }
    /// Files follower `index`'s batch bookkeeping, and from its newest
    /// batch its estimate of the leader's clock and its links' figures.
    fn note_follower(&mut self, index: usize, b: &Batch, clock: Option<ClockReport>, links: Vec<LinkStats>) {
        let g = &self.scenario.graph;
        let n = self.nodes.entry(self.followers[index].id).or_default();
        n.note(b);
        if n.newest == Some((b.delivery.incarnation, b.first_k)) {
            n.clock = clock.filter(|c| c.offset_ms.is_finite() && c.uncertainty_us.is_finite()).or(n.clock);
            // A forged batch cannot fill the monitor's memory: one entry per source.
            let sources = g.neighbours(index).len() + usize::from(g.hears_leader(index));
            if links.len() <= sources {
                n.links = links;
            }
        }
    }

    /// Files what the network did to follower `id`, as it noticed it.
    fn file_events(&mut self, id: u32, events: Vec<NetEvent>) {
        let n = self.nodes.entry(id).or_default();
        // A batch sent again repeats its events: a set keeps each once.
        for e in events.into_iter().take(MAX_EVENTS_PER_BATCH) {
            if n.timeline.insert(e) {
                for sink in &self.sinks {
                    sink.event(&id.to_string(), e.k, &e.what.describe());
                }
            }
        }
    }

    /// Files the messages follower `index`'s sources sent that it rescued
    /// (a forged batch cannot fill the monitor's memory).
    fn file_rescued(&mut self, index: usize, rescued: Vec<Rescued>) {
        let steps = self.scenario.steps();
        let sources = &self.followers[index].hearing.sources;
        for r in rescued.into_iter().take(MAX_RESCUED_PER_BATCH) {
            let ok = sources.contains(&r.source) && r.stamp <= steps && r.state.is_finite();
            if ok && self.rescued.len() < MAX_RESCUED {
                self.rescued.entry((r.source, r.stamp)).or_insert(r);
            }
        }
    }

    /// Files follower `index`'s checked samples into its stream; those now
    /// in step order wait for the leader's state of their step.
    fn file_samples(&mut self, index: usize, b: &Batch, samples: Vec<(FollowerSample, Box<[Heard]>)>) {
        let recording = self.scenario.network.hearing_record;
        let f = &mut self.followers[index];
        let mut fresh = Vec::new();
        f.stream.file(b.first_k, samples, b.delivery.available_from, b.delivery.incarnation, &mut fresh);
        self.nodes.entry(f.id).or_default().samples += fresh.len() as u64;
        for (k, (sample, heard)) in fresh {
            if recording {
                f.hearing.push(k, &heard);
            }
            f.pending.push_back(sample);
        }
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
                let row = Row::new(&sample, &l, self.scenario.control.frame, f.slots.at(k), dt);
                f.metrics.push(k, &row, sample.guard.as_ref());
                if self.proximity.is_some() {
                    let n = self.scenario.followers.len();
                    self.step_poses.entry(k).or_insert_with(|| vec![None; n])[index] = Some(sample.pose);
                    f.last_pose = Some(sample.pose);
                }
                f.formation_error = row.formation_error;
                f.latest = Some((row, l));
                if self.writer.wants(k, k == steps) {
                    self.writer.follower_row(index, &row)?;
                }
                for sink in &self.sinks {
                    sink.follower(index, k, &row);
                }
            }
            if f.pending.is_empty() {
                f.next_k = f.next_k.max(f.stream.end.min(leader_end));
            }
        }
        // Leader states every follower has used are no longer needed. One
        // that left for good (it said so) or was absent from the start sends
        // nothing older than now: it holds none back, but an absent one may
        // join at the step then due, so the last JOIN_WINDOW stay for it.
        let (gone, absent) = (&self.gone, &self.absent_at_start);
        let waits = |f: &&FollowerTrack| f.left.is_none() || gone.contains(&f.id) || !f.pending.is_empty();
        let mut used = self
            .followers
            .iter()
            .filter(waits)
            .map(|f| f.pending.front().map_or(f.next_k, |s| s.k))
            .min()
            .unwrap_or(leader_end);
        if self.followers.iter().any(|f| f.left.is_some() && absent.contains(&f.id)) {
            used = used.min(leader_end.saturating_sub((JOIN_WINDOW_S / dt).round() as u64));
        }
        while self.leader_base < used && !self.leader.is_empty() {
            self.leader.pop_front();
            self.leader_base += 1;
        }
        self.measure_proximity(false);
        Ok(())
    }

    /// Steps whose every robot's pose is in go to the proximity measure; so
    /// do, with the poses that are in, steps no follower can still fill
    /// (each is past it) or [`PROXIMITY_BEHIND`] steps behind the newest,
    /// and at the end (`all`) every step left.
    fn measure_proximity(&mut self, all: bool) {
        let Some(p) = self.proximity.as_mut() else { return };
        let filled = self.followers.iter().map(|f| f.next_k).min().unwrap_or(0);
        let newest = self.step_poses.last_key_value().map_or(0, |(&k, _)| k);
        let ids: Vec<u32> = self.followers.iter().map(|f| f.id).collect();
        // A robot that does not run is still there (docs/model.md §16): one
        // absent at the start at its initial pose, one that left at its last
        // recorded pose, from the step it left on.
        let still: Vec<Option<(u64, Pose)>> = self
            .followers
            .iter()
            .zip(&self.scenario.followers)
            .map(|(f, spec)| {
                let l = f.left.as_ref()?;
                let pose = if l.at_k == 0 { Some(spec.pose) } else { f.stands.or(f.last_pose) };
                pose.map(|p| (l.at_k, p))
            })
            .collect();
        let (mut have_ids, mut have) = (Vec::new(), Vec::new());
        while let Some(entry) = self.step_poses.first_entry() {
            let k = *entry.key();
            let complete = entry.get().iter().all(Option::is_some);
            if !(all || complete || k < filled || k + PROXIMITY_BEHIND < newest) {
                break;
            }
            let poses = entry.remove();
            have_ids.clear();
            have.clear();
            for ((&id, pose), still) in ids.iter().zip(&poses).zip(&still) {
                let held = still.filter(|&(at_k, _)| k >= at_k).map(|(_, p)| p);
                if let Some(pose) = pose.or(held) {
                    have_ids.push(id);
                    have.push(pose);
                }
            }
            p.push(k as f64 * self.scenario.dt_s, &have_ids, &have);
        }
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
            && self.followers.iter().all(|f| f.next_k >= f.end_k(steps) && f.pending.is_empty())
    }

    /// The followers the run started without (a quorum start): each as if
    /// it left before step 0 (no rows; its neighbours and the model cut its
    /// links from the start), and done: nothing more is waited for from it.
    pub fn absent(&mut self, ids: &[u32]) {
        self.absent_at_start = ids.to_vec();
        for f in self.followers.iter_mut().filter(|f| ids.contains(&f.id) && f.next_k == 0) {
            let why = ABSENT.to_string();
            f.hearing.end = End::Left { k: 0, why: why.clone() };
            f.left = Some(Left { at_k: 0, why });
            self.nodes.entry(f.id).or_default().done = true;
        }
    }

    /// "follower 3 left the run at t = 2.179 s (formation leave); every
    /// remaining follower still reaches the leader": Lemma 1 checked again
    /// on the graph without every follower gone so far.
    fn leave_line(&self, id: u32, at_k: u64, why: &str) -> String {
        let mut gone: Vec<u32> = self.left().iter().map(|l| l.0).collect();
        if !gone.contains(&id) {
            gone.push(id);
        }
        let cut = self.scenario.graph.unreachable_without(&gone);
        let reach = match cut.len() {
            0 => "every remaining follower still reaches the leader".to_string(),
            n => format!(
                "{}: {} estimates drift",
                formation_scenario::graph::no_longer_reach(&cut),
                if n == 1 { "its" } else { "their" }
            ),
        };
        format!("follower {id} left the run at t = {:.3} s ({why}); {reach}", at_k as f64 * self.scenario.dt_s)
    }

    /// `network.gone_after` (docs/model.md §14): a follower whose telemetry
    /// has been silent that long at `now` is taken for gone: it left the
    /// run where its record ends, and nothing more is waited for from it.
    /// Telemetry from it later takes that back ([`Recorder::telemetry`]).
    pub fn check_gone(&mut self, now: Instant) {
        let Some(after) = self.scenario.network.gone_after_s else { return };
        let steps = self.scenario.steps();
        let mut newly = Vec::new();
        for f in self.followers.iter_mut().filter(|f| f.left.is_none()) {
            let Some(n) = self.nodes.get_mut(&f.id).filter(|n| !n.done) else { continue };
            let Some(heard) = n.heard else { continue };
            if now.saturating_duration_since(heard).as_secs_f64() < after {
                continue;
            }
            let (at_k, why) = (f.stream.end.min(steps + 1), format!("silent for {after} s"));
            let why: String = why.chars().take(MAX_LEFT_WHY).collect();
            f.hearing.end = End::Left { k: at_k, why: why.clone() };
            f.left = Some(Left { at_k, why: why.clone() });
            n.done = true;
            newly.push((f.id, at_k, why));
        }
        for (id, at_k, why) in newly {
            self.gone.insert(id);
            let line = self.leave_line(id, at_k, &why);
            self.news.push(format!("{line} (taken for gone: network.gone_after)"));
        }
    }

    /// Whether follower `id` has nothing more to send: it left (or was
    /// absent, or taken for gone) or reported its final step.
    pub fn through(&self, id: u32) -> bool {
        let left = self.scenario.index_of(id).is_some_and(|i| self.followers[i].left.is_some());
        left || self.nodes.get(&id).is_some_and(|n| n.done)
    }

    /// Lock-step: follower `id` was killed, its links cut from step `at_k`
    /// as every node was told (formation_protocol::died): it left before
    /// `at_k` as far as its record goes, its steps not received by now are
    /// lost with its process (a gap, "killed"), nothing more is waited for
    /// from it, and the run's model is the row `{ node = id, from = at_k
    /// Δt, died = true }`; its robot stands at `stands` (its pose of
    /// `at_k` − 2, as its neighbours heard it) for the closest pair. A
    /// follower that already left or finished is not touched.
    pub fn died(&mut self, id: u32, at_k: u64, stands: Option<[f64; 3]>) {
        let steps = self.scenario.steps();
        let Some(i) = self.scenario.index_of(id) else { return };
        let f = &mut self.followers[i];
        if f.left.is_some() || self.nodes.get(&id).is_some_and(|n| n.done) {
            return;
        }
        let at_k = at_k.min(steps + 1);
        let why = KILLED.to_string();
        f.hearing.end = End::Left { k: at_k, why: why.clone() };
        f.left = Some(Left { at_k, why: why.clone() });
        f.stream.lose_to(at_k, "killed");
        f.metrics.gap_to(at_k);
        f.stands = stands.map(|[x, y, theta]| Pose::new(x, y, theta));
        self.nodes.entry(id).or_default().done = true;
        self.died.insert(id, at_k);
        let line = self.leave_line(id, at_k, &why);
        self.news.push(line);
        let _ = self.process();
    }

    /// Telemetry from follower `index`, absent at the start: it joined the
    /// run at step `k` (real time; docs/model.md §14), and is waited for
    /// from now on.
    fn join_if_absent(&mut self, index: usize, k: u64) {
        let f = &mut self.followers[index];
        if !f.left.as_ref().is_some_and(|l| l.at_k == 0 && l.why == ABSENT) {
            return;
        }
        f.left = None;
        f.hearing.end = End::Unknown;
        // Its steps before k were never to come: no gap, nothing lost.
        f.stream.skip_to(k);
        self.nodes.entry(f.id).or_default().done = false;
        let id = f.id;
        if !self.joined.iter().any(|j| j.0 == id) {
            self.joined.push((id, k));
            self.news.push(format!(
                "follower {id} joined the run at t = {:.3} s (absent at the start)",
                k as f64 * self.scenario.dt_s
            ));
        }
    }

    /// Telemetry from follower `index`, taken for gone: it is back.
    fn back_from_gone(&mut self, index: usize) {
        let f = &mut self.followers[index];
        if !self.gone.remove(&f.id) {
            return;
        }
        f.left = None;
        f.hearing.end = End::Unknown;
        self.nodes.entry(f.id).or_default().done = false;
        self.news.push(format!("follower {} is heard again: no longer taken for gone", f.id));
    }

    /// The end-of-run line on who took part, when anyone came or went:
    /// "members: followers 1, 2, 4 to the end; follower 3 joined at t =
    /// 8.594 s; follower 2 left at t = 5.000 s (SIGTERM); led by a standby
    /// from t = 10.503 s". None when everyone ran the whole run.
    pub fn membership_line(&self) -> Option<String> {
        let dt = self.scenario.dt_s;
        let left = self.left();
        if left.is_empty() && self.joined.is_empty() && self.handovers.is_empty() {
            return None;
        }
        let stayed: Vec<u32> =
            self.followers.iter().map(|f| f.id).filter(|id| !left.iter().any(|l| l.0 == *id)).collect();
        let mut parts = vec![format!("{} to the end", formation_scenario::graph::followers_named(&stayed))];
        for &(id, k) in &self.joined {
            parts.push(format!("follower {id} joined at t = {:.3} s", k as f64 * dt));
        }
        for (id, k, why) in &left {
            parts.push(match k {
                0 => format!("follower {id} {why}"),
                k => format!("follower {id} left at t = {:.3} s ({why})", *k as f64 * dt),
            });
        }
        for h in &self.handovers {
            parts.push(format!("led by a standby from t = {:.3} s", h.at_k as f64 * dt));
        }
        Some(format!("members: {}", parts.join("; ")))
    }

    /// Who came and went since the last call, a line each (leaves, handovers).
    pub fn take_news(&mut self) -> Vec<String> {
        std::mem::take(&mut self.news)
    }

    /// The followers that left the run for good: id, the first step not
    /// taken, and why.
    pub fn left(&self) -> Vec<(u32, u64, String)> {
        self.followers.iter().filter_map(|f| f.left.as_ref().map(|l| (f.id, l.at_k, l.why.clone()))).collect()
    }

    /// The scenario the run's model runs: the scenario, with each follower
    /// that left cut off from then on (docs/model.md §14's node fault), as
    /// its neighbours lived it.
    pub fn model_scenario(&self) -> Scenario {
        let leaves: Vec<(u32, u64)> =
            self.left().iter().filter(|l| !self.died.contains_key(&l.0)).map(|&(id, k, _)| (id, k)).collect();
        let died: Vec<(u32, u64)> = self.died.iter().map(|(&id, &k)| (id, k)).collect();
        let gaps: Vec<(u64, u64)> = self.handovers.iter().filter_map(Handover::gap).collect();
        let s = self.scenario.with_leaves(&leaves).with_died(&died).with_handovers(&gaps).with_joins(&self.joined);
        // A live leader: played from what it did, when every step of it arrived.
        match s.live_leader().is_some() && self.live_leader.len() as u64 == s.steps() + 1 {
            true => s.with_leader_states(self.live_leader.clone().into()),
            false => s,
        }
    }

    /// Steps recorded by every follower still in the run (one that left, or
    /// was absent from the start, has all it will have); every follower's
    /// most when none is left.
    pub fn recorded_steps(&self) -> u64 {
        let present = self.followers.iter().filter(|f| f.left.is_none()).map(|f| f.next_k).min();
        present.or_else(|| self.followers.iter().map(|f| f.next_k).max()).unwrap_or(0)
    }

    /// Nodes that have not reported their final step.
    pub fn unfinished(&self) -> Vec<String> {
        self.nodes
            .iter()
            .filter(|(_, n)| !n.done)
            .map(|(&id, _)| if id == 0 { "leader".to_string() } else { format!("follower {id}") })
            .collect()
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
            rescued: self.rescued.values().filter(|r| self.rescue_needed(r)).copied().collect(),
        })
    }

    /// Whether a replay needs a rescued message: only a follower's message
    /// of stamp s > 0 whose sender's step s − 1, which made it, is not in
    /// the record (a sender killed before its telemetry got out, or the
    /// message a lock-step restart resumes from). The leader's messages,
    /// the initial ones and those of a step the sender recorded, the replay
    /// computes itself; each follower's last batch rescues every source's
    /// last messages, and kept whole they were about 65 KB of the paper's
    /// 72 KB `hearing.bin`.
    fn rescue_needed(&self, r: &Rescued) -> bool {
        r.source != formation_protocol::wire::LEADER_ID
            && r.stamp > 0
            && self
                .scenario
                .index_of(r.source)
                .and_then(|i| self.followers.get(i))
                .is_none_or(|f| !f.hearing.covers(r.stamp - 1))
    }

    /// Writes `network.json` and `summary.json` (metrics of what was
    /// received) and moves the folder into place.
    pub fn finish(self, ending: Ending) -> std::io::Result<(Summary, PathBuf)> {
        self.finish_judged(ending).map(|(s, d, _)| (s, d))
    }

    /// [`Recorder::finish`], with the run's health when a model was set.
    pub fn finish_judged(mut self, ending: Ending) -> std::io::Result<(Summary, PathBuf, Option<Health>)> {
        self.pair_past_the_leader()?;
        self.measure_proximity(true);
        let metrics = self.followers.iter().map(|f| (f.id, f.metrics.finish())).collect();
        let outages = self.followers.iter().map(|f| (f.id, f.metrics.outages())).collect();
        let settling = self.followers.iter().map(|f| (f.id, f.metrics.settled_after())).collect();
        let mut summary =
            Summary::new(&self.scenario, metrics).with_outages(&self.scenario, &outages).with_settling(&settling);
        summary.safety = self.proximity.take();
        for (id, _, why) in self.left() {
            summary.mark_left(id, &why);
        }
        for &(id, k) in &self.joined {
            summary.mark_joined(id, k);
        }
        let health = self.health(&summary);
        self.writer.write_file("network.json", &self.network_json_with(ending, health.as_ref()))?;
        if let Some(record) = self.hearing_record() {
            self.writer.write_bytes(HEARING_FILE, &record.encode())?;
        }
        let dir = self.writer.finish(&summary)?;
        Ok((summary, dir, health))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_record::HeardRuns;

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
            guard: None,
        }
    }

    /// A recorder of the paper scenario cut to 10 steps, in a temporary folder.
    fn paper_recorder() -> (tempfile::TempDir, Scenario, Recorder) {
        recorder_with(&[])
    }

    /// Follower `id`'s batch of steps first_k..first_k + n, each heard
    /// fresh from every source.
    fn follower_batch(s: &Scenario, id: u32, first_k: u64, n: u64, done: bool, left: Option<Left>) -> Telemetry {
        follower_batch_of(s, id, first_k, (first_k..first_k + n).map(sample).collect(), done, left)
    }

    /// Follower `id`'s batch of `samples` from step first_k, each heard
    /// fresh from every source (a forged batch may say anything).
    fn follower_batch_of(
        s: &Scenario,
        id: u32,
        first_k: u64,
        samples: Vec<FollowerSample>,
        done: bool,
        left: Option<Left>,
    ) -> Telemetry {
        let slots = s.sources_of(s.index_of(id).expect("a follower")).len();
        Telemetry::Follower {
            id,
            first_k,
            heard: HeardRuns::uniform(slots, samples.len() as u32, Heard::Age(0)),
            rescued: Vec::new(),
            resumed: None,
            diverged: None,
            left,
            samples,
            counters: Counters::default(),
            done,
            loop_stats: None,
            delivery: Delivery::default(),
            events: Vec::new(),
            clock: None,
            links: Vec::new(),
        }
    }

    /// [`paper_recorder`] with more settings.
    fn recorder_with(sets: &[&str]) -> (tempfile::TempDir, Scenario, Recorder) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        let sets: Vec<String> = ["duration=0.01"].iter().chain(sets).map(|s| s.to_string()).collect();
        let scenario = Scenario::load(&path, &sets).expect("scenario");
        let dir = tempfile::tempdir().expect("tempdir");
        let opts = RecordOptions { dir: dir.path().join("run"), every: 1, csv: true, mcap: false, rosbag2: false };
        let r = Recorder::new(&scenario, &opts).expect("recorder");
        (dir, scenario, r)
    }

    /// docs/model.md §16: the monitor measures how close the robots came
    /// from every follower's samples of a step (a step one follower's
    /// sample is missing from, with the others'), names the pair in the
    /// summary and on the live page.
    #[test]
    fn the_monitor_names_the_closest_pair_and_a_step_below_the_safety_distance() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/turtlebot.toml");
        let scenario = Scenario::load(&path, &["duration=0.04".to_string()]).expect("scenario");
        let dir = tempfile::tempdir().expect("tempdir");
        let opts = RecordOptions { dir: dir.path().join("run"), every: 1, csv: true, mcap: false, rosbag2: false };
        let mut r = Recorder::new(&scenario, &opts).expect("recorder");
        let steps = scenario.steps();
        let leader = Telemetry::Leader {
            first_k: 0,
            states: vec![LeaderState::default(); steps as usize + 1],
            counters: Counters::default(),
            done: true,
            loop_stats: None,
            delivery: Delivery::default(),
            handover: None,
            term: Term { number: 1, stood_down_at: None },
        };
        r.telemetry(Some(0), &codec::encode(&leader), Instant::now()).unwrap();
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        for (i, &id) in ids.iter().enumerate() {
            // Robots 1 m apart on a line; at step 1 the second is 0.1 m from the first.
            let pose = |k: u64| {
                let x = if i == 1 && k == 1 { 0.1 } else { i as f64 };
                formation_plant::Pose::new(x, 0.0, 0.0)
            };
            // The last follower's last sample is lost.
            let n = if i == ids.len() - 1 { steps } else { steps + 1 };
            let samples = (0..n).map(|k| FollowerSample { pose: pose(k), ..sample(k) }).collect();
            let slots = scenario.sources_of(i).len();
            let batch = Telemetry::Follower {
                id,
                first_k: 0,
                heard: HeardRuns::uniform(slots, n as u32, Heard::Age(0)),
                rescued: Vec::new(),
                resumed: None,
                diverged: None,
                left: None,
                samples,
                counters: Counters::default(),
                done: true,
                loop_stats: None,
                delivery: Delivery::default(),
                events: Vec::new(),
                clock: None,
                links: Vec::new(),
            };
            r.telemetry(Some(id), &codec::encode(&batch), Instant::now()).unwrap();
        }
        let (frame, _) = r.live_frame(Instant::now(), 1, 0.0, "running", 0);
        let frame: serde_json::Value = serde_json::from_str(&frame).expect("a JSON frame");
        let violation = frame["safety"]["violation"].as_str().unwrap_or_default().to_string();
        assert!(violation.starts_with(&format!("robots {} and {} came 0.100 m apart", ids[0], ids[1])), "{frame}");
        let (summary, _) = r.finish(Ending::Interrupted).expect("finish");
        let p = summary.safety.expect("summary.json's safety");
        let closest = p.closest.expect("a closest pair");
        assert_eq!((closest.pair, closest.t, p.steps_below), ([ids[0], ids[1]], scenario.dt_s, 1), "{p:?}");
        drop(dir);
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
                handover: None,
                term: Term { number: 1, stood_down_at: None },
            })
        };
        let follower = |id: u32, first_k: u64, samples: Vec<FollowerSample>, done: bool| {
            codec::encode(&follower_batch_of(&scenario, id, first_k, samples, done, None))
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

    /// A leader that stopped at step 4 (killed) while the followers ran to
    /// the end: their rows are written, paired with the leader the scenario
    /// steps (they were dropped though they had arrived); its own rows end
    /// at step 4.
    #[test]
    fn followers_rows_past_a_stopped_leader_are_kept() {
        let (dir, scenario, mut r) = paper_recorder();
        let steps = scenario.steps();
        let mut model = scenario.leader();
        let states: Vec<LeaderState> = (0..5)
            .map(|k| {
                let s = model.state(k as f64 * scenario.dt_s);
                model.advance(&s, scenario.dt_s);
                s
            })
            .collect();
        let leader = Telemetry::Leader {
            first_k: 0,
            states,
            counters: Counters::default(),
            done: false,
            loop_stats: None,
            delivery: Delivery::default(),
            handover: None,
            term: Term { number: 1, stood_down_at: None },
        };
        r.telemetry(Some(0), &codec::encode(&leader), Instant::now()).unwrap();
        for f in &scenario.followers {
            let slots = scenario.sources_of(scenario.index_of(f.id).expect("a follower")).len();
            let batch = Telemetry::Follower {
                id: f.id,
                first_k: 0,
                heard: HeardRuns::uniform(slots, steps as u32 + 1, Heard::Age(0)),
                rescued: Vec::new(),
                resumed: None,
                diverged: None,
                left: None,
                samples: (0..=steps).map(sample).collect(),
                counters: Counters::default(),
                done: true,
                loop_stats: None,
                delivery: Delivery::default(),
                events: Vec::new(),
                clock: None,
                links: Vec::new(),
            };
            r.telemetry(Some(f.id), &codec::encode(&batch), Instant::now()).unwrap();
        }
        let (summary, out) = r.finish(Ending::Interrupted).expect("finish");
        let lines = |name: &str| std::fs::read_to_string(out.join(name)).expect(name).lines().count() as u64;
        for f in &scenario.followers {
            assert_eq!(
                lines(&format!("follower_{}.csv", f.id)),
                steps + 2,
                "follower {}: a header and every step",
                f.id
            );
        }
        assert_eq!(lines("leader.csv"), 1 + 5, "the leader's own rows only");
        assert!(summary.complete, "every follower's samples are recorded");
        drop(dir);
    }

    /// `network.gone_after`: a follower silent that long is taken for gone
    /// where its record ends (said once, not waited for); its telemetry
    /// later takes that back.
    #[test]
    fn a_silent_follower_is_taken_for_gone_and_back_when_heard() {
        let (_dir, scenario, mut r) = recorder_with(&["network.gone_after=2"]);
        let batch =
            |id: u32, first_k: u64, n: u64| codec::encode(&follower_batch(&scenario, id, first_k, n, false, None));
        let t0 = Instant::now();
        r.telemetry(Some(3), &batch(3, 0, 4), t0).unwrap();
        r.check_gone(t0 + std::time::Duration::from_millis(1999));
        assert!(r.left().is_empty() && r.take_news().is_empty(), "not before 2 s");
        r.check_gone(t0 + std::time::Duration::from_secs(2));
        assert_eq!(r.left(), vec![(3, 4, "silent for 2 s".to_string())]);
        let news = r.take_news();
        assert!(
            news.len() == 1 && news[0].starts_with("follower 3 left the run at t = 0.004 s (silent for 2 s)"),
            "{news:?}"
        );
        r.check_gone(t0 + std::time::Duration::from_secs(5));
        assert!(r.take_news().is_empty(), "said once");
        assert_eq!(
            r.membership_line().as_deref(),
            Some("members: followers 1, 2, 4 to the end; follower 3 left at t = 0.004 s (silent for 2 s)")
        );
        r.telemetry(Some(3), &batch(3, 4, 2), t0 + std::time::Duration::from_secs(6)).unwrap();
        assert!(r.left().is_empty(), "heard again: no longer gone");
        assert_eq!(r.take_news(), ["follower 3 is heard again: no longer taken for gone"]);
    }

    /// A standby's batches say when it took the run over: said once as
    /// news, in network.json's handovers and the leader's timeline, and its
    /// gap is the model's row `{ node = 0, from, to }` (real time).
    #[test]
    fn each_term_is_recorded_and_an_old_terms_late_record_files_no_states() {
        let (_dir, _scenario, mut r) = recorder_with(&["timing=realtime", "duration=0.1"]);
        let handover = Some(formation_protocol::telemetry::Handover { heard: Some(4), at_k: 7 });
        let batch = |first_k: u64, number: u32, stood_down_at: Option<u64>, v: f64| {
            let (incarnation, handover) = if number == 2 { (2, handover) } else { (1, None) };
            codec::encode(&Telemetry::Leader {
                first_k,
                states: vec![LeaderState { v, ..LeaderState::default() }; 5],
                counters: Counters::default(),
                done: false,
                loop_stats: None,
                delivery: Delivery { incarnation, available_from: first_k.min(5), ..Delivery::default() },
                handover,
                term: Term { number, stood_down_at },
            })
        };
        // Term 1 to step 5; the standby's term 2 from step 5; then term 1's
        // record of steps 10–14, ahead of term 2's (other states: a
        // forger's, or a bug), with its stand-down at step 12; a term no
        // handover made.
        let (old, forged) = (batch(10, 1, Some(12), 9.0), batch(15, 7, None, 9.0));
        for bytes in [batch(0, 1, None, 1.0), batch(5, 2, None, 2.0), old, forged] {
            r.telemetry(Some(0), &bytes, Instant::now()).unwrap();
        }
        let json: serde_json::Value = serde_json::from_str(&r.network_json(Ending::Complete)).expect("json");
        let terms = &json["terms"];
        assert_eq!(terms.as_array().map(Vec::len), Some(2), "{terms}");
        assert_eq!((terms[0]["term"].as_u64(), terms[0]["led_by"].as_str()), (Some(1), Some("the leader")), "{terms}");
        assert_eq!(terms[0]["stood_down_at_step"].as_u64(), Some(12), "{terms}");
        assert_eq!(terms[0]["to_step"].as_u64(), Some(14), "its record counts in its own term's steps: {terms}");
        assert_eq!((terms[1]["term"].as_u64(), terms[1]["led_by"].as_str()), (Some(2), Some("a standby")), "{terms}");
        assert_eq!(terms[1]["from_step"].as_u64(), Some(7), "term 2 from its takeover");
        let news = r.take_news();
        assert!(news.iter().any(|n| n.contains("the leader of term 1 stood down at t = 0.012 s")), "{news:?}");
        assert_eq!(r.malformed, 1, "the term no handover made is refused");
        let filed: Vec<f64> = r.leader.iter().flatten().map(|s| s.v).collect();
        assert_eq!(filed, [[1.0; 5], [2.0; 5]].concat(), "an old term's states and a forged term's are not filed");
    }

    #[test]
    fn a_handover_is_said_recorded_and_modelled() {
        let (_dir, scenario, mut r) = recorder_with(&["timing=realtime"]);
        let handover = Some(formation_protocol::telemetry::Handover { heard: Some(4), at_k: 7 });
        for (first_k, incarnation) in [(0, 1), (5, 2)] {
            let b = Telemetry::Leader {
                first_k,
                states: vec![LeaderState::default(); 5],
                counters: Counters::default(),
                done: false,
                loop_stats: None,
                delivery: Delivery { incarnation, available_from: first_k.min(5), ..Delivery::default() },
                handover: if incarnation == 2 { handover } else { None },
                term: Term { number: if incarnation == 2 { 2 } else { 1 }, stood_down_at: None },
            };
            r.telemetry(Some(0), &codec::encode(&b), Instant::now()).unwrap();
        }
        assert_eq!(
            r.take_news(),
            ["the leader handed over: a standby took the run over at t = 0.007 s; no leader message from t = 0.005 s \
              (0.002 s)"]
        );
        let model = r.model_scenario();
        let row = model.faults.last().expect("the gap's row");
        let dt = scenario.dt_s;
        assert_eq!((row.target, row.from_s, row.to_s), (formation_scenario::FaultTarget::Node(0), 5.0 * dt, 7.0 * dt));
        let json: serde_json::Value = serde_json::from_str(&r.network_json(Ending::Complete)).expect("json");
        assert_eq!(
            (json["handovers"][0]["heard_step"].as_u64(), json["handovers"][0]["step"].as_u64()),
            (Some(4), Some(7))
        );
        let timeline = json["nodes"]["leader"]["timeline"].to_string();
        assert!(timeline.contains("a standby leader took the run over"), "{timeline}");
        // Its record began at step 5, resending the leader's: not a restart.
        assert!(timeline.contains("the standby's record begins") && !timeline.contains("restarted"), "{timeline}");
        assert_eq!(
            r.membership_line().as_deref(),
            Some("members: followers 1, 2, 3, 4 to the end; led by a standby from t = 0.007 s")
        );
        // The live page's frame carries the same line.
        let (frame, _) = r.live_frame(Instant::now(), 1, 0.0, "running", 0);
        let frame: serde_json::Value = serde_json::from_str(&frame).expect("frame");
        assert_eq!(frame["members"], "members: followers 1, 2, 3, 4 to the end; led by a standby from t = 0.007 s");
        assert_eq!(frame["membership"], serde_json::json!({"0": "a standby leads from 0.007 s"}), "the leader's row");
        // In lock-step the followers wait for the standby: no gap to model.
        let lockstep = scenario.clone().with_handovers(&[]);
        assert_eq!(lockstep.faults.len(), scenario.faults.len());
        let mut ls = scenario.clone();
        ls.timing = formation_scenario::Timing::Lockstep;
        assert_eq!(ls.with_handovers(&[(5, 7)]).faults.len(), scenario.faults.len());
    }

    /// The monitor's memory with followers absent or gone: the leader's
    /// states a follower absent from the start (3) or one that left for
    /// good (2, at 3 s) will never use are not kept beyond the join window
    /// (the buffer stays within JOIN_WINDOW_S, not the run), and follower 3
    /// joining at 10 s still finds the states of its first steps.
    #[test]
    fn followers_absent_or_gone_hold_back_no_leader_state() {
        let (_dir, scenario, mut r) = recorder_with(&["duration=12", "timing=realtime"]);
        r.absent(&[3]);
        let (steps, batch) = (scenario.steps(), u64::from(scenario.network.telemetry_batch));
        let window = (JOIN_WINDOW_S / scenario.dt_s) as usize;
        let mut most = 0;
        for first in (0..=steps).step_by(batch as usize) {
            let n = batch.min(steps + 1 - first);
            let leader = Telemetry::Leader {
                first_k: first,
                states: vec![LeaderState::default(); n as usize],
                counters: Counters::default(),
                done: first + n > steps,
                loop_stats: None,
                delivery: Delivery::default(),
                handover: None,
                term: Term { number: 1, stood_down_at: None },
            };
            r.telemetry(Some(0), &codec::encode(&leader), Instant::now()).unwrap();
            for id in [1, 2, 3, 4] {
                let left = (id == 2 && first + n >= 3000).then(|| Left { at_k: first + n, why: "SIGTERM".into() });
                if (id == 2 && first >= 3000) || (id == 3 && first < 10_000) {
                    continue;
                }
                let done = first + n > steps || left.is_some();
                let b = follower_batch(&scenario, id, first, n, done, left);
                r.telemetry(Some(id), &codec::encode(&b), Instant::now()).unwrap();
            }
            most = most.max(r.leader.len());
        }
        assert!(most <= window + 2 * batch as usize, "{most} leader states held (window {window})");
        assert_eq!(r.joined, vec![(3, 10_000)], "follower 3 joined at 10 s");
        assert!(r.followers.iter().all(|f| f.unpaired == 0), "a sample without its leader state");
        assert!(r.complete(), "the record is whole: {:?}", r.unfinished());
    }

    /// A follower that left the run (its last batch says so, done) is not
    /// waited for: the run completes when the others have; network.json
    /// names it with the step and why, its record is short only of the
    /// steps it did not take, and the run's model cuts it off from then on.
    #[test]
    fn a_follower_that_left_is_not_waited_for_and_is_named() {
        let (_dir, scenario, mut r) = paper_recorder();
        let steps = scenario.steps();
        let leader = Telemetry::Leader {
            first_k: 0,
            states: vec![LeaderState::default(); steps as usize + 1],
            counters: Counters::default(),
            done: true,
            loop_stats: None,
            delivery: Delivery::default(),
            handover: None,
            term: Term { number: 1, stood_down_at: None },
        };
        r.telemetry(Some(0), &codec::encode(&leader), Instant::now()).unwrap();
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        let batch = |id: u32, n: u64, left: Option<Left>| follower_batch(&scenario, id, 0, n, true, left);
        for &id in &ids[1..] {
            r.telemetry(Some(id), &codec::encode(&batch(id, steps + 1, None)), Instant::now()).unwrap();
        }
        assert!(!r.complete(), "follower {} has said nothing yet", ids[0]);
        let left = Left { at_k: 4, why: "SIGTERM".into() };
        r.telemetry(Some(ids[0]), &codec::encode(&batch(ids[0], 4, Some(left))), Instant::now()).unwrap();
        assert!(r.complete(), "a follower that left is not waited for");
        assert_eq!(r.left(), vec![(ids[0], 4, "SIGTERM".to_string())]);
        // Nor does it hold back the steps counted recorded (the live line's t).
        assert_eq!(r.recorded_steps(), steps + 1, "{}", r.status_line());
        // Said as it is learnt, with Lemma 1 checked again: in the paper's
        // graph follower 1 is the only one that hears the leader.
        assert_eq!(
            r.take_news(),
            ["follower 1 left the run at t = 0.004 s (SIGTERM); followers 2, 3, 4 no longer reach the leader (Lemma \
              1): their estimates drift"]
        );
        assert!(r.take_news().is_empty(), "said once");
        assert_eq!(
            r.membership_line().as_deref(),
            Some("members: followers 2, 3, 4 to the end; follower 1 left at t = 0.004 s (SIGTERM)")
        );
        assert_eq!(
            r.membership_line().as_deref(),
            Some("members: followers 2, 3, 4 to the end; follower 1 left at t = 0.004 s (SIGTERM)")
        );
        // The live page marks its row.
        let (frame, _) = r.live_frame(Instant::now(), 1, 0.0, "running", 0);
        let frame: serde_json::Value = serde_json::from_str(&frame).expect("frame");
        assert_eq!(frame["membership"], serde_json::json!({"1": "left at 0.004 s (SIGTERM)"}), "{frame}");
        let model = r.model_scenario();
        let cut = model.faults.last().expect("a fault");
        assert_eq!((cut.target, cut.from_s), (formation_scenario::FaultTarget::Node(ids[0]), 4.0 * scenario.dt_s));
        let json: serde_json::Value = serde_json::from_str(&r.network_json(Ending::Complete)).expect("json");
        assert_eq!(json["left"][0]["follower"], ids[0], "{}", json["left"]);
        assert_eq!((json["left"][0]["step"].as_u64(), json["left"][0]["why"].as_str()), (Some(4), Some("SIGTERM")));
        r.set_model(Ok(BTreeMap::new()));
        let summary = formation_record::Summary::new(&scenario, BTreeMap::new());
        let health = r.health(&summary).expect("judged");
        let line = health.line();
        assert!(line.contains(&format!("follower {} left the run at t = 0.004 s (SIGTERM)", ids[0])), "{line}");
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
            handover: None,
            term: Term { number: 1, stood_down_at: None },
        };
        r.telemetry(Some(0), &codec::encode(&leader), Instant::now()).unwrap();
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        // The third follower stops after 4 of the steps + 1 samples.
        for &id in &ids {
            let n = if id == ids[2] { 4 } else { steps + 1 };
            let batch = follower_batch(&scenario, id, 0, n, false, None);
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
