//! A simulation written to a run folder: the one observer that writes a
//! folder's CSVs, and the run that finishes the folder (or keeps what was
//! recorded when the run stops early).

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

use formation_leader::LeaderState;
use formation_record::{RecordOptions, Row, RunWriter, Summary};
use formation_scenario::Scenario;

use crate::simulation::{Observer, SimError, Simulation};

/// Writes every sample the run folder wants (every N-th and the last).
pub struct FolderObserver<'w> {
    pub writer: &'w mut RunWriter,
    steps: u64,
    dt_s: f64,
    /// Set (by a signal handler) to stop the run at the next step.
    stop: Option<&'w AtomicBool>,
}

impl<'w> FolderObserver<'w> {
    pub fn new(writer: &'w mut RunWriter, scenario: &Scenario) -> Self {
        Self { writer, steps: scenario.steps(), dt_s: scenario.dt_s, stop: None }
    }
}

impl Observer for FolderObserver<'_> {
    fn leader(&mut self, k: u64, state: &LeaderState) -> std::io::Result<()> {
        // Stopped between steps: every step before k is whole.
        if self.stop.is_some_and(|s| s.load(Ordering::Relaxed)) {
            return Err(std::io::Error::new(
                std::io::ErrorKind::Interrupted,
                format!("interrupted at t = {} s (step {k})", (k as f64 * self.dt_s * 1e6).round() / 1e6),
            ));
        }
        if self.writer.wants(k, k == self.steps) {
            self.writer.leader_row(k as f64 * self.dt_s, state)?;
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

/// Runs a scenario in process with the followers of each step on `threads`
/// threads (1: one after another; the numbers are the same for any count),
/// writes its run folder and returns its summary and where it went.
/// `progress(k)` is called every 1000 steps. A run that stops early keeps
/// what it recorded, with the summary of an incomplete run
/// ([`SimError::Kept`]).
pub fn run_to_folder(
    scenario: &Scenario,
    opts: &RecordOptions,
    threads: usize,
    progress: impl FnMut(u64) + Send,
) -> Result<(Summary, PathBuf), SimError> {
    run_to_folder_until(scenario, opts, threads, None, progress)
}

/// [`run_to_folder`] that stops at the step after `stop` is set (Ctrl-C),
/// keeping what it recorded as a run stopped early does
/// ([`SimError::Kept`], its source an `Interrupted` IO error).
pub fn run_to_folder_until(
    scenario: &Scenario,
    opts: &RecordOptions,
    threads: usize,
    stop: Option<&AtomicBool>,
    progress: impl FnMut(u64) + Send,
) -> Result<(Summary, PathBuf), SimError> {
    if threads > 1 {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| SimError::Threads { threads, what: e.to_string() })?;
        return pool.install(|| run_folder(scenario, opts, true, stop, progress));
    }
    run_folder(scenario, opts, false, stop, progress)
}

fn run_folder(
    scenario: &Scenario,
    opts: &RecordOptions,
    parallel: bool,
    stop: Option<&AtomicBool>,
    progress: impl FnMut(u64),
) -> Result<(Summary, PathBuf), SimError> {
    let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
    let mut writer = RunWriter::create(opts, &ids)?;
    let mut sim = Simulation::new(scenario);
    sim.set_parallel(parallel);
    let mut observer = FolderObserver::new(&mut writer, scenario);
    observer.stop = stop;
    let result = sim.run(&mut observer, progress);
    match result {
        Ok(metrics) => {
            let mut summary = Summary::new(scenario, ids.iter().copied().zip(metrics).collect())
                .with_outages(scenario, &sim.outages())
                .with_settling(&sim.settling());
            summary.safety = sim.proximity().cloned();
            let dir = writer.finish(&summary)?;
            Ok((summary, dir))
        }
        Err(e) => {
            // Keep what was recorded up to the failure, with the summary of
            // an incomplete run (`complete: false`).
            let mut summary =
                Summary::new(scenario, ids.iter().copied().zip(sim.metrics()).collect()).with_settling(&sim.settling());
            summary.safety = sim.proximity().cloned();
            let _ = writer.flush();
            let _ = writer.write_file("summary.json", &summary.to_json());
            Err(SimError::Kept { source: Box::new(e), kept: writer.partial_dir().to_path_buf() })
        }
    }
}
