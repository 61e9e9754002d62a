//! The monitor node on zenoh: it listens to the run's telemetry, the nodes'
//! access-control reports and the run's control keys, acknowledges what it
//! holds, and feeds the [`Recorder`] and the [`Watch`] until the run ends;
//! then it writes the run folder and says how the run ended. Only this
//! module knows zenoh and the terminal.

use std::collections::BTreeMap;
use std::future::Future;
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use formation_record::hearing::ScenarioSource;
use formation_record::RecordOptions;
use formation_scenario::Scenario;
use formation_view::foxglove::FoxgloveLive;
use formation_view::web::{self, Live};
use tokio::sync::mpsc;

use super::args::MonitorArgs;
use crate::startup;
use formation_exit::shutdown::Signal;
use formation_exit::Error;
use formation_protocol::barrier::{self, Start};
use formation_protocol::codec;
use formation_protocol::names::{self, Keys, MONITOR};
use formation_recorder::health::{ControlWatch, Verdict};
use formation_recorder::watch::{Ending, Watch};
use formation_recorder::Recorder;

/// How often the monitor acknowledges what it holds.
const ACK_PERIOD: Duration = Duration::from_millis(100);
/// Lock-step: how often the monitor looks for a follower killed (its
/// token lost) whose step it can name.
const DEATH_LOOK: Duration = Duration::from_millis(20);

/// Telemetry received and not yet filed, bytes: beyond this a message is
/// dropped and counted (its sender sends it again: it is not acknowledged).
const MAX_QUEUED_BYTES: usize = 64 << 20;

/// Runs the monitor to the end of the run, the idle timeout, or until
/// `shutdown` resolves (polled from the start of the run's loop on; its
/// signal becomes the ending). Returns how the run ended (`Idle` is an
/// error) and its health's verdict.
pub async fn run(
    args: &MonitorArgs,
    shutdown: impl Future<Output = Signal>,
) -> Result<(Ending, Option<Verdict>), Error> {
    let began = args.node.clock.instant();
    let launched_by = std::os::unix::process::parent_id();
    let (scenario, keys) = args.node.load(MONITOR)?;
    check(args)?;
    let web = serve_live_page(args, &scenario, &keys.run).await?;
    let foxglove = match args.web.foxglove {
        Some(addr) => {
            let live = FoxgloveLive::start(addr, &scenario, &keys.run).await?;
            crate::node::say(&format!("foxglove: ws://{}:{}", addr.ip(), live.port()));
            Some(Arc::new(live))
        }
        None => None,
    };
    let mut recorder = start_record(args, &scenario, &keys.run)?;
    if let Some(live) = &foxglove {
        recorder.add_sink(live.clone());
    }
    let session = match args.node.open(MONITOR, &scenario).await {
        Ok(s) => s,
        Err(e) => {
            // Nothing was recorded: leave no empty `<out>.partial` behind.
            recorder.discard();
            return Err(e);
        }
    };
    let viewers = Viewers { web: web.as_deref(), foxglove: foxglove.as_deref() };
    let result = monitor(&session, &scenario, &keys, recorder, args, began, viewers, shutdown).await;
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    if let Ok((Ending::Interrupted | Ending::Terminated, _)) = result {
        crate::session::keep_zenoh_logs_of_a_gone_launch(&run_folder(args, &keys.run), launched_by);
    }
    result
}

/// Refuses times that make no sense.
fn check(args: &MonitorArgs) -> Result<(), Error> {
    if !args.idle_timeout.is_finite() || args.idle_timeout <= 0.0 {
        return Err(Error::Input("--idle-timeout must be positive".into()));
    }
    if !(args.web.web_linger.is_finite() && args.web.web_linger >= 0.0) {
        return Err(Error::Input(format!("--web-linger must be 0 or more seconds, not {}", args.web.web_linger)));
    }
    Ok(())
}

/// `--web` or the lab's Unix socket: the live page, served from now on.
async fn serve_live_page(args: &MonitorArgs, scenario: &Scenario, run: &str) -> Result<Option<Arc<Live>>, Error> {
    let bind = match (args.web.web, &args.web_unix) {
        (Some(addr), _) => web::Bind::Tcp(addr),
        (None, Some(path)) => web::Bind::Unix(path.clone()),
        (None, None) => return Ok(None),
    };
    let live = Live::new(Recorder::scene_json(scenario, run));
    let at = web::serve(bind, live.clone()).await?;
    if args.web_unix.is_none() {
        crate::node::say(&format!("live page: {at}"));
    }
    Ok(Some(live))
}

/// The recorder of the run folder (`--out`, or `runs/<run>`), with the
/// scenario as loaded for its hearing record (`formation replay` checks it
/// against the run's fingerprint).
/// The run folder: `--out`, or `runs/<run name>`.
fn run_folder(args: &MonitorArgs, run: &str) -> PathBuf {
    args.out.clone().unwrap_or_else(|| PathBuf::from("runs").join(run))
}

fn start_record(args: &MonitorArgs, scenario: &Scenario, run: &str) -> Result<Recorder, Error> {
    let dir = run_folder(args, run);
    let opts = RecordOptions { dir, every: args.every.max(1), csv: true, mcap: args.mcap, rosbag2: args.rosbag2 };
    let mut recorder =
        Recorder::new(scenario, &opts).map_err(|e| Error::Run(format!("creating the run folder: {e}")))?;
    // The text the scenario was loaded from: a file's, or the built-in
    // copy's for `paper` (without it a run of a built-in scenario had no
    // hearing record, and `formation replay` said it predated them).
    if let Ok((label, text)) = Scenario::source(&args.node.scenario) {
        recorder.set_source(ScenarioSource { label, text, overrides: args.node.overrides.clone() });
    }
    Ok(recorder)
}

/// Bytes of telemetry received and not yet filed, and what was dropped.
#[derive(Default)]
struct Queued {
    bytes: AtomicUsize,
    dropped: AtomicU64,
}

impl Queued {
    /// Whether a message of `len` bytes fits under [`MAX_QUEUED_BYTES`] (then it is counted in).
    fn admit(&self, len: usize) -> bool {
        let fits =
            self.bytes.fetch_update(Relaxed, Relaxed, |b| (b + len <= MAX_QUEUED_BYTES).then_some(b + len)).is_ok();
        if !fits {
            self.dropped.fetch_add(1, Relaxed);
        }
        fits
    }

    fn release(&self, len: usize) {
        self.bytes.fetch_sub(len, Relaxed);
    }

    fn dropped(&self) -> u64 {
        self.dropped.load(Relaxed)
    }
}

/// What the monitor hears and says on zenoh while it records.
struct Ears {
    /// Telemetry as (the id its key names, payload).
    telemetry: mpsc::UnboundedReceiver<(Option<u32>, Vec<u8>)>,
    queue: Arc<Queued>,
    /// Dropped to stop listening (a signal: what already arrived is kept).
    telemetry_sub: Option<zenoh::pubsub::Subscriber<()>>,
    /// What each node's access control refused, as (node, report).
    denied: mpsc::Receiver<(String, Vec<u8>)>,
    _denied_sub: zenoh::pubsub::Subscriber<()>,
    /// Every put on the run's control keys from another process, counted per key.
    control: Arc<Mutex<ControlWatch>>,
    _control_sub: zenoh::pubsub::Subscriber<()>,
    /// Acknowledgements: what the monitor holds, so senders forget it and
    /// send again what it lacks (droppable: the next one says the same).
    acks: zenoh::pubsub::Publisher<'static>,
    /// Lock-step: followers killed without a word (formation_protocol::died).
    deaths: Option<super::deaths::Deaths>,
}

impl Ears {
    async fn declare(session: &zenoh::Session, keys: &Keys, scenario: &Scenario) -> Result<Self, Error> {
        // Bounded in bytes: a sender that floods the monitor loses its own
        // messages (counted), never the monitor's memory.
        let (tx, telemetry) = mpsc::unbounded_channel::<(Option<u32>, Vec<u8>)>();
        let queue = Arc::new(Queued::default());
        let q = Arc::clone(&queue);
        let telemetry_sub = session
            .declare_subscriber(keys.telemetry_all())
            .callback(move |s| {
                if !q.admit(s.payload().len()) {
                    return;
                }
                let id = names::last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
                let _ = tx.send((id, s.payload().to_bytes().into_owned()));
            })
            .await
            .map_err(|e| Error::Run(format!("declaring the telemetry subscriber: {e}")))?;
        let (dtx, denied) = mpsc::channel::<(String, Vec<u8>)>(64);
        let denied_sub = session
            .declare_subscriber(keys.denied_all())
            .callback(move |s| {
                let node = names::last_chunk(s.key_expr().as_str()).to_string();
                let _ = dtx.try_send((node, s.payload().to_bytes().into_owned()));
            })
            .await
            .map_err(|e| Error::Run(format!("declaring the access-control report subscriber: {e}")))?;
        let control = Arc::new(Mutex::new(ControlWatch::default()));
        let (c, prefix, fingerprint) = (control.clone(), names::key(&keys.run, ""), barrier::fingerprint(scenario));
        let control_sub = session
            .declare_subscriber(names::key(&keys.run, "control/**"))
            .allowed_origin(zenoh::sample::Locality::Remote)
            .callback(move |s| {
                let rel = s.key_expr().as_str().strip_prefix(prefix.as_str()).unwrap_or("").to_string();
                let bytes = s.payload().to_bytes();
                c.lock().unwrap_or_else(|p| p.into_inner()).note(&rel, &bytes, fingerprint);
            })
            .await
            .map_err(|e| Error::Run(format!("declaring the control-key watch: {e}")))?;
        let acks = session
            .declare_publisher(keys.ack())
            .congestion_control(zenoh::qos::CongestionControl::Drop)
            .priority(crate::node::priority::ACK)
            .express(true)
            .await
            .map_err(|e| Error::Run(format!("declaring the acknowledgement publisher: {e}")))?;
        let deaths = match scenario.timing == formation_scenario::Timing::Lockstep {
            true => Some(super::deaths::Deaths::declare(session, keys, scenario).await?),
            false => None,
        };
        Ok(Self {
            deaths,
            telemetry,
            queue,
            telemetry_sub: Some(telemetry_sub),
            denied,
            _denied_sub: denied_sub,
            control,
            _control_sub: control_sub,
            acks,
        })
    }

    async fn acknowledge(&self, recorder: &Recorder) {
        let _ = self.acks.put(codec::encode(&recorder.ack())).await;
    }
}

/// The run's viewers: the live page (fed frames) and the Foxglove server
/// (fed rows by the recorder).
#[derive(Clone, Copy)]
struct Viewers<'a> {
    web: Option<&'a Live>,
    foxglove: Option<&'a FoxgloveLive>,
}

impl Viewers<'_> {
    /// Whether anyone watches now.
    fn watched(&self) -> bool {
        use formation_record::LiveSink;
        self.web.is_some_and(|w| w.viewers() > 0) || self.foxglove.is_some_and(|f| f.viewers() > 0)
    }
}

/// The live page's frames, numbered.
struct Frames<'a> {
    web: Option<&'a Live>,
    seq: u64,
}

impl Frames<'_> {
    fn publish(&mut self, recorder: &Recorder, watch: &Watch, state: &str, now: Instant) {
        if let Some(w) = self.web {
            self.seq += 1;

            let (frame, past) = recorder.live_frame(now, self.seq, watch.wall_s(now), state, w.viewers());
            w.publish(frame, past);
        }
    }
}

/// How the loop stopped.
enum Stopped {
    /// The run ended this way.
    Ended(Ending),
    /// The run never started (another scenario, nodes missing): nothing
    /// was recorded.
    NotStarted(Error),
}

/// One monitored run: what the loop feeds and asks.
struct Monitor<'a> {
    args: &'a MonitorArgs,
    recorder: Recorder,
    watch: Watch,
    ears: Ears,
    frames: Frames<'a>,
    /// stderr is a terminal: the live line rewrites itself.
    tty: bool,
}

fn written(e: std::io::Error) -> Error {
    Error::Run(format!("writing the run folder: {e}"))
}

impl Monitor<'_> {
    /// Listens until the run ends: the start, telemetry, reports,
    /// acknowledgements, frames, the shutdown and the live line.
    async fn record(
        &mut self,
        mut barrier: Pin<&mut impl Future<Output = Result<Start, Error>>>,
        nodes: usize,
        mut shutdown: Pin<&mut impl Future<Output = Signal>>,
    ) -> Result<Stopped, Error> {
        let mut status =
            tokio::time::interval(if self.tty { Duration::from_millis(250) } else { Duration::from_secs(2) });
        let mut frames = tokio::time::interval(web::FRAME_PERIOD);
        frames.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let mut ack_tick = tokio::time::interval(ACK_PERIOD);
        let mut death_tick = tokio::time::interval(DEATH_LOOK);
        let live = !self.args.quiet;
        let ending = loop {
            tokio::select! {
                r = &mut barrier, if !self.watch.started() => {
                    let start = match r {
                        Ok(start) => start,
                        Err(e) => return Ok(Stopped::NotStarted(e)),
                    };
                    let startup = self.watch.on_start(self.args.node.clock.instant());
                    self.recorder.absent(&start.absent);
                    if live {
                        crate::node::say(&started_line(nodes, &start.absent, startup));
                    }
                }
                m = self.ears.telemetry.recv() => {
                    let Some((id, bytes)) = m else { break Ending::Idle };
                    if let Some(end) = self.file(id, &bytes)? {
                        break end;
                    }
                }
                Some((node, bytes)) = self.ears.denied.recv() => {
                    self.recorder.denied.file(&node, &bytes);
                }
                _ = ack_tick.tick(), if self.watch.started() => {
                    self.ears.acknowledge(&self.recorder).await;
                }
                _ = death_tick.tick(), if self.watch.started() && self.ears.deaths.is_some() => {
                    if let Some(d) = self.ears.deaths.as_mut() {
                        d.look(&mut self.recorder, self.args.node.clock.mono()).await;
                    }
                    self.say_news();
                    if let Some(end) = self.watch.on_telemetry_check(self.recorder.complete()) {
                        break end;
                    }
                }
                _ = frames.tick(), if self.frames.web.is_some() => {
                    let state = if self.watch.started() { "running" } else { "waiting" };
                    self.frames.publish(&self.recorder, &self.watch, state, self.args.node.clock.instant());
                }
                signal = &mut shutdown => break Ending::from(signal),
                _ = status.tick() => {
                    let now = self.args.node.clock.instant();
                    if self.watch.started() {
                        // network.gone_after: a silent follower no longer waited for.
                        self.recorder.check_gone(now);
                        self.say_news();
                        if let Some(end) = self.watch.on_telemetry_check(self.recorder.complete()) {
                            break end;
                        }
                    }
                    if let Some(end) = self.watch.on_tick(now) {
                        break end;
                    }
                    self.recorder.flush().map_err(written)?;
                    if live && self.watch.started() {
                        self.print_status();
                    }
                }
            }
        };
        Ok(Stopped::Ended(ending))
    }

    /// Files one telemetry message; how the run ended, if it did.
    fn file(&mut self, id: Option<u32>, bytes: &[u8]) -> Result<Option<Ending>, Error> {
        self.ears.queue.release(bytes.len());
        self.recorder.queue_dropped = self.ears.queue.dropped();
        let now = self.args.node.clock.instant();
        self.recorder.telemetry(id, bytes, now).map_err(written)?;
        self.say_news();
        Ok(self.watch.on_telemetry(now, self.recorder.complete()))
    }

    /// Who came and went, a line each (not with --quiet).
    fn say_news(&mut self) {
        for line in self.recorder.take_news() {
            if !self.args.quiet {
                if self.tty {
                    eprint!("\r\x1b[K");
                }
                crate::node::say(&line);
            }
        }
    }

    /// The live line on stderr: rewritten in place on a terminal.
    fn print_status(&self) {
        let line = self.recorder.status_line();
        let mut err = std::io::stderr().lock();
        let _ = if self.tty { write!(err, "\r{line}\x1b[K") } else { writeln!(err, "{line}") };
    }

    /// After the loop: keeps what already arrived after a signal, tells the
    /// senders of a complete run that all of it is held, and files the
    /// access-control reports that came in meanwhile.
    async fn wind_down(&mut self, ending: Ending) -> Result<(), Error> {
        if matches!(ending, Ending::Interrupted | Ending::Terminated) {
            // Stop listening first, so this ends.
            self.ears.telemetry_sub = None;
            while let Ok((id, bytes)) = self.ears.telemetry.try_recv() {
                self.recorder.telemetry(id, &bytes, self.args.node.clock.instant()).map_err(written)?;
            }
        }
        if ending == Ending::Complete {
            // The senders' last batches are acknowledged only now: say so a few
            // times, so they can stop without waiting for their drain limit.
            for _ in 0..5 {
                self.ears.acknowledge(&self.recorder).await;
                tokio::time::sleep(ACK_PERIOD / 2).await;
            }
        }
        while let Ok((node, bytes)) = self.ears.denied.try_recv() {
            self.recorder.denied.file(&node, &bytes);
        }
        Ok(())
    }
}

/// Records the run on `session` until it ends; writes the run folder.
// The node's parts as run() built them: grouping them would only rename them.
#[allow(clippy::too_many_arguments)]
async fn monitor(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    recorder: Recorder,
    args: &MonitorArgs,
    began: Instant,
    viewers: Viewers<'_>,
    shutdown: impl Future<Output = Signal>,
) -> Result<(Ending, Option<Verdict>), Error> {
    let ears = Ears::declare(session, keys, scenario).await?;
    tokio::spawn(crate::denials::report(session.clone(), MONITOR.to_string(), Some(keys.run.clone())));
    let mut needs: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
    needs.push(names::LEADER_NODE.to_string());
    let barrier =
        startup::wait_for_start(session, keys, MONITOR, &needs, scenario, &args.node.clock, args.node.quorum_wait()?);
    tokio::pin!(barrier);
    let watch = Watch::new(began, args.node.clock.instant(), Duration::from_secs_f64(args.idle_timeout));
    let tty = std::io::stderr().is_terminal();
    let mut m = Monitor { args, recorder, watch, ears, frames: Frames { web: viewers.web, seq: 0 }, tty };
    tokio::pin!(shutdown);
    let ending = match m.record(barrier, needs.len() + 1, shutdown).await? {
        Stopped::Ended(ending) => ending,
        Stopped::NotStarted(e) => {
            // A start that failed leaves no folder behind.
            m.recorder.discard();
            return Err(e);
        }
    };
    let run_s = m.watch.run_s(args.node.clock.instant());
    m.frames.publish(&m.recorder, &m.watch, ending.name(), args.node.clock.instant());
    m.wind_down(ending).await?;
    if !args.quiet && tty {
        eprintln!();
    }
    let Monitor { mut recorder, watch, ears, .. } = m;
    recorder.set_wall(watch.startup_s(), run_s);
    recorder.control = ears.control.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let result = finish(recorder, ending, args);
    if viewers.watched() && matches!(ending, Ending::Complete | Ending::Idle) {
        // Open pages get the final frame before the server ends with the process.
        tokio::time::sleep(Duration::from_secs_f64(args.web.web_linger)).await;
    }
    if let Some(f) = viewers.foxglove {
        f.stop().await;
    }
    result
}

/// The monitor's line at the start: everyone, or who is absent.
fn started_line(nodes: usize, absent: &[u32], startup: f64) -> String {
    if absent.is_empty() {
        return format!("started: all {nodes} nodes ready {startup:.1} s after the monitor's start");
    }
    format!(
        "started: {} of {nodes} nodes ready {startup:.1} s after the monitor's start; absent: {} (a quorum start: \
         cut off from the start in the run and in its model)",
        nodes - absent.len(),
        formation_scenario::graph::followers_named(absent)
    )
}

/// Judges the run against its model, writes the run folder and says how
/// the run ended (a summary table, or one line on stderr).
fn finish(mut recorder: Recorder, ending: Ending, args: &MonitorArgs) -> Result<(Ending, Option<Verdict>), Error> {
    // The rows past a leader that stopped first count among those written.
    recorder.pair_past_the_leader().map_err(written)?;
    let recorded = recorder.recorded_steps();
    let unfinished = recorder.unfinished();
    // The model of what happened: a follower that left is cut off from then on.
    recorder.set_model(model_errors(&recorder.model_scenario()));
    let members = recorder.membership_line();
    let (summary, dir, health) = recorder.finish_judged(ending).map_err(written)?;
    let verdict = health.as_ref().map(|h| h.verdict);
    match ending {
        Ending::Complete => {
            if !args.quiet {
                print!("{}", summary.table());
                if let Some(m) = &members {
                    println!("{m}");
                }
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
            crate::node::say(&format!("{how}: wrote the {recorded} steps received to {}{short}", dir.display()));
            Ok((ending, verdict))
        }
        Ending::Idle => Err(Error::Run(format!(
            "no telemetry for {} s; never reported their last step: {} (stopped, or cut off from the monitor); \
             wrote the {recorded} steps received to {}",
            args.idle_timeout,
            unfinished.join(", "),
            dir.display()
        ))),
    }
}

/// The model runs at the end of a run only up to this many follower-steps
/// (the paper's 4 followers for 30 s are 120,004: 0.3 s).
const MODEL_MAX_FOLLOWER_STEPS: u64 = 3_000_000;

/// Each follower's formation error over the last 10 s in the model of the
/// run (the simulator on the same scenario: delay, loss and fault table),
/// or why the model was not run.
pub fn model_errors(scenario: &Scenario) -> Result<BTreeMap<u32, Option<f64>>, String> {
    if let Some(source) = scenario.live_leader() {
        return Err(format!(
            "the leader was steered live (leader.source = \"{source}\") and not every step of it was recorded: \
             no model to judge the run by"
        ));
    }
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
