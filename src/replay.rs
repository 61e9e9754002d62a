//! `formation replay RUN_DIR`: a networked run re-computed in one process
//! from its scenario and what each follower heard (`hearing.bin`), checked
//! byte for byte against the run's CSVs and `summary.json`; with
//! `--explain`, the run beside its model.

use std::path::PathBuf;

use clap::Args;
use formation_exit::shutdown::Signal;
use formation_replay::check::{check, Comparison};
use formation_replay::replay;

use formation_exit::Error;

#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// A networked run's folder (written by `launch`, `lab` or a `monitor`).
    #[arg(value_name = "RUN_DIR")]
    pub run: PathBuf,
    /// Keep the replay's folder here (default: a temporary folder, removed
    /// once compared).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// The run beside its model (every message used `network.delay_steps`
    /// after it was sent, the fault table applied): where it first departed,
    /// and which links and which periods explain the difference in each
    /// follower's metrics.
    #[arg(long)]
    pub explain: bool,
    /// With --explain: the metric to attribute (a summary.json metric of a
    /// follower: torque_tv, formation_rms_last10, vc_peak, …) [default:
    /// torque_tv].
    #[arg(long, value_name = "METRIC")]
    pub metric: Option<String>,
    /// With --explain: the length of the time windows ranked (s) [default: 1].
    #[arg(long, value_name = "SECONDS")]
    pub window: Option<f64>,
    /// With --explain: how many links and windows to list [default: 10].
    #[arg(long, value_name = "N")]
    pub top: Option<usize>,
}

pub fn run(a: &ReplayArgs) -> Result<(), Error> {
    let given: Vec<&str> =
        [("--metric", a.metric.is_some()), ("--window", a.window.is_some()), ("--top", a.top.is_some())]
            .into_iter()
            .filter_map(|(flag, set)| set.then_some(flag))
            .collect();
    if !a.explain && !given.is_empty() {
        // They were ignored: the user asked for something not done.
        let (last, rest) = given.split_last().unwrap_or((&"", &[]));
        let flags = if rest.is_empty() { last.to_string() } else { format!("{} and {last}", rest.join(", ")) };
        let verb = if rest.is_empty() { "goes" } else { "go" };
        return Err(Error::Input(format!("{flags} {verb} with --explain: add --explain, or leave {flags} out")));
    }
    if let Some(top) = a.top {
        formation_exit::at_least_one("--top", top as u64)?;
    }
    let loaded = replay::load(&a.run)?;
    if a.explain {
        let metric = a.metric.as_deref().unwrap_or("torque_tv");
        return formation_report::explain::run(&loaded, metric, a.window.unwrap_or(1.0), a.top.unwrap_or(10))
            .map_err(Into::into);
    }
    let mut bar = formation_report::progress::Progress::new(loaded.scenario.steps() + 1, "replay", false);
    let (verdict, text) = check(&loaded, a.out.as_deref(), &mut |k| bar.set(k))?;
    bar.finish();
    print!("{text}");
    match verdict {
        Comparison::Identical => Ok(()),
        // The run's own files are damaged: nothing to say about the replay.
        Comparison::Damaged(what) => Err(Error::Input(format!(
            "{} is a damaged run folder ({}): its hearing record replays, but there is nothing whole to compare \
             the replay with (--out DIR keeps the files the replay re-computes)",
            a.run.display(),
            what.join("; ")
        ))),
        Comparison::Differs(damaged) => Err(Error::Run(format!(
            "the replay of {} differs from the run: a bug in the hearing record or in the step's purity{}",
            a.run.display(),
            match damaged.is_empty() {
                true => String::new(),
                false => format!(" (besides, the run's own files are damaged: {})", damaged.join("; ")),
            }
        ))),
    }
}

/// `formation play RUN_DIR`: a finished run played again.
#[derive(Args, Debug)]
pub struct PlayArgs {
    /// The networked run folder to play (its hearing.bin).
    #[arg(value_name = "RUN_DIR")]
    pub run: PathBuf,
    #[command(flatten)]
    pub how: PlayHow,
}

/// `formation monitor --replay RUN_DIR`: the old spelling of `formation
/// play`, kept so that scripts go on working; it says where it moved.
#[derive(Args, Debug)]
pub struct MonitorReplayArgs {
    /// The networked run folder to play (its hearing.bin).
    #[arg(long = "replay", value_name = "RUN_DIR", required = true)]
    pub run: PathBuf,
    #[command(flatten)]
    pub how: PlayHow,
}

/// Where and how a finished run plays.
#[derive(Args, Debug)]
pub struct PlayHow {
    /// Play it on a live page at this address (open http://ADDR/): pause,
    /// speed and seek on the page. `--web` alone: 127.0.0.1:8765; port 0:
    /// any free port (the line `live page: http://…` says which).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8765")]
    pub web: Option<std::net::SocketAddr>,
    /// Play it to Foxglove (Foxglove WebSocket protocol) at this address:
    /// the channels of run.mcap as they are replayed. `--foxglove` alone:
    /// 127.0.0.1:8766; port 0: any free port.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8766")]
    pub foxglove: Option<std::net::SocketAddr>,
    /// Run seconds per wall-clock second (the page can change it).
    #[arg(long, default_value_t = 1.0, value_name = "X")]
    pub speed: f64,
    /// After the end, keep the page and its controls this long (a seek or
    /// play starts again), then exit.
    #[arg(long, default_value_t = 600.0, value_name = "SECONDS")]
    pub linger: f64,
}

/// Where `formation monitor --replay` moved.
const MOVED: &str = "`formation monitor --replay RUN_DIR` is now `formation play RUN_DIR`";

/// `formation monitor --replay`: plays, saying where it moved (in its one
/// line when it fails, before the playback's lines when it plays).
pub fn monitor_replay(a: &MonitorReplayArgs) -> Result<(), Error> {
    let moved = |m: String| format!("{MOVED}: {m}");
    playback(&a.run, &a.how, true).map_err(|e| match e {
        Error::Input(m) => Error::Input(moved(m)),
        Error::Run(m) => Error::Run(moved(m)),
        other => other,
    })
}

/// The longest `--linger`: a day.
const MAX_LINGER_S: f64 = 86_400.0;

/// A number as a user would write it: 1e-300, not 300 zeros.
fn number(x: f64) -> String {
    if x != 0.0 && x.is_finite() && !(1e-4..1e15).contains(&x.abs()) {
        format!("{x:e}")
    } else {
        x.to_string()
    }
}

/// Plays a finished run on the live page and to Foxglove.
/// `moved`: asked by the old spelling, which the first line says.
pub fn playback(run: &std::path::Path, a: &PlayHow, moved: bool) -> Result<(), Error> {
    use formation_replay::playback::{self, Control, Outputs};
    if a.web.is_none() && a.foxglove.is_none() {
        return Err(Error::Input("formation play: give --web, --foxglove or both (where to play it)".into()));
    }
    let (speed, linger) = (number(a.speed), number(a.linger));
    if !(playback::MIN_SPEED..=playback::MAX_SPEED).contains(&a.speed) {
        let what = if a.speed > 0.0 {
            format!("--speed {speed} is out of range")
        } else {
            format!("--speed must be positive, not {speed}")
        };
        return Err(Error::Input(format!(
            "{what} ({} to {} run seconds per second)",
            playback::MIN_SPEED,
            playback::MAX_SPEED
        )));
    }
    if !(0.0..=MAX_LINGER_S).contains(&a.linger) {
        return Err(Error::Input(format!("--linger must be 0 to {MAX_LINGER_S} seconds (a day), not {linger}")));
    }
    let loaded = replay::load(run)?;
    if moved {
        eprintln!("note: {MOVED} (the old spelling still works)");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| Error::Run(format!("starting the async runtime: {e}")))?;
    let name = run.file_name().map_or("run".to_string(), |n| n.to_string_lossy().into_owned());
    let s = loaded.scenario.clone();
    let result = runtime.block_on(async move {
        let (tx, rx) = std::sync::mpsc::channel::<Control>();
        let live = match a.web {
            Some(addr) => {
                let mut scene: serde_json::Value =
                    serde_json::from_str(&formation_recorder::Recorder::scene_json(&s, &name)).unwrap_or_default();
                scene["playback"] =
                    serde_json::json!({"duration": s.steps() as f64 * s.dt_s, "speed": a.speed, "from": run.display().to_string()});
                let live = formation_view::web::Live::new(scene.to_string());
                let at = formation_view::web::serve(formation_view::web::Bind::Tcp(addr), live.clone()).await?;
                live.set_control(Box::new(move |body| Control::parse(body).is_some_and(|c| tx.send(c).is_ok())));
                eprintln!("live page: {at} (playing {} at {}×)", run.display(), a.speed);
                Some(live)
            }
            None => None,
        };
        let foxglove = match a.foxglove {
            Some(addr) => {
                let f = formation_view::foxglove::FoxgloveLive::start(addr, &s, &name).await?;
                eprintln!("foxglove: ws://{}:{}", addr.ip(), f.port());
                Some(std::sync::Arc::new(f))
            }
            None => None,
        };
        let (speed, linger) = (a.speed, std::time::Duration::from_secs_f64(a.linger));
        let sinks: Vec<std::sync::Arc<dyn formation_record::LiveSink>> =
            foxglove.iter().map(|f| f.clone() as std::sync::Arc<dyn formation_record::LiveSink>).collect();
        let task = tokio::task::spawn_blocking(move || {
            let out = Outputs { live, sinks };
            playback::play(&loaded, speed, &out, &rx, linger)
        });
        tokio::select! {
            r = task => {
                r.map_err(|e| Error::Run(format!("the playback stopped: {e}")))??;
                if let Some(f) = foxglove {
                    f.stop().await;
                }
                Ok(())
            }
            // The player's thread is left to the process's end (it was
            // waited for, and Ctrl-C ended the command only when the
            // playback did, with status 0).
            s = formation_exit::shutdown::signalled() => match s {
                Signal::Interrupt => Err(Error::Interrupted("interrupted".into(), 2)),
                Signal::Terminate => Err(Error::Interrupted("terminated".into(), 15)),
            },
        }
    });
    runtime.shutdown_background();
    if result.is_err() {
        playback::remove_scratch();
    }
    result
}
