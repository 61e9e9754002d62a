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
use std::time::{Duration, Instant};

use formation_agent::LeaderState;
use formation_topology::Scenario;
use serde_json::json;
use tokio::sync::mpsc;

use crate::error::Error;

use crate::net::barrier;
use crate::net::codec;
use crate::net::counters::Counters;
use crate::net::keys::{self, Keys, MONITOR};
use crate::net::node::NodeArgs;
use crate::net::telemetry::Telemetry;
use crate::net::timing::LoopStats;
use crate::record::{FollowerSample, MetricsAccumulator, RecordOptions, Row, RunWriter, Summary};

/// `monitor` arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct MonitorArgs {
    #[command(flatten)]
    pub node: NodeArgs,
    /// Run folder to write [default: runs/<run name>]. Replaced if it is a run folder; any other existing folder is refused.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Write every N-th sample to the CSVs (metrics always use every sample).
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub every: u64,
    /// Give up when no telemetry arrives for this long (s).
    #[arg(long, default_value_t = 60.0, value_name = "SECONDS")]
    pub idle_timeout: f64,
    /// No live line.
    #[arg(long, short)]
    pub quiet: bool,
}

/// How a monitored run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    /// Every node reported its final step.
    Complete,
    /// Ctrl-C (SIGINT).
    Interrupted,
    /// SIGTERM.
    Terminated,
    /// No telemetry for the idle timeout.
    Idle,
}

#[derive(Default)]
struct NodeStats {
    messages: u64,
    bytes: u64,
    samples: u64,
    gaps: u64,
    counters: Counters,
    loop_stats: Option<LoopStats>,
    done: bool,
}

impl NodeStats {
    /// Files an admitted batch's bookkeeping.
    fn note(&mut self, bytes: usize, counters: Counters, done: bool, loop_stats: Option<LoopStats>, fresh: usize) {
        self.messages += 1;
        self.bytes += bytes as u64;
        self.samples += fresh as u64;
        self.counters = counters;
        self.done |= done;
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

/// What to do with a telemetry batch (items for steps first_k, first_k + 1, …).
#[derive(Debug, PartialEq)]
enum Batch<T> {
    /// Beyond the run's last step.
    Malformed,
    /// Starts after the end of what is recorded (a batch was lost).
    Gap,
    /// The items beyond what is recorded (an overlap with recorded steps,
    /// e.g. after a forged batch of another length, is skipped); `truncated`
    /// when it was cut at a non-finite or misnumbered item.
    Fresh { items: Vec<T>, truncated: bool },
}

impl<T> Batch<T> {
    /// Counts a rejected or truncated batch; the items to record, if any.
    fn count(self, malformed: &mut u64, gaps: &mut u64) -> Option<Vec<T>> {
        match self {
            Batch::Malformed => {
                *malformed += 1;
                None
            }
            Batch::Gap => {
                *gaps += 1;
                None
            }
            Batch::Fresh { items, truncated } => {
                *malformed += u64::from(truncated);
                Some(items)
            }
        }
    }
}

/// Checks a batch against the recorded steps `..end` of a run of `steps` + 1
/// steps, before anything is updated; `ok(k, item)` validates one item.
fn admit<T>(mut items: Vec<T>, first_k: u64, end: u64, steps: u64, ok: impl Fn(u64, &T) -> bool) -> Batch<T> {
    match first_k.checked_add(items.len() as u64) {
        Some(last) if last <= steps + 1 => {}
        _ => return Batch::Malformed,
    }
    if first_k > end {
        return Batch::Gap;
    }
    let bad = items.iter().enumerate().position(|(i, x)| !ok(first_k + i as u64, x));
    if let Some(b) = bad {
        items.truncate(b);
    }
    let skip = (end - first_k) as usize;
    let items = if skip < items.len() { items.split_off(skip) } else { Vec::new() };
    Batch::Fresh { items, truncated: bad.is_some() }
}

struct FollowerTrack {
    id: u32,
    offset: [f64; 2],
    pending: VecDeque<FollowerSample>,
    next_k: u64,
    metrics: MetricsAccumulator,
    formation_error: f64,
}

/// The monitor's bookkeeping, independent of zenoh (fed with telemetry payloads).
pub struct Recorder {
    scenario: Scenario,
    writer: RunWriter,
    followers: Vec<FollowerTrack>,
    /// Leader states from step `leader_base` on.
    leader: VecDeque<LeaderState>,
    leader_base: u64,
    leader_next_k: u64,
    nodes: BTreeMap<u32, NodeStats>,
    malformed: u64,
}

impl Recorder {
    pub fn new(scenario: &Scenario, opts: &RecordOptions) -> std::io::Result<Self> {
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        let writer = RunWriter::create(opts, &ids)?;
        let followers = scenario
            .followers
            .iter()
            .map(|f| FollowerTrack {
                id: f.id,
                offset: f.offset,
                pending: VecDeque::new(),
                next_k: 0,
                metrics: MetricsAccumulator::for_scenario(scenario),
                formation_error: f64::NAN,
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
            leader: VecDeque::new(),
            leader_base: 0,
            leader_next_k: 0,
            nodes,
            malformed: 0,
        })
    }

    /// Files one telemetry message received on `telemetry/<key_id>`.
    pub fn telemetry(&mut self, key_id: Option<u32>, bytes: &[u8]) -> std::io::Result<()> {
        let Some(t) = codec::decode::<Telemetry>(bytes) else {
            self.malformed += 1;
            return Ok(());
        };
        let steps = self.scenario.steps();
        match t {
            Telemetry::Leader { first_k, states, counters, done, loop_stats } => {
                if key_id != Some(0) {
                    self.malformed += 1;
                    return Ok(());
                }
                let end = self.leader_next_k;
                let n = self.nodes.entry(0).or_default();
                let batch = admit(states, first_k, end, steps, |_, s| s.is_finite());
                let Some(fresh) = batch.count(&mut self.malformed, &mut n.gaps) else { return Ok(()) };
                n.note(bytes.len(), counters, done, loop_stats, fresh.len());
                for (i, s) in fresh.into_iter().enumerate() {
                    let k = end + i as u64;
                    if self.writer.wants(k, k == steps) {
                        self.writer.leader_row(k as f64 * self.scenario.dt_s, &s)?;
                    }
                    self.leader.push_back(s);
                }
                self.leader_next_k = self.leader_base + self.leader.len() as u64;
            }
            Telemetry::Follower { id, first_k, samples, counters, done, loop_stats } => {
                let Some(index) = self.scenario.index_of(id).filter(|_| key_id == Some(id)) else {
                    self.malformed += 1;
                    return Ok(());
                };
                let f = &mut self.followers[index];
                let end = f.next_k + f.pending.len() as u64;
                let n = self.nodes.entry(id).or_default();
                let batch = admit(samples, first_k, end, steps, |k, s| s.k == k && s.is_finite());
                let Some(fresh) = batch.count(&mut self.malformed, &mut n.gaps) else { return Ok(()) };
                n.note(bytes.len(), counters, done, loop_stats, fresh.len());
                f.pending.extend(fresh);
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
            while f.next_k < leader_end {
                let Some(sample) = f.pending.pop_front() else { break };
                let k = f.next_k;
                let l = &self.leader[(k - self.leader_base) as usize];
                let row = Row::new(&sample, l, f.offset, dt);
                f.metrics.push(k, &row);
                f.formation_error = row.formation_error;
                if self.writer.wants(k, k == steps) {
                    self.writer.follower_row(index, &row)?;
                }
                f.next_k += 1;
            }
        }
        // Leader states every follower has used are no longer needed.
        let used = self.followers.iter().map(|f| f.next_k).min().unwrap_or(leader_end);
        while self.leader_base < used && !self.leader.is_empty() {
            self.leader.pop_front();
            self.leader_base += 1;
        }
        Ok(())
    }

    /// Removes the folder being written (a run that never started).
    pub fn discard(self) {
        self.writer.discard();
    }

    /// Appends the buffered CSV rows to the (partial) folder.
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.writer.flush()
    }

    /// Whether every node has reported its final step and all of it is recorded.
    pub fn complete(&self) -> bool {
        let steps = self.scenario.steps();
        self.nodes.values().all(|n| n.done) && self.followers.iter().all(|f| f.next_k == steps + 1)
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

    /// `network.json`: per-node message counts and loop timing.
    pub fn network_json(&self, ending: Ending) -> String {
        let nodes: serde_json::Map<String, serde_json::Value> = self
            .nodes
            .iter()
            .map(|(&id, n)| {
                let name = if id == 0 { "leader".to_string() } else { id.to_string() };
                let c = &n.counters;
                // Rows in this follower's CSV (followers can be ahead of the slowest one).
                let recorded = self.scenario.index_of(id).filter(|_| id != 0).map(|i| self.followers[i].next_k);
                (
                    name,
                    json!({
                        "telemetry_messages": n.messages,
                        "telemetry_bytes": n.bytes,
                        "telemetry_samples": n.samples,
                        "telemetry_gaps": n.gaps,
                        "done": n.done,
                        "recorded_steps": recorded,
                        "estimates_sent": c.sent,
                        "republished": c.republished,
                        "received": c.received,
                        "late": c.late,
                        "silent": c.silent,
                        "fault_lost": c.fault_lost,
                        "rejected": c.rejected,
                        "rejected_invalid": c.rejected.invalid(),
                        "loop": n.loop_stats,
                    }),
                )
            })
            .collect();
        let v = json!({
            "scenario": self.scenario.name,
            "timing": crate::record::name(&self.scenario.timing),
            "complete": ending == Ending::Complete,
            // Both signals interrupt the run; `signal` says which.
            "ending": match ending {
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
            "malformed_telemetry": self.malformed,
            "nodes": nodes,
        });
        serde_json::to_string_pretty(&v).unwrap_or_default() + "\n"
    }

    /// Writes `network.json` and `summary.json` (metrics of what was
    /// received) and moves the folder into place.
    pub fn finish(self, ending: Ending) -> std::io::Result<(Summary, PathBuf)> {
        self.writer.write_file("network.json", &self.network_json(ending))?;
        let metrics = self.followers.iter().map(|f| (f.id, f.metrics.finish())).collect();
        let outages = self.followers.iter().map(|f| (f.id, f.metrics.outages())).collect();
        let summary = Summary::new(&self.scenario, metrics).with_outages(&self.scenario, &outages);
        let dir = self.writer.finish(&summary)?;
        Ok((summary, dir))
    }
}

/// Runs the monitor to the end of the run (or Ctrl-C / SIGTERM / idle timeout).
/// Returns how the run ended (`Idle` is an error).
pub async fn run(args: &MonitorArgs) -> Result<Ending, Error> {
    let (scenario, keys) = args.node.load()?;
    if !args.idle_timeout.is_finite() || args.idle_timeout <= 0.0 {
        return Err(Error::Input("--idle-timeout must be positive".into()));
    }
    let dir = args.out.clone().unwrap_or_else(|| PathBuf::from("runs").join(&keys.run));
    let opts = RecordOptions { dir, every: args.every.max(1), csv: true };
    let recorder = Recorder::new(&scenario, &opts).map_err(|e| Error::Run(format!("creating the run folder: {e}")))?;
    let session = match args.node.open().await {
        Ok(s) => s,
        Err(e) => {
            // Nothing was recorded: leave no empty `<out>.partial` behind.
            recorder.discard();
            return Err(e);
        }
    };
    let result = monitor(&session, &scenario, &keys, recorder, args).await;
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    result
}

async fn monitor(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    mut recorder: Recorder,
    args: &MonitorArgs,
) -> Result<Ending, Error> {
    let (tx, mut rx) = mpsc::unbounded_channel::<(Option<u32>, Vec<u8>)>();
    let _sub = session
        .declare_subscriber(keys.telemetry_all())
        .callback(move |s| {
            let id = keys::last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
            let _ = tx.send((id, s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(|e| Error::Run(format!("declaring the telemetry subscriber: {e}")))?;

    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| Error::Run(format!("installing the SIGTERM handler: {e}")))?;
    // A stream created once, so that a signal arriving between two polls is not lost.
    let mut sigint = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
        .map_err(|e| Error::Run(format!("installing the SIGINT handler: {e}")))?;
    let mut needs: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
    needs.push(keys::LEADER_NODE.to_string());
    let barrier = barrier::wait_for_start(session, keys, MONITOR, &needs, barrier::fingerprint(scenario));
    tokio::pin!(barrier);
    let mut started = false;

    let idle = Duration::from_secs_f64(args.idle_timeout);
    let tty = std::io::stderr().is_terminal();
    let mut last_heard = Instant::now();
    let mut status = tokio::time::interval(if tty { Duration::from_millis(250) } else { Duration::from_secs(2) });
    let live = !args.quiet;
    let ending = loop {
        tokio::select! {
            r = &mut barrier, if !started => {
                r?;
                started = true;
                last_heard = Instant::now();
            }
            m = rx.recv() => {
                let Some((id, bytes)) = m else { break Ending::Idle };
                last_heard = Instant::now();
                recorder.telemetry(id, &bytes).map_err(|e| Error::Run(format!("writing the run folder: {e}")))?;
                if recorder.complete() {
                    break Ending::Complete;
                }
            }
            _ = sigint.recv() => break Ending::Interrupted,
            _ = sigterm.recv() => break Ending::Terminated,
            _ = status.tick() => {
                if last_heard.elapsed() > idle {
                    break Ending::Idle;
                }
                recorder.flush().map_err(|e| Error::Run(format!("writing the run folder: {e}")))?;
                if live && started {
                    let line = recorder.status_line();
                    let mut err = std::io::stderr().lock();
                    let _ = if tty { write!(err, "\r{line}\x1b[K") } else { writeln!(err, "{line}") };
                }
            }
        }
    };
    if matches!(ending, Ending::Interrupted | Ending::Terminated) {
        // Keep what already arrived (stop listening first, so this ends).
        drop(_sub);
        while let Ok((id, bytes)) = rx.try_recv() {
            recorder.telemetry(id, &bytes).map_err(|e| Error::Run(format!("writing the run folder: {e}")))?;
        }
    }
    if live && tty {
        eprintln!();
    }
    let recorded = recorder.recorded_steps();
    let unfinished = recorder.unfinished();
    let (summary, dir) = recorder.finish(ending).map_err(|e| Error::Run(format!("writing the run folder: {e}")))?;
    match ending {
        Ending::Complete => {
            if !args.quiet {
                print!("{}", summary.table());
                println!("wrote {}", dir.display());
            }
            Ok(Ending::Complete)
        }
        Ending::Interrupted | Ending::Terminated => {
            let short = summary.shortfall_text().map(|s| format!(" (incomplete: {s})")).unwrap_or_default();
            let how = if ending == Ending::Terminated { "terminated" } else { "interrupted" };
            eprintln!("{how}: wrote the {recorded} steps received to {}{short}", dir.display());
            Ok(ending)
        }
        Ending::Idle => Err(Error::Run(format!(
            "no telemetry for {} s; still running: {}; wrote the {recorded} steps received to {}",
            args.idle_timeout,
            unfinished.join(", "),
            dir.display()
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn admit_validates_before_anything_is_recorded() {
        let ok = |_: u64, x: &f64| x.is_finite();
        // Beyond the run's end: malformed.
        assert_eq!(admit(vec![1.0; 3], 9, 9, 10, ok), Batch::Malformed);
        assert_eq!(admit(vec![1.0; 1], u64::MAX, 9, 10, ok), Batch::Malformed);
        assert_eq!(admit(vec![f64::NAN, 1.0], 0, 0, 10, ok), Batch::Fresh { items: vec![], truncated: true });
        // After the recorded end: a gap.
        assert_eq!(admit(vec![1.0], 5, 4, 10, ok), Batch::Gap);
        // Overlap: only what is beyond the recorded end.
        assert_eq!(
            admit(vec![1.0, 2.0, 3.0, 4.0], 2, 4, 10, ok),
            Batch::Fresh { items: vec![3.0, 4.0], truncated: false }
        );
        assert_eq!(admit(vec![1.0, 2.0], 2, 4, 10, ok), Batch::Fresh { items: vec![], truncated: false });
        // Cut at the first non-finite item.
        assert_eq!(admit(vec![1.0, f64::NAN, 3.0], 4, 4, 10, ok), Batch::Fresh { items: vec![1.0], truncated: true });
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
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
        let scenario = Scenario::load(&path, &["duration=0.01".to_string()]).expect("scenario");
        let dir = tempfile::tempdir().expect("tempdir");
        let opts = RecordOptions { dir: dir.path().join("run"), every: 1, csv: true };
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
            })
        };
        let follower = |id: u32, first_k: u64, samples: Vec<FollowerSample>, done: bool| {
            codec::encode(&Telemetry::Follower {
                id,
                first_k,
                samples,
                counters: Counters::default(),
                done,
                loop_stats: None,
            })
        };
        r.telemetry(Some(0), &leader(0, steps + 1, true)).unwrap();
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        // Forged: the expected first step, but 2 samples instead of the whole batch; then a NaN sample.
        r.telemetry(Some(ids[0]), &follower(ids[0], 0, (0..2).map(sample).collect(), false)).unwrap();
        let mut nan = sample(2);
        nan.torque_l = f64::NAN;
        r.telemetry(Some(ids[0]), &follower(ids[0], 2, vec![nan], false)).unwrap();
        // Forged: beyond the run's end, claiming done.
        r.telemetry(Some(ids[0]), &follower(ids[0], steps, (steps..steps + 3).map(sample).collect(), true)).unwrap();
        assert_eq!(r.malformed, 2);
        assert_eq!(r.followers[0].next_k + r.followers[0].pending.len() as u64, 2);
        assert!(!r.nodes[&ids[0]].done, "a rejected batch must not set done");
        // The genuine batches, overlapping the forged one, still complete the run.
        for &id in &ids {
            r.telemetry(Some(id), &follower(id, 0, (0..=steps).map(sample).collect(), true)).unwrap();
        }
        assert!(r.complete());
        assert_eq!(r.recorded_steps(), steps + 1);
    }

    #[test]
    fn an_interrupted_run_writes_a_summary_that_says_who_is_short() {
        let (_dir, scenario, mut r) = paper_recorder();
        let steps = scenario.steps();
        let states = vec![LeaderState::default(); steps as usize + 1];
        let leader =
            Telemetry::Leader { first_k: 0, states, counters: Counters::default(), done: true, loop_stats: None };
        r.telemetry(Some(0), &codec::encode(&leader)).unwrap();
        let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
        // The third follower stops after 4 of the steps + 1 samples.
        for &id in &ids {
            let n = if id == ids[2] { 4 } else { steps + 1 };
            let samples = (0..n).map(sample).collect();
            let batch = Telemetry::Follower {
                id,
                first_k: 0,
                samples,
                counters: Counters::default(),
                done: false,
                loop_stats: None,
            };
            r.telemetry(Some(id), &codec::encode(&batch)).unwrap();
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
