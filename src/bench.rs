//! `formation bench`: follower-steps per second of the in-process simulator,
//! for the paper scenario and generated rings, with recording off and
//! (optionally) on. Wall-clock timing lives here, in a shell, never in the core.

use std::time::Instant;

use formation_topology::{generate, Scenario};

use crate::cli::{BenchArgs, CliError};
use crate::record::RecordOptions;
use crate::sim::{NoRecord, Simulation};

/// One measurement.
pub struct Measurement {
    pub followers: usize,
    pub edges: usize,
    pub steps: u64,
    pub seconds: f64,
    pub recording: bool,
}

impl Measurement {
    pub fn follower_steps_per_second(&self) -> f64 {
        (self.followers as u64 * self.steps) as f64 / self.seconds
    }
}

fn scenario_for(n: u32, paper: &std::path::Path) -> Result<Scenario, CliError> {
    if n == 4 {
        Scenario::load(paper, &[]).map_err(|e| CliError::Input(e.to_string()))
    } else {
        generate::ring_with_chords(n, n / 5, 1).map_err(|e| CliError::Input(e.to_string()))
    }
}

/// Steps `scenario` (shortened to `steps`) and times it.
pub fn measure(scenario: &Scenario, steps: u64, record: bool) -> Result<Measurement, CliError> {
    let mut s = scenario.clone();
    s.duration_s = steps as f64 * s.dt_s;
    let started;
    if record {
        let dir = std::env::temp_dir().join(format!("formation-bench-{}", std::process::id()));
        started = Instant::now();
        crate::cli::run_to_folder(&s, &RecordOptions { dir: dir.clone(), every: 1, csv: true, mcap: false }, true)?;
        let seconds = started.elapsed().as_secs_f64();
        let _ = std::fs::remove_dir_all(&dir);
        return Ok(Measurement {
            followers: s.followers.len(),
            edges: s.graph.edge_count(),
            steps: steps + 1,
            seconds,
            recording: true,
        });
    }
    let mut sim = Simulation::new(&s);
    started = Instant::now();
    sim.run(&mut NoRecord, |_| {})?;
    let seconds = started.elapsed().as_secs_f64();
    Ok(Measurement {
        followers: s.followers.len(),
        edges: s.graph.edge_count(),
        steps: steps + 1,
        seconds,
        recording: false,
    })
}

/// The fault-table cases of `formation bench --faults`: the paper scenario
/// without faults, with follower 3 cut off for 3 s, with 30 % loss on every link.
pub const FAULT_CASES: [(&str, &[&str]); 3] = [
    ("no faults", &[]),
    ("follower 3 cut off 10-13 s", &["faults=[{node=3, from=10, to=13}]"]),
    (
        "30 % loss on every link, whole run",
        &["faults=[{node=1, from=0, to=30, loss=0.3}, {node=2, from=0, to=30, loss=0.3}, \
           {node=3, from=0, to=30, loss=0.3}, {node=4, from=0, to=30, loss=0.3}, {link=[0, 1], from=0, to=30, loss=0.3}]"],
    ),
];

/// Follower-steps/s of the paper scenario (its own duration) for each fault
/// case, the best of three repetitions of at least `work` follower-steps.
fn fault_cases(a: &BenchArgs) -> Result<(), CliError> {
    println!("\n{:<36} {:>9} {:>20} {:>7}", "paper scenario, fault table", "runs", "follower-steps/s", "ratio");
    let mut base = None;
    for (name, sets) in FAULT_CASES {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let s = Scenario::load(&a.scenario, &sets).map_err(|e| CliError::Input(e.to_string()))?;
        let per_run = s.followers.len() as u64 * (s.steps() + 1);
        let runs = a.work.div_ceil(per_run).max(1);
        let mut best = 0.0f64;
        for _ in 0..3 {
            let started = Instant::now();
            for _ in 0..runs {
                Simulation::new(&s).run(&mut NoRecord, |_| {})?;
            }
            best = best.max((runs * per_run) as f64 / started.elapsed().as_secs_f64());
        }
        let ratio = best / *base.get_or_insert(best);
        println!("{name:<36} {runs:>9} {best:>20.0} {ratio:>7.3}");
    }
    Ok(())
}

pub fn run(a: &BenchArgs) -> Result<(), CliError> {
    if a.faults {
        return fault_cases(a);
    }
    println!(
        "{:>9} {:>7} {:>8} {:>9} {:>9} {:>20}",
        "followers", "edges", "steps", "record", "seconds", "follower-steps/s"
    );
    for &n in &a.followers {
        let scenario = scenario_for(n, &a.scenario)?;
        let steps = (a.work / u64::from(n.max(1))).max(100);
        let modes: &[bool] = if a.record { &[false, true] } else { &[false] };
        for &record in modes {
            let m = measure(&scenario, steps, record)?;
            println!(
                "{:>9} {:>7} {:>8} {:>9} {:>9.3} {:>20.0}",
                m.followers,
                m.edges,
                m.steps,
                if m.recording { "csv" } else { "off" },
                m.seconds,
                m.follower_steps_per_second()
            );
        }
    }
    // The paper scenario end to end, recording included.
    let paper = scenario_for(4, &a.scenario)?;
    let dir = std::env::temp_dir().join(format!("formation-bench-paper-{}", std::process::id()));
    let started = Instant::now();
    crate::cli::run_to_folder(&paper, &RecordOptions { dir: dir.clone(), every: 1, csv: true, mcap: false }, true)?;
    println!(
        "paper scenario end to end ({} follower-steps, CSV of every sample): {:.3} s",
        paper.followers.len() as u64 * (paper.steps() + 1),
        started.elapsed().as_secs_f64()
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
