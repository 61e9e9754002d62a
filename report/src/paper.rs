//! `formation paper`: runs every case the paper compares (docs/model.md §12) on the
//! paper scenario, for one or many seeds in parallel, and writes the report
//! (figures, tables, claims) next to the cases' run folders.
//!
//! Each case is a run folder under the report folder, so `formation report`
//! can read it again. Only the first seed writes CSVs (decimated by
//! `--every`, for the figures); every seed's metrics go to the case's
//! `seeds.json`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use formation_scenario::Scenario;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use rayon::prelude::*;

use crate::study;
use crate::{tables, Case, ClaimParams, Context, SeedRecord, ESTIMATOR_CHECK_TIMES_S, SEEDS_FILE};
use formation_exit::{at_least_one, Error};
use formation_record::{at_path, RecordOptions, Row, RunWriter, Summary};
use formation_sim::{FolderObserver, Observer, Simulation};

#[derive(Debug)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct PaperArgs {
    /// Scenario file the cases are built on.
    #[cfg_attr(feature = "clap", arg(long, default_value = "scenarios/paper.toml"))]
    pub scenario: PathBuf,
    /// Override a scenario value in every case, e.g. `--set duration=5`.
    /// Keys that define a case (kinematic, dynamic, filter, estimate_init)
    /// are set by the case; `fault.time` sets the fault cases' fault time.
    #[cfg_attr(feature = "clap", arg(long = "set", value_name = "KEY=VALUE"))]
    pub overrides: Vec<String>,
    /// Seeds per case: the scenario's seed s and s+1 … s+N−1.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1, value_name = "N"))]
    pub seeds: u64,
    /// Report folder; each case's run folder goes inside it.
    #[cfg_attr(feature = "clap", arg(long, default_value = "runs/paper-report"))]
    pub out: PathBuf,
    /// Write every N-th sample of the first seed to the CSVs the figures read.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 10, value_name = "N"))]
    pub every: u64,
    /// Print nothing but errors.
    #[cfg_attr(feature = "clap", arg(long, short))]
    pub quiet: bool,
    /// Skip the outage study (docs/model.md §14) that follows the paper's cases.
    #[cfg_attr(feature = "clap", arg(long))]
    pub no_study: bool,
}

/// One case the paper compares.
#[derive(Clone, Copy, Debug)]
pub struct PaperCase {
    /// Folder name.
    pub name: &'static str,
    pub description: &'static str,
    /// The keys that define the case.
    pub overrides: &'static [&'static str],
    /// The fault case (filter model wrong from t_fault on).
    pub fault: bool,
}

const PROPOSED: &[&str] = &["kinematic=bio", "dynamic=bio", "filter=asif", "estimate_init=leader"];

/// Every case of docs/model.md §12.
pub const CASES: [PaperCase; 8] = [
    PaperCase {
        name: "proposed",
        description: "bioinspired backstepping, bioinspired SMC, ASIF, normal case",
        overrides: PROPOSED,
        fault: false,
    },
    PaperCase {
        name: "conventional-backstepping",
        description: "conventional backstepping (Fig. 5)",
        overrides: &["kinematic=conventional", "dynamic=bio", "filter=asif", "estimate_init=leader"],
        fault: false,
    },
    PaperCase {
        name: "conventional-smc",
        description: "conventional sliding mode control (Fig. 6)",
        overrides: &["kinematic=bio", "dynamic=smc", "filter=asif", "estimate_init=leader"],
        fault: false,
    },
    PaperCase {
        name: "super-twisting",
        description: "second-order (super-twisting) sliding mode control (Fig. 6)",
        overrides: &["kinematic=bio", "dynamic=super-twisting", "filter=asif", "estimate_init=leader"],
        fault: false,
    },
    PaperCase {
        name: "kf-normal",
        description: "Kalman filter, normal case (Table I)",
        overrides: &["kinematic=bio", "dynamic=bio", "filter=kf", "estimate_init=leader"],
        fault: false,
    },
    PaperCase {
        name: "kf-fault",
        description: "Kalman filter, fault case (Table II)",
        overrides: &["kinematic=bio", "dynamic=bio", "filter=kf", "estimate_init=leader"],
        fault: true,
    },
    PaperCase { name: "asif-fault", description: "ASIF, fault case (Table II)", overrides: PROPOSED, fault: true },
    PaperCase {
        name: "zero-init",
        description: "estimator started from zero estimates",
        overrides: &["kinematic=bio", "dynamic=bio", "filter=asif", "estimate_init=zero"],
        fault: false,
    },
];

/// The fault time of section IV, s.
pub const PAPER_FAULT_TIME_S: f64 = 10.0;

/// The scenario of a case: the user's overrides, then the case's keys; the
/// fault cases get the fault at 10 s unless the user or the file sets one, and
/// the normal cases have no fault.
pub fn case_scenario(path: &Path, user: &[String], case: &PaperCase) -> Result<Scenario, Error> {
    let keys: Vec<String> = case.overrides.iter().map(|s| s.to_string()).collect();
    scenario_with(path, user, &keys, case.fault)
}

/// The scenario of a case given by its keys (set after the user's
/// overrides) and whether it is a fault case (see [`case_scenario`]).
pub fn scenario_with(path: &Path, user: &[String], keys: &[String], fault: bool) -> Result<Scenario, Error> {
    let mut overrides: Vec<String> = user.to_vec();
    overrides.extend(keys.iter().cloned());
    let paper_fault = fault
        && !user.iter().any(|o| o.trim_start().starts_with("fault.time"))
        && !Scenario::load(path, user).is_ok_and(|s| s.control.fault.is_some());
    if paper_fault {
        // Validates the file's fault factors; the time is the paper's, set
        // below, also in a run that ends before it (`--set duration=3`),
        // whose fault claims are then N/A. A fault time the user gives must
        // lie within the run.
        overrides.push("fault.time=0".into());
    }
    let mut s = Scenario::load(path, &overrides).map_err(|e| Error::Input(e.to_string()))?;
    if paper_fault {
        if let Some(f) = std::sync::Arc::make_mut(&mut s.control).fault.as_mut() {
            f.time_s = PAPER_FAULT_TIME_S;
        }
        s.source.fault.time = Some(PAPER_FAULT_TIME_S);
    }
    if !fault {
        std::sync::Arc::make_mut(&mut s.control).fault = None;
    }
    Ok(s)
}

/// The estimator error of every follower at the check times (and, through
/// the folder observer, the first seed's CSVs).
struct PaperObserver<'w> {
    folder: Option<FolderObserver<'w>>,
    ids: Vec<u32>,
    check_steps: [Option<u64>; 2],
    at_checks: [BTreeMap<u32, f64>; 2],
    vc_initial: BTreeMap<u32, f64>,
}

impl Observer for PaperObserver<'_> {
    fn leader(&mut self, k: u64, state: &formation_leader::LeaderState) -> std::io::Result<()> {
        match &mut self.folder {
            Some(f) => f.leader(k, state),
            None => Ok(()),
        }
    }

    fn follower(&mut self, index: usize, k: u64, row: &Row, last: bool) -> std::io::Result<()> {
        if let Some(f) = &mut self.folder {
            f.follower(index, k, row, last)?;
        }
        if k == 0 {
            self.vc_initial.insert(self.ids[index], row.v_c);
        }
        for (slot, at) in self.check_steps.iter().zip(&mut self.at_checks) {
            if *slot == Some(k) {
                at.insert(self.ids[index], row.estimator_error);
            }
        }
        Ok(())
    }
}

/// Runs one seed of a scenario; writes its run folder if `record` is given.
pub fn run_seed(scenario: &Scenario, seed: u64, record: Option<&RecordOptions>) -> Result<SeedRecord, Error> {
    let mut s = scenario.clone();
    s.seed = seed;
    let ids: Vec<u32> = s.followers.iter().map(|f| f.id).collect();
    let steps = s.steps();
    let check_steps = ESTIMATOR_CHECK_TIMES_S.map(|t| {
        let k = (t / s.dt_s).round() as u64;
        (k <= steps).then_some(k)
    });
    let mut writer = record.map(|o| RunWriter::create(o, &ids)).transpose()?;
    let mut sim = Simulation::new(&s);
    let (metrics, at_checks, vc_initial) = {
        let folder = writer.as_mut().map(|w| FolderObserver::new(w, &s));
        let mut obs = PaperObserver {
            folder,
            ids: ids.clone(),
            check_steps,
            at_checks: Default::default(),
            vc_initial: Default::default(),
        };
        let metrics = sim.run(&mut obs, |_| {}).map_err(|e| Error::Run(format!("{} seed {seed}: {e}", s.name)))?;
        (metrics, obs.at_checks, obs.vc_initial)
    };
    let summary = Summary::new(&s, ids.iter().copied().zip(metrics).collect()).with_outages(&s, &sim.outages());
    if let Some(w) = writer {
        w.finish(&summary)?;
    }
    let [e4, e6] = at_checks;
    Ok(SeedRecord { seed, summary, estimator_error_4s: e4, estimator_error_6s: e6, vc_initial })
}

/// Runs `formation paper`.
pub fn run(a: &PaperArgs) -> Result<(), Error> {
    at_least_one("--seeds", a.seeds)?;
    at_least_one("--every", a.every)?;
    crate::error::check_out("--out", &a.out)?;
    crate::outdir::check(&a.out, crate::outdir::Kind::Paper)?;
    let started = Instant::now();
    let base = Scenario::load(&a.scenario, &a.overrides).map_err(|e| Error::Input(e.to_string()))?;
    let plan = if a.no_study { None } else { Some(study::plan(&base)) };
    // Every case's folder name and scenario: the paper's, then the study's.
    let mut runs: Vec<(String, Scenario)> = CASES
        .iter()
        .map(|c| Ok((c.name.to_string(), case_scenario(&a.scenario, &a.overrides, c)?)))
        .collect::<Result<_, Error>>()?;
    for c in plan.iter().flat_map(|p| &p.cases) {
        runs.push((c.name.clone(), scenario_with(&a.scenario, &a.overrides, &c.overrides, false)?));
    }
    let seeds: Vec<u64> = (0..a.seeds).map(|i| base.seed + i).collect();
    // The runs and seeds.json under <out>.partial; moved into place once
    // every run is done, then the report is written beside them.
    let output = crate::outdir::Output::begin(&a.out, crate::outdir::Kind::Paper)?;

    let jobs: Vec<(usize, usize)> = (0..runs.len()).flat_map(|c| (0..seeds.len()).map(move |s| (c, s))).collect();
    let results = run_all(a, &runs, &seeds, &jobs, output.dir());
    let run_time = started.elapsed();

    let mut per_case: Vec<Vec<SeedRecord>> = vec![Vec::new(); runs.len()];
    let mut failures = Vec::new();
    for (&(c, _), r) in jobs.iter().zip(results) {
        match r {
            Ok(rec) => per_case[c].push(rec),
            Err(e) => failures.push(format!("{}: {e}", runs[c].0)),
        }
    }
    if !failures.is_empty() {
        return Err(Error::Run(format!("{} run(s) failed:\n  {}", failures.len(), failures.join("\n  "))));
    }
    for ((name, _), recs) in runs.iter().zip(&per_case) {
        let json = serde_json::to_string_pretty(recs).map_err(|e| Error::Run(e.to_string()))?;
        let path = output.dir().join(name).join(SEEDS_FILE);
        std::fs::write(&path, json + "\n").map_err(at_path(&path, "cannot write"))?;
    }
    // An earlier output goes; if the report below fails, the runs stay
    // (their seeds.json says whose they are, so a rerun replaces them).
    let out = output.finish()?;
    let mut cases = Vec::with_capacity(runs.len());
    for (name, _) in &runs {
        cases.push(Case::load(&out.join(name), name.clone())?);
    }
    let study_cases = cases.split_off(CASES.len());
    let study = plan.map(|p| {
        let kinds: Vec<bool> = p.cases.iter().map(|c| c.sweep).collect();
        study::study(kinds.into_iter().zip(study_cases).collect(), p)
    });

    let command = command_line(a);
    let threads = rayon::current_num_threads();
    let study_count = runs.len() - CASES.len();
    let notes = vec![
        format!(
            "{} cases{} × {} seed(s) (seeds {}..={}) = {} runs of {} s, on {threads} threads: {:.1} s wall time for the runs.",
            runs.len(),
            if study_count > 0 { format!(" ({} of the paper, {study_count} of the outage study)", CASES.len()) } else { String::new() },
            seeds.len(),
            seeds[0],
            seeds[seeds.len() - 1],
            jobs.len(),
            base.duration_s,
            run_time.as_secs_f64()
        ),
        format!(
            "The first seed of each case writes its CSVs (one sample in {}); the figures show it.",
            a.every
        ),
    ];
    let ctx = Context { paper: true, command, params: ClaimParams::from_scenario(&base), notes, study };
    let (path, built) = crate::write_report(&a.out, &cases, &ctx)?;
    if !a.quiet {
        print!("{}", tables::claims_text(&built.claims));
        print!("{}", built.faults);
        println!(
            "{} runs in {:.1} s, report in {:.1} s total",
            jobs.len(),
            run_time.as_secs_f64(),
            started.elapsed().as_secs_f64()
        );
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// Every (case, seed) job on rayon's threads, with a progress bar; the first seed of each case records its folder under `dir`.
fn run_all(
    a: &PaperArgs,
    runs: &[(String, Scenario)],
    seeds: &[u64],
    jobs: &[(usize, usize)],
    dir: &Path,
) -> Vec<Result<SeedRecord, Error>> {
    let bar = ProgressBar::with_draw_target(
        Some(jobs.len() as u64),
        if a.quiet { ProgressDrawTarget::hidden() } else { ProgressDrawTarget::stderr() },
    );
    bar.set_style(
        ProgressStyle::with_template("runs [{bar:30}] {pos}/{len} {elapsed} (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let results: Vec<Result<SeedRecord, Error>> = jobs
        .par_iter()
        .map(|&(c, s)| {
            let record = (s == 0).then(|| RecordOptions {
                dir: dir.join(&runs[c].0),
                every: a.every,
                csv: true,
                mcap: false,
                rosbag2: false,
            });
            let r = run_seed(&runs[c].1, seeds[s], record.as_ref());
            bar.inc(1);
            r
        })
        .collect();
    bar.finish_and_clear();
    results
}

/// The command that made the report, as the report quotes it.
fn command_line(a: &PaperArgs) -> String {
    let mut command = format!("formation paper --scenario {} --seeds {}", a.scenario.display(), a.seeds);
    for o in &a.overrides {
        command += &format!(" --set {o}");
    }
    command += &format!(" --out {} --every {}", a.out.display(), a.every);
    if a.no_study {
        command += " --no-study";
    }
    command
}
