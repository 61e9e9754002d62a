//! The `formation` command line: argument definitions and dispatch. Each
//! command's work lives in its own module; this file only wires them up.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use formation_record::{RecordOptions, Summary};
use formation_scenario::Scenario;

use formation_bench::sim::BenchArgs;
use formation_exit::{at_least_one, Error};
use formation_report::progress::Progress;
use formation_scenario::args::ScenarioArgs;

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

// Every command takes negative numbers as values (`--speed -1`), so that
// the option's own check refuses them in plain words rather than clap
// taking them for flags.
#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run a scenario in one process, deterministically, and write a run folder.
    #[command(allow_negative_numbers = true)]
    Sim(SimArgs),
    /// Measure follower-steps per second of the simulator.
    #[command(allow_negative_numbers = true)]
    Bench(BenchArgs),
    /// Run every case the paper compares and write its figures, tables and claims.
    #[command(allow_negative_numbers = true)]
    Paper(formation_report::paper::PaperArgs),
    /// Fit the values the paper leaves open (the robot's m and I, the
    /// disturbance, the noise covariances, the ASIF's limit) jointly against
    /// its Tables I and II by a seeded search, with each entry's sensitivity.
    #[command(allow_negative_numbers = true)]
    Calibrate(formation_report::calibrate::CalibrateArgs),
    /// The paper's figures and tables for any run folders, side by side.
    #[command(allow_negative_numbers = true)]
    Report(formation_report::ReportArgs),
    /// Run the formation as separate processes over zenoh on this machine
    /// (leader, one agent per follower, monitor) and print the summary.
    #[command(allow_negative_numbers = true)]
    Launch(formation_launch::options::LaunchArgs),
    /// Run the formation as on several machines: every node in a network
    /// namespace of its own on a virtual bridge, the fault table performed
    /// by the network (links down, packet loss), router and agent restarts.
    /// Needs root or unprivileged user namespaces.
    #[command(allow_negative_numbers = true)]
    Lab(formation_launch::lab::LabArgs),
    /// Measure the networked formation: lock-step steps/s, real-time loop jitter, one-hop latency.
    #[command(allow_negative_numbers = true)]
    BenchNet(formation_bench::net::BenchNetArgs),
    /// The networked formation at nominal timing against its model: the
    /// lab's faults (join, leave, quorum, cut-off, sites, clocks, handover)
    /// and 50 and 100 agents in real time, one at a time with the machine to
    /// themselves; each run's late source-steps and figures beside the
    /// model's, judged when the run kept its period. A table, verify.csv
    /// and verify.json. The lab's studies need root.
    #[command(allow_negative_numbers = true)]
    Verify(formation_bench::verify::VerifyArgs),
    /// A stand-in robot that speaks ROS 2: follower ID's velocity-commanded
    /// robot (robot.model = "velocity"), driven on /follower_ID/cmd_vel,
    /// publishing /follower_ID/odom and /tf over zenoh as rmw_zenoh does
    /// (docs/ros2.md). `launch --robots stand-in` starts one per follower.
    #[command(allow_negative_numbers = true)]
    Robot(formation_net::ros2::robot::RobotArgs),
    /// Make a certificate authority, a certificate and key per node and the
    /// access-control policy of a scenario, for `--tls DIR` (mutual TLS on
    /// every link, each node allowed to speak only for itself).
    #[command(allow_negative_numbers = true)]
    Certs(formation_launch::certs::CertsArgs),
    /// Write a scenario of any size: N followers on formation slots, a graph
    /// of the given kind checked against Lemma 1, λ_min(H) in its header.
    #[command(allow_negative_numbers = true)]
    Generate(GenerateArgs),
    /// Re-compute a networked run in one process from what each follower
    /// heard (its run folder's hearing.bin), byte for byte; with --explain,
    /// where and why the run departed from its model.
    #[command(allow_negative_numbers = true)]
    Replay(crate::replay::ReplayArgs),
    /// Ask follower ID of a running formation to leave the run for good (as
    /// SIGTERM to its agent would): it tells its neighbours and the monitor,
    /// its robot stops; refused if the others would lose the leader (Lemma 1).
    #[command(allow_negative_numbers = true)]
    Leave(formation_net::leave::LeaveArgs),
    /// Play a finished networked run again on the live page (--web) or to
    /// Foxglove (--foxglove), at --speed, with pause and seek on the page.
    #[command(allow_negative_numbers = true)]
    Play(crate::replay::PlayArgs),
    /// The old spelling of `formation play RUN_DIR`: `monitor --replay
    /// RUN_DIR` (it says where it moved, then plays).
    #[command(allow_negative_numbers = true, hide = true)]
    Monitor(crate::replay::MonitorReplayArgs),
    /// A single node of a networked run (used by `launch`).
    #[command(hide = true)]
    Node(crate::node::NodeCommand),
    /// One of `bench-net --floor`'s plain-zenoh processes (used by `bench-net`).
    #[command(hide = true)]
    BenchFloor(formation_bench::floor::FloorArgs),
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

fn generate(a: &GenerateArgs) -> Result<(), Error> {
    use formation_scenario::generate::{self, GraphKind, Spec};
    let graph = GraphKind::parse(&a.graph).ok_or_else(|| Error::Input(format!("--graph {}: unknown", a.graph)))?;
    let spec = Spec {
        chords: a.chords,
        leader_links: a.leader_links,
        radius: a.radius,
        seed: a.seed,
        ..Spec::new(a.followers, graph)
    };
    formation_record::out_path::check_out_path("--out", &a.out, formation_record::out_path::MAX_NAME_BYTES)
        .map_err(Error::Input)?;
    let text = generate::toml(&spec).map_err(|e| {
        let hint = match (&e, graph) {
            (formation_scenario::ScenarioError::GraphNotConnected { .. }, GraphKind::RandomGeometric) => {
                " (try a larger --radius, more --leader-links or another --seed)"
            }
            (formation_scenario::ScenarioError::GraphNotConnected { .. }, _) => " (try more --leader-links)",
            _ => "",
        };
        Error::Input(format!("{e}{hint}"))
    })?;
    if a.out.exists() && !a.force {
        return Err(Error::Input(format!("{} exists (--force to replace it)", a.out.display())));
    }
    if let Some(parent) = a.out.parent().filter(|p| !p.as_os_str().is_empty() && !p.is_dir()) {
        return Err(Error::Input(format!("--out {}: there is no folder {}", a.out.display(), parent.display())));
    }
    std::fs::write(&a.out, &text).map_err(|e| Error::Run(format!("writing {}: {e}", a.out.display())))?;
    let s = Scenario::load(&a.out, &[]).map_err(|e| Error::Run(e.to_string()))?;
    let lambda = s.graph.lambda_min_h().map_or_else(|| "not computed at this size".to_string(), |l| format!("{l:.6}"));
    println!(
        "wrote {}: {}, {} graph with {}, {} hearing the leader, λ_min(H) = {lambda}",
        a.out.display(),
        formation_report::words::count(s.followers.len(), "follower"),
        graph.name(),
        formation_report::words::count(s.graph.edge_count(), "edge"),
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
    /// Also write rosbag2/: the CSVs' rows as a ROS 2 bag (metadata.yaml and
    /// an MCAP file of CDR messages: odom, cmd_vel, leader_estimate, /tf,
    /// /clock) that `ros2 bag` and Foxglove open (docs/ros2.md).
    #[arg(long, conflicts_with = "no_csv")]
    pub rosbag2: bool,
    /// Print nothing but errors.
    #[arg(long, short)]
    pub quiet: bool,
    /// Threads that step the followers: 0 uses every core for formations of
    /// 256 followers or more and one thread below. Results are bit for bit
    /// the same for any number.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub threads: usize,
}

/// From this many followers `--threads 0` steps them on every core (the
/// `--threads` help says the number).
pub const PARALLEL_FROM: usize = 256;
/// Most `--threads`.
pub const MAX_THREADS: usize = 256;

/// `--threads N`: at most [`MAX_THREADS`].
pub fn check_threads(threads: usize) -> Result<(), Error> {
    if threads > MAX_THREADS {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        return Err(Error::Input(format!(
            "--threads {threads}: at most {MAX_THREADS} (this machine has {cores} cores; 0 picks for you)"
        )));
    }
    Ok(())
}

pub fn main() -> ExitCode {
    let cli: Cli = crate::args::parse_or_exit();
    let result = match cli.command {
        Command::Sim(a) => sim(&a).map(|_| ()),
        Command::Bench(a) => formation_bench::sim::run(&a).map_err(Into::into),
        Command::Paper(a) => formation_report::paper::run(&a).map_err(Into::into),
        Command::Calibrate(a) => formation_report::calibrate::run(&a).map_err(Into::into),
        Command::Report(a) => formation_report::run(&a).map_err(Into::into),
        Command::Launch(a) => formation_launch::launch::run(&a).map_err(Into::into),
        Command::Lab(a) => formation_launch::lab::run(&a).map_err(Into::into),
        Command::BenchNet(a) => {
            // Its latency sessions run in this process: as in the nodes.
            formation_net::session::default_runtime();
            formation_bench::net::run(&a).map_err(Into::into)
        }
        Command::Verify(a) => formation_bench::verify::run(&a).map_err(Into::into),
        Command::Certs(a) => formation_launch::certs::run(&a).map_err(Into::into),
        Command::Generate(a) => generate(&a),
        Command::Replay(a) => crate::replay::run(&a),
        Command::Play(a) => crate::replay::playback(&a.run, &a.how, false),
        Command::Monitor(a) => crate::replay::monitor_replay(&a),
        Command::Node(a) => return crate::node::run(a.node),
        Command::Leave(a) => return crate::node::run_leave(a),
        Command::Robot(a) => return crate::node::run_robot(a),
        Command::BenchFloor(f) => return crate::node::run_floor(f),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(e.status())
        }
    }
}

/// `formation sim`: run, write the folder, print the table.
pub fn sim(a: &SimArgs) -> Result<(Summary, PathBuf), Error> {
    at_least_one("--every", a.every)?;
    check_threads(a.threads)?;
    let scenario = a.scenario.load()?;
    scenario.simulable().map_err(Error::Input)?;
    let dir = a.out.clone().unwrap_or_else(|| Path::new("runs").join(&scenario.name));
    formation_record::out_path::check_out_path("--out", &dir, formation_record::out_path::MAX_OUT_NAME_BYTES)
        .map_err(Error::Input)?;
    formation_launch::runsize::check(
        &scenario,
        a.every,
        !a.no_csv,
        a.mcap,
        &dir,
        "--every N, --no-csv or a shorter duration",
    )?;
    if let Some(w) = scenario.estimator_stability_warning() {
        eprintln!("{w}");
    }
    let threads = match a.threads {
        0 if scenario.followers.len() >= PARALLEL_FROM => std::thread::available_parallelism().map_or(1, |n| n.get()),
        0 => 1,
        n => n,
    };
    let opts = RecordOptions { dir, every: a.every, csv: !a.no_csv, mcap: a.mcap, rosbag2: a.rosbag2 };
    let (summary, dir) = run_to_folder(&scenario, &opts, a.quiet, threads)?;
    if !a.quiet {
        print!("{}", summary.table());
        println!("wrote {}", dir.display());
    }
    // docs/model.md §16: two robots closer than the safety distance is a degraded run.
    if let Some(v) = summary.safety.as_ref().and_then(|p| p.violation_text()) {
        return Err(Error::Degraded(format!("degraded: {v} ({})", dir.join("summary.json").display())));
    }
    Ok((summary, dir))
}

/// Runs a scenario in process on `threads` threads and writes its run
/// folder, with a progress line unless `quiet`.
pub fn run_to_folder(
    scenario: &Scenario,
    opts: &RecordOptions,
    quiet: bool,
    threads: usize,
) -> Result<(Summary, PathBuf), Error> {
    let mut progress = Progress::new(scenario.steps() + 1, &scenario.name, quiet);
    let stop = formation_exit::shutdown::flag::catch();
    let result = formation_sim::run_to_folder_until(scenario, opts, threads, Some(stop), |k| progress.set(k));
    formation_exit::shutdown::flag::release();
    progress.finish();
    match result {
        // Ctrl-C: what was recorded is kept, and said (it left a
        // `<out>.partial` without its last rows or a summary, silently).
        Err(formation_sim::SimError::Kept { source, kept }) => match *source {
            formation_sim::SimError::Io(e) if e.kind() == std::io::ErrorKind::Interrupted => {
                Err(formation_exit::shutdown::flag::signal().error(format!(
                    "{e}: {} holds every step before it, and summary.json says `\"complete\": false`",
                    kept.display()
                )))
            }
            source => Err(formation_sim::SimError::Kept { source: Box::new(source), kept }.into()),
        },
        r => Ok(r?),
    }
}
