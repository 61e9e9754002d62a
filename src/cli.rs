//! The `formation` command line: argument definitions and dispatch. Each
//! command's work lives in its own module; this file only wires them up.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::{Args, Parser, Subcommand};
use formation_topology::Scenario;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::record::{RecordOptions, Row, RunWriter, Summary};
use crate::sim::{Observer, Simulation};

#[derive(Parser, Debug)]
#[command(
    name = "formation",
    version,
    about = "Distributed leader-follower formation control (bioinspired backstepping and sliding mode, \
             distributed leader estimator, adaptive sliding innovation filter)",
    long_about = None
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run a scenario in one process, deterministically, and write a run folder.
    Sim(SimArgs),
    /// Measure follower-steps per second of the simulator.
    Bench(BenchArgs),
    /// Run every case the paper compares and write its figures, tables and claims.
    Paper(crate::paper::PaperArgs),
    /// The paper's figures and tables for any run folders, side by side.
    Report(crate::report::ReportArgs),
    /// Run the formation as separate processes over zenoh on this machine
    /// (leader, one agent per follower, monitor) and print the summary.
    Launch(crate::launch::LaunchArgs),
    /// Run the formation as on several machines: every node in a network
    /// namespace of its own on a virtual bridge, the fault table performed
    /// by the network (links down, packet loss), router and agent restarts.
    /// Needs root or unprivileged user namespaces.
    Lab(crate::lab::LabArgs),
    /// Measure the networked formation: lock-step steps/s, real-time loop jitter, one-hop latency.
    BenchNet(crate::net::bench::BenchNetArgs),
    /// Make a certificate authority, a certificate and key per node and the
    /// access-control policy of a scenario, for `--tls DIR` (mutual TLS on
    /// every link, each node allowed to speak only for itself).
    Certs(crate::certs::CertsArgs),
    /// Write a scenario of any size: N followers on formation slots, a graph
    /// of the given kind checked against Lemma 1, λ_min(H) in its header.
    Generate(GenerateArgs),
    /// A single node of a networked run (used by `launch`).
    #[command(hide = true)]
    Node(crate::launch::NodeCommand),
}

/// Scenario selection shared by every command that runs one.
#[derive(Args, Debug, Clone)]
pub struct ScenarioArgs {
    /// Scenario file (TOML). See scenarios/paper.toml for every key.
    pub scenario: PathBuf,
    /// Override a scenario value without editing the file, e.g.
    /// `--set filter=kf --set fault.time=10 --set duration=5`. Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
}

impl ScenarioArgs {
    pub fn load(&self) -> Result<Scenario, CliError> {
        Scenario::load(&self.scenario, &self.overrides).map_err(|e| CliError::Input(e.to_string()))
    }
}

#[derive(Args, Debug)]
pub struct GenerateArgs {
    /// Number of followers (ids 1..=N).
    #[arg(long, value_name = "N")]
    pub followers: u32,
    /// ring (a cycle, plus --chords), grid (4-neighbours), random-geometric
    /// (random slots, linked within --radius), complete, line.
    #[arg(long, value_parser = ["ring", "grid", "random-geometric", "complete", "line"])]
    pub graph: String,
    /// Extra random edges of a ring.
    #[arg(long, default_value_t = 0, value_name = "M")]
    pub chords: u32,
    /// How many followers hear the leader (those nearest to it).
    #[arg(long, default_value_t = 1, value_name = "K")]
    pub leader_links: u32,
    /// Link radius of a random geometric graph, m [default: about the
    /// connectivity threshold for the followers' density].
    #[arg(long, value_name = "METRES")]
    pub radius: Option<f64>,
    /// Seed of the layout, the chords and the scenario's noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The scenario file to write.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Replace FILE if it exists.
    #[arg(long)]
    pub force: bool,
}

fn generate(a: &GenerateArgs) -> Result<(), CliError> {
    use formation_topology::generate::{self, GraphKind, Spec};
    let graph = GraphKind::parse(&a.graph).ok_or_else(|| CliError::Input(format!("--graph {}: unknown", a.graph)))?;
    let spec = Spec {
        chords: a.chords,
        leader_links: a.leader_links,
        radius: a.radius,
        seed: a.seed,
        ..Spec::new(a.followers, graph)
    };
    let text = generate::toml(&spec).map_err(|e| {
        let hint = match (&e, graph) {
            (formation_topology::ScenarioError::GraphNotConnected { .. }, GraphKind::RandomGeometric) => {
                " (try a larger --radius, more --leader-links or another --seed)"
            }
            (formation_topology::ScenarioError::GraphNotConnected { .. }, _) => " (try more --leader-links)",
            _ => "",
        };
        CliError::Input(format!("{e}{hint}"))
    })?;
    if a.out.exists() && !a.force {
        return Err(CliError::Input(format!("{} exists (--force to replace it)", a.out.display())));
    }
    std::fs::write(&a.out, &text).map_err(|e| CliError::Run(format!("writing {}: {e}", a.out.display())))?;
    let s = Scenario::load(&a.out, &[]).map_err(|e| CliError::Run(e.to_string()))?;
    let lambda = s.graph.lambda_min_h().map_or_else(|| "not computed at this size".to_string(), |l| format!("{l:.6}"));
    println!(
        "wrote {}: {} followers, {} graph with {} edges, {} hearing the leader, λ_min(H) = {lambda}",
        a.out.display(),
        s.followers.len(),
        graph.name(),
        s.graph.edge_count(),
        (0..s.graph.len()).filter(|&i| s.graph.hears_leader(i)).count(),
    );
    Ok(())
}

#[derive(Args, Debug)]
pub struct SimArgs {
    #[command(flatten)]
    pub scenario: ScenarioArgs,
    /// Run folder to write (default: runs/<scenario name>). Replaced if it is a run folder; any other existing folder is refused.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write every N-th sample to the CSVs (metrics always use every sample).
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub every: u64,
    /// Write summary.json only, no CSV time series.
    #[arg(long)]
    pub no_csv: bool,
    /// Also write run.mcap: the CSVs' rows as an MCAP recording that
    /// Foxglove and the mcap tools open (poses as foxglove.PoseInFrame, every
    /// column as numbers, network events). About 1.6 KB per follower row:
    /// combine with --every for long runs.
    #[arg(long, conflicts_with = "no_csv")]
    pub mcap: bool,
    /// Print nothing but errors.
    #[arg(long, short)]
    pub quiet: bool,
    /// Threads that step the followers: 0 uses every core for formations of
    /// PARALLEL_FROM followers or more and one thread below. Results are bit
    /// for bit the same for any number.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub threads: usize,
}

/// From this many followers `--threads 0` steps them on every core.
pub const PARALLEL_FROM: usize = 256;

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Follower counts to measure; 4 is the paper scenario, larger counts are
    /// generated rings with n/5 random chords.
    #[arg(long, value_delimiter = ',', default_values_t = vec![4, 100, 10_000, 100_000])]
    pub followers: Vec<u32>,
    /// Threads to measure each count on: 1 steps the followers one after
    /// another, N > 1 on N threads (as `sim --threads N`), `all` on every core.
    #[arg(long, value_delimiter = ',', default_values = ["1", "all"], value_parser = parse_threads, value_name = "N|all")]
    pub threads: Vec<usize>,
    /// Minimum follower-steps per measurement (at least 100 steps).
    #[arg(long, default_value_t = 2_000_000)]
    pub work: u64,
    /// Runs per measurement; the fastest is reported.
    #[arg(long, default_value_t = 3, value_name = "N")]
    pub repeat: u32,
    /// Also measure with recording on (CSV of every sample into a temporary folder).
    #[arg(long)]
    pub record: bool,
    /// The paper scenario file, for n = 4.
    #[arg(long, default_value = "scenarios/paper.toml")]
    pub scenario: PathBuf,
    /// Instead: the paper scenario without faults, with follower 3 cut off
    /// for 3 s and with 30 % loss on every link, side by side (SPEC §14).
    #[arg(long)]
    pub faults: bool,
}

/// `--threads` of `bench`: a count of at least 1, or `all` for every core.
fn parse_threads(s: &str) -> Result<usize, String> {
    match s {
        "all" => Ok(std::thread::available_parallelism().map_or(1, |n| n.get())),
        _ => match s.parse::<usize>() {
            Ok(0) | Err(_) => Err(format!("{s:?} is neither a thread count of at least 1 nor `all`")),
            Ok(n) => Ok(n),
        },
    }
}

/// Every command ends with [`crate::error::Error`]: one line and its exit status.
pub use crate::error::Error as CliError;

/// Refuses 0 for a count option that must be at least 1.
pub fn at_least_one(flag: &str, value: u64) -> Result<(), CliError> {
    match value {
        0 => Err(CliError::Input(format!("{flag} must be at least 1, not 0"))),
        _ => Ok(()),
    }
}

pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Sim(a) => sim(&a).map(|_| ()),
        Command::Bench(a) => crate::bench::run(&a),
        Command::Paper(a) => crate::paper::run(&a),
        Command::Report(a) => crate::report::run(&a),
        Command::Launch(a) => crate::launch::run(&a),
        Command::Lab(a) => crate::lab::run(&a),
        Command::BenchNet(a) => {
            // Its latency sessions run in this process: as in the nodes.
            crate::net::session::default_runtime();
            crate::net::bench::run(&a)
        }
        Command::Certs(a) => crate::certs::run(&a),
        Command::Generate(a) => generate(&a),
        Command::Node(a) => crate::launch::run_node(&a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            e.exit_code()
        }
    }
}

/// A progress bar that appears only once work has taken more than a second.
pub struct Progress {
    bar: ProgressBar,
    started: Instant,
    shown: bool,
    quiet: bool,
}

impl Progress {
    pub fn new(len: u64, what: &str, quiet: bool) -> Self {
        let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::hidden());
        let style = ProgressStyle::with_template("{msg} [{bar:30}] {percent:>3}% {elapsed} (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> ");
        bar.set_style(style);
        bar.set_message(what.to_string());
        Self { bar, started: Instant::now(), shown: false, quiet }
    }

    pub fn set(&mut self, pos: u64) {
        if !self.shown && !self.quiet && self.started.elapsed() > Duration::from_secs(1) {
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
            self.shown = true;
        }
        self.bar.set_position(pos);
    }

    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// `formation sim`: run, write the folder, print the table.
pub fn sim(a: &SimArgs) -> Result<(Summary, PathBuf), CliError> {
    at_least_one("--every", a.every)?;
    let scenario = a.scenario.load()?;
    let dir = a.out.clone().unwrap_or_else(|| Path::new("runs").join(&scenario.name));
    let threads = match a.threads {
        0 if scenario.followers.len() >= PARALLEL_FROM => std::thread::available_parallelism().map_or(1, |n| n.get()),
        0 => 1,
        n => n,
    };
    let opts = RecordOptions { dir, every: a.every, csv: !a.no_csv, mcap: a.mcap };
    let (summary, dir) = run_to_folder_on(&scenario, &opts, a.quiet, threads)?;
    if !a.quiet {
        print!("{}", summary.table());
        println!("wrote {}", dir.display());
    }
    Ok((summary, dir))
}

/// Runs a scenario in process and writes its run folder.
pub fn run_to_folder(scenario: &Scenario, opts: &RecordOptions, quiet: bool) -> Result<(Summary, PathBuf), CliError> {
    run_to_folder_on(scenario, opts, quiet, 1)
}

/// [`run_to_folder`] with the followers of each step on `threads` threads.
pub fn run_to_folder_on(
    scenario: &Scenario,
    opts: &RecordOptions,
    quiet: bool,
    threads: usize,
) -> Result<(Summary, PathBuf), CliError> {
    if threads > 1 {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| CliError::Run(format!("starting {threads} threads: {e}")))?;
        return pool.install(|| run_folder(scenario, opts, quiet, true));
    }
    run_folder(scenario, opts, quiet, false)
}

fn run_folder(
    scenario: &Scenario,
    opts: &RecordOptions,
    quiet: bool,
    parallel: bool,
) -> Result<(Summary, PathBuf), CliError> {
    let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
    let mut writer = RunWriter::create(opts, &ids)?;
    let steps = scenario.steps();
    let mut progress = Progress::new(steps + 1, &scenario.name, quiet);
    let mut sim = Simulation::new(scenario);
    sim.set_parallel(parallel);
    let result = {
        let mut observer = FolderObserver { writer: &mut writer, steps, dt: scenario.dt_s };
        sim.run(&mut observer, |k| progress.set(k))
    };
    progress.finish();
    match result {
        Ok(metrics) => {
            let summary = Summary::new(scenario, ids.iter().copied().zip(metrics).collect())
                .with_outages(scenario, &sim.outages());
            let dir = writer.finish(&summary)?;
            Ok((summary, dir))
        }
        Err(e) => {
            // Keep what was recorded up to the failure, with the summary of
            // an incomplete run (`complete: false`).
            let metrics = sim.followers().iter().map(|f| f.metrics.finish());
            let summary = Summary::new(scenario, ids.iter().copied().zip(metrics).collect());
            let _ = writer.flush();
            let _ = writer.write_file("summary.json", &summary.to_json());
            Err(CliError::Run(format!(
                "{e} (samples so far and their summary.json kept in {})",
                writer.partial_dir().display()
            )))
        }
    }
}

/// Writes every sample the writer wants.
struct FolderObserver<'w> {
    writer: &'w mut RunWriter,
    steps: u64,
    dt: f64,
}

impl Observer for FolderObserver<'_> {
    fn leader(&mut self, k: u64, state: &formation_agent::LeaderState) -> std::io::Result<()> {
        if self.writer.wants(k, k == self.steps) {
            self.writer.leader_row(k as f64 * self.dt, state)?;
        }
        Ok(())
    }
    fn follower(&mut self, index: usize, k: u64, row: &Row, last: bool) -> std::io::Result<()> {
        if self.writer.wants(k, last) {
            self.writer.follower_row(index, row)?;
        }
        Ok(())
    }
}
