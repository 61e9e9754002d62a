//! The monitor (the `monitor` binary): subscribes to every node's
//! telemetry, shows a live line of the formation error per follower and the
//! worst one, and writes the same run folder as `formation sim` (through
//! [`RunWriter`], [`MetricsAccumulator`] and [`Summary`], so a lock-step run
//! gives a byte-identical `summary.json`) plus `network.json` with each
//! node's message counters. Ctrl-C or SIGTERM: writes everything received
//! so far and exits with status 130.

use std::collections::{BTreeMap, VecDeque};
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use formation_agent::LeaderState;
use formation_topology::Scenario;
use serde_json::json;
use tokio::sync::mpsc;

use crate::cli::CliError;
use crate::net::barrier;
use crate::net::node::{self, Counters, Keys, LoopStats, NodeArgs, Telemetry, MONITOR};
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
    /// Ctrl-C or SIGTERM.
    Interrupted,
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
                metrics: MetricsAccumulator::new(scenario.steps(), scenario.dt_s),
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
        let Some(t) = node::decode::<Telemetry>(bytes) else {
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
                let n = self.nodes.entry(0).or_default();
                n.messages += 1;
                n.bytes += bytes.len() as u64;
                n.counters = counters;
                n.done |= done;
                n.loop_stats = loop_stats.or(n.loop_stats);
                if first_k != self.leader_next_k {
                    n.gaps += 1;
                    return Ok(());
                }
                n.samples += states.len() as u64;
                for (i, s) in states.into_iter().enumerate() {
                    let k = first_k + i as u64;
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
                let n = self.nodes.entry(id).or_default();
                n.messages += 1;
                n.bytes += bytes.len() as u64;
                n.counters = counters;
                n.done |= done;
                n.loop_stats = loop_stats.or(n.loop_stats);
                let f = &mut self.followers[index];
                let expected = f.next_k + f.pending.len() as u64;
                if first_k != expected {
                    n.gaps += 1;
                    return Ok(());
                }
                n.samples += samples.len() as u64;
                f.pending.extend(samples);
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
            "ending": format!("{ending:?}").to_lowercase(),
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
        let summary = Summary::new(&self.scenario, metrics);
        let dir = self.writer.finish(&summary)?;
        Ok((summary, dir))
    }
}

/// Runs the monitor to the end of the run (or Ctrl-C / SIGTERM / idle timeout).
/// Returns how the run ended (`Idle` is an error).
pub async fn run(args: &MonitorArgs) -> Result<Ending, CliError> {
    let (scenario, keys) = args.node.load()?;
    if !args.idle_timeout.is_finite() || args.idle_timeout <= 0.0 {
        return Err(CliError::Input("--idle-timeout must be positive".into()));
    }
    let dir = args.out.clone().unwrap_or_else(|| PathBuf::from("runs").join(&keys.run));
    let opts = RecordOptions { dir, every: args.every.max(1), csv: true };
    let recorder =
        Recorder::new(&scenario, &opts).map_err(|e| CliError::Run(format!("creating the run folder: {e}")))?;
    let session = args.node.open().await?;
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
) -> Result<Ending, CliError> {
    let (tx, mut rx) = mpsc::unbounded_channel::<(Option<u32>, Vec<u8>)>();
    let _sub = session
        .declare_subscriber(keys.telemetry_all())
        .callback(move |s| {
            let id = node::last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
            let _ = tx.send((id, s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(|e| CliError::Run(format!("declaring the telemetry subscriber: {e}")))?;

    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| CliError::Run(format!("installing the SIGTERM handler: {e}")))?;
    // A stream created once, so that a signal arriving between two polls is not lost.
    let mut sigint = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
        .map_err(|e| CliError::Run(format!("installing the SIGINT handler: {e}")))?;
    let mut needs: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
    needs.push(node::LEADER_NODE.to_string());
    let barrier = barrier::wait_for_start(session, keys, MONITOR, &needs, node::fingerprint(scenario));
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
                recorder.telemetry(id, &bytes).map_err(|e| CliError::Run(format!("writing the run folder: {e}")))?;
                if recorder.complete() {
                    break Ending::Complete;
                }
            }
            _ = sigint.recv() => break Ending::Interrupted,
            _ = sigterm.recv() => break Ending::Interrupted,
            _ = status.tick() => {
                if last_heard.elapsed() > idle {
                    break Ending::Idle;
                }
                recorder.flush().map_err(|e| CliError::Run(format!("writing the run folder: {e}")))?;
                if live && started {
                    let line = recorder.status_line();
                    let mut err = std::io::stderr().lock();
                    let _ = if tty { write!(err, "\r{line}\x1b[K") } else { writeln!(err, "{line}") };
                }
            }
        }
    };
    if live && tty {
        eprintln!();
    }
    let recorded = recorder.recorded_steps();
    let unfinished = recorder.unfinished();
    let (summary, dir) = recorder.finish(ending).map_err(|e| CliError::Run(format!("writing the run folder: {e}")))?;
    match ending {
        Ending::Complete => {
            if !args.quiet {
                print!("{}", summary.table());
                println!("wrote {}", dir.display());
            }
            Ok(Ending::Complete)
        }
        Ending::Interrupted => {
            eprintln!("interrupted: wrote the {recorded} steps received to {}", dir.display());
            Ok(Ending::Interrupted)
        }
        Ending::Idle => Err(CliError::Run(format!(
            "no telemetry for {} s; still running: {}; wrote the {recorded} steps received to {}",
            args.idle_timeout,
            unfinished.join(", "),
            dir.display()
        ))),
    }
}
