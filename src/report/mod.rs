//! Reports over run folders: the paper's figures (Fig. 3–6) and tables
//! (Tables I–II, speed jump and chattering), the SPEC §12 claims as pass or
//! fail, and `report.md` that shows it all. `formation paper` calls this on
//! the cases it ran; `formation report` on any run folders, whether from
//! `formation sim` or from a networked run's monitor.
//!
//! A run folder is a *case*: its `summary.json`, its CSVs (if written) and,
//! when `formation paper` ran several seeds, `seeds.json` with every seed's
//! summary. Every table cell is the statistics of one number over a case's
//! seeds (just the value for one seed).
//!
//! A run that did not record every sample (`"complete": false` in its
//! summary, or, in older files, fewer samples than steps + 1) is shown as
//! such: a metric whose window it did not reach is n/a (null, never 0), cells
//! say how many seeds measured them, and every claim that uses the run is
//! N/A with the reason, never PASS.

pub mod faults;
mod network;
pub mod plots;
pub mod stats;
pub mod tables;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::cli::CliError;
use crate::record::{at_path, Summary};

/// File, in a case folder, with every seed's record (written by `formation paper`).
pub const SEEDS_FILE: &str = "seeds.json";

/// Times (s) at which SPEC §12 checks the estimator started from zero.
pub const ESTIMATOR_CHECK_TIMES_S: [f64; 2] = [4.0, 6.0];

/// What one seed of a case measured: its summary and the estimator's
/// position error at [`ESTIMATOR_CHECK_TIMES_S`] (which `summary.json` does
/// not hold).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SeedRecord {
    pub seed: u64,
    pub summary: Summary,
    /// Estimator position error ‖(x_ir, y_ir) − (x_r, y_r)‖ (m) at t = 4 s,
    /// by follower id; empty if the run is shorter or was not sampled there.
    #[serde(default)]
    pub estimator_error_4s: BTreeMap<u32, f64>,
    /// The same at t = 6 s.
    #[serde(default)]
    pub estimator_error_6s: BTreeMap<u32, f64>,
}

/// The part a case plays in the paper's comparisons (SPEC §12), read from
/// its summary's settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Role {
    /// Bioinspired backstepping, bioinspired SMC, ASIF, normal case.
    Proposed,
    /// Conventional backstepping (bioinspired SMC, ASIF).
    ConventionalBackstepping,
    /// Conventional sliding mode control (bioinspired backstepping, ASIF).
    ConventionalSmc,
    /// Second-order (super-twisting) sliding mode control.
    SuperTwisting,
    /// The proposed controllers with a Kalman filter, normal case.
    KfNormal,
    /// The proposed controllers with a Kalman filter, fault case.
    KfFault,
    /// The proposed method, fault case.
    AsifFault,
    /// The proposed method with the estimator started from zero.
    ZeroInit,
    /// Anything else.
    Other,
}

impl Role {
    pub fn of(s: &Summary) -> Role {
        let fault = s.fault_time.is_some();
        let zero = s.estimate_init == "zero";
        match (s.kinematic.as_str(), s.dynamic.as_str(), s.filter.as_str(), fault, zero) {
            ("bio", "bio", "asif", false, false) => Role::Proposed,
            ("conventional", "bio", "asif", false, false) => Role::ConventionalBackstepping,
            ("bio", "smc", "asif", false, false) => Role::ConventionalSmc,
            ("bio", "super-twisting", "asif", false, false) => Role::SuperTwisting,
            ("bio", "bio", "kf", false, false) => Role::KfNormal,
            ("bio", "bio", "kf", true, false) => Role::KfFault,
            ("bio", "bio", "asif", true, false) => Role::AsifFault,
            ("bio", "bio", "asif", false, true) => Role::ZeroInit,
            _ => Role::Other,
        }
    }
}

/// One run folder with all its seeds.
#[derive(Clone, Debug)]
pub struct Case {
    /// The folder's name; names the case in every figure and table.
    pub label: String,
    pub dir: PathBuf,
    /// At least one; the first is the folder's own `summary.json`.
    pub seeds: Vec<SeedRecord>,
    pub role: Role,
    /// The folder holds `leader.csv` and a CSV per follower.
    pub has_csv: bool,
    /// The folder came from a networked run (it holds `network.json`).
    pub networked: bool,
}

impl Case {
    pub fn summary(&self) -> &Summary {
        &self.seeds[0].summary
    }

    /// Follower ids of the case, ascending.
    pub fn follower_ids(&self) -> Vec<u32> {
        self.summary().followers.keys().copied().collect()
    }

    /// A one-line description of the case's settings.
    pub fn settings(&self) -> String {
        let s = self.summary();
        let fault = s.fault_time.map(|t| format!("fault at {t} s")).unwrap_or_else(|| "normal".into());
        let seeds = if self.seeds.len() > 1 {
            format!("seeds {}..{} ({})", self.seeds[0].seed, self.seeds[self.seeds.len() - 1].seed, self.seeds.len())
        } else {
            format!("seed {}", s.seed)
        };
        let short = self.incomplete_seeds();
        let incomplete = match short.first() {
            None => String::new(),
            Some(r) if self.seeds.len() == 1 => {
                format!(", INCOMPLETE: {}", r.summary.shortfall_text().unwrap_or_default())
            }
            Some(_) => format!(", INCOMPLETE: {} of {} seeds", short.len(), self.seeds.len()),
        };
        let links = if s.faults.is_empty() {
            String::new()
        } else {
            let list: Vec<&str> = s.faults.iter().map(|f| f.fault.as_str()).collect();
            format!(", link faults: {}, rejoin {}", list.join("; "), s.rejoin.as_deref().unwrap_or("consensus"))
        };
        format!(
            "kinematic {}, dynamic {}, filter {}, {fault}, estimate init {}, T = {} s, noise {}, {seeds}{}{links}{incomplete}",
            s.kinematic,
            s.dynamic,
            s.filter,
            s.estimate_init,
            s.duration,
            if s.noise { "on" } else { "off" },
            if self.networked { ", networked" } else { "" }
        )
    }

    /// The seeds whose run did not record every sample.
    pub fn incomplete_seeds(&self) -> Vec<&SeedRecord> {
        self.seeds.iter().filter(|r| !r.summary.complete).collect()
    }

    /// Reads a run folder: `summary.json`, and `seeds.json` if present.
    /// Without `seeds.json`, the estimator errors at 4 s and 6 s come from the
    /// follower CSVs when they cover those times.
    pub fn load(dir: &Path, label: String) -> Result<Case, CliError> {
        if !dir.is_dir() {
            return Err(CliError::Input(format!("{}: no such run folder", dir.display())));
        }
        let summary_path = dir.join("summary.json");
        let text = fs::read_to_string(&summary_path).map_err(|e| {
            CliError::Input(format!("{}: not a run folder (cannot read summary.json: {e})", dir.display()))
        })?;
        let mut summary: Summary = serde_json::from_str(&text)
            .map_err(|e| CliError::Input(format!("{}: invalid summary.json: {e}", summary_path.display())))?;
        summary.mark_unreached();
        let ids: Vec<u32> = summary.followers.keys().copied().collect();
        let has_csv =
            dir.join("leader.csv").is_file() && ids.iter().all(|id| dir.join(format!("follower_{id}.csv")).is_file());
        let seeds_path = dir.join(SEEDS_FILE);
        let seeds = if seeds_path.is_file() {
            let text = fs::read_to_string(&seeds_path).map_err(at_path(&seeds_path, "cannot read"))?;
            let mut seeds: Vec<SeedRecord> = serde_json::from_str(&text)
                .map_err(|e| CliError::Input(format!("{}: invalid: {e}", seeds_path.display())))?;
            for r in &mut seeds {
                r.summary.mark_unreached();
            }
            if seeds.is_empty() {
                return Err(CliError::Input(format!("{}: no seeds", seeds_path.display())));
            }
            seeds
        } else {
            let (e4, e6) =
                if has_csv { estimator_checkpoints_from_csv(dir, &ids, summary.dt)? } else { Default::default() };
            vec![SeedRecord { seed: summary.seed, summary, estimator_error_4s: e4, estimator_error_6s: e6 }]
        };
        let role = Role::of(&seeds[0].summary);
        Ok(Case { label, dir: dir.to_path_buf(), seeds, role, has_csv, networked: dir.join("network.json").is_file() })
    }
}

/// A value per follower id.
type ErrorById = BTreeMap<u32, f64>;

/// The estimator position error at t = 4 s and 6 s from a folder's CSVs:
/// the sample within half a step of the time, if there is one.
fn estimator_checkpoints_from_csv(dir: &Path, ids: &[u32], dt_s: f64) -> Result<(ErrorById, ErrorById), CliError> {
    let mut at = [BTreeMap::new(), BTreeMap::new()];
    for &id in ids {
        let table = plots::read_columns(&dir.join(format!("follower_{id}.csv")), &["t", "estimator_error"])?;
        for (slot, &time) in at.iter_mut().zip(&ESTIMATOR_CHECK_TIMES_S) {
            let hit = table[0].iter().position(|&t| (t - time).abs() <= 0.5 * dt_s + 1e-9);
            if let Some(i) = hit {
                slot.insert(id, table[1][i]);
            }
        }
    }
    let [a, b] = at;
    Ok((a, b))
}

/// How the report was made and what it compares.
#[derive(Clone, Debug)]
pub struct Context {
    /// Paper mode: the figures and tables pick the paper's cases by role
    /// and use the paper's wording; otherwise every case is compared,
    /// labelled by folder name.
    pub paper: bool,
    /// The exact command that made the report.
    pub command: String,
    /// Values the claims are checked against.
    pub params: tables::ClaimParams,
    /// Extra lines for the report's header (seeds, wall time, …).
    pub notes: Vec<String>,
    /// `formation paper`'s outage study, when it ran.
    pub study: Option<faults::Study>,
}

/// What a report shows besides its files: the claims, and text for the
/// terminal about link faults (the study's findings, or each folder's table
/// of metrics under faults).
#[derive(Clone, Debug)]
pub struct Written {
    pub claims: Vec<tables::Check>,
    pub faults: String,
}

/// Writes every figure, table and `report.md` into `out`; returns the path
/// of `report.md` and what it shows.
pub fn write_report(out: &Path, cases: &[Case], ctx: &Context) -> Result<(PathBuf, Written), CliError> {
    fs::create_dir_all(out).map_err(at_path(out, "cannot create the folder"))?;
    let colours = plots::colours(cases, ctx.paper);
    let tables = tables::build(cases, ctx);
    for t in &tables.tables {
        let path = out.join(format!("{}.csv", t.file));
        fs::write(&path, &t.csv).map_err(at_path(&path, "cannot write"))?;
    }
    let path = out.join("claims.csv");
    fs::write(&path, tables::claims_csv(&tables.claims)).map_err(at_path(&path, "cannot write"))?;
    let figures = plots::draw_all(out, cases, ctx, &colours)?;

    let mut md = String::new();
    let title = if ctx.paper { "Reproducing the paper" } else { "Run comparison" };
    let _ = writeln!(md, "# {title}\n");
    if ctx.paper {
        let _ = writeln!(
            md,
            "Xu, Yan, Yang, Gadsden, \"Distributed Leader Follower Formation Control of Mobile Robots based on \
             Bioinspired Neural Dynamics and Adaptive Sliding Innovation Filter\", IEEE TII 2023, section IV, \
             reproduced on the scenario of SPEC §10.\n"
        );
    }
    let _ = writeln!(md, "Made by:\n\n```\n{}\n```\n", ctx.command);
    for n in &ctx.notes {
        let _ = writeln!(md, "- {n}");
    }
    if !ctx.notes.is_empty() {
        md.push('\n');
    }
    let multi = cases.iter().any(|c| c.seeds.len() > 1);
    if multi {
        let _ = writeln!(
            md,
            "Each table cell reads mean ± standard deviation over seeds [95 % confidence interval of the mean, \
             Student's t]. Figures show the first seed.\n"
        );
    }

    let _ = writeln!(md, "## Cases\n\n| case | settings | folder |\n| --- | --- | --- |");
    for c in cases {
        let _ = writeln!(md, "| {} | {} | `{}` |", c.label, c.settings(), c.dir.display());
    }
    md.push('\n');

    let _ = writeln!(md, "## Claims (SPEC §12)\n");
    md += &tables::claims_markdown(&tables.claims);
    md.push('\n');

    let _ = writeln!(md, "## Figures\n");
    if !figures.is_empty() {
        let _ = writeln!(
            md,
            "Figures are drawn from the samples the runs wrote to CSV (`formation paper` writes every 10th step by \
             default, `--every 1` writes all). Conventional SMC switches at every step, so a thinned Fig. 6 \
             under-samples its chattering; the tables' torque variation always uses every step.\n"
        );
    }
    for f in &figures {
        let _ = writeln!(md, "### {}\n", f.title);
        let _ = writeln!(md, "![{}]({}.png)\n", f.title, f.file);
        let _ = writeln!(md, "{}\n", f.caption);
        let _ = writeln!(md, "Files: [{0}.svg]({0}.svg), [{0}.png]({0}.png), data [{0}.csv]({0}.csv).\n", f.file);
    }
    if figures.is_empty() {
        let _ = writeln!(md, "No case has CSV time series, so there are no figures.\n");
    }

    let _ = writeln!(md, "## Tables\n");
    for t in &tables.tables {
        let _ = writeln!(md, "### {}\n", t.title);
        md += &t.markdown;
        let _ = writeln!(md, "\nData: [{0}.csv]({0}.csv).\n", t.file);
    }
    let faulted: Vec<&Case> = cases.iter().filter(|c| !c.summary().faults.is_empty()).collect();
    let link_faults = faults::write(out, &faulted, ctx.study.as_ref())?;
    md += &link_faults.markdown;
    let networked: Vec<&Case> = cases.iter().filter(|c| c.networked).collect();
    md += &network::write(out, &networked)?;
    let path = out.join("report.md");
    fs::write(&path, md).map_err(at_path(&path, "cannot write"))?;
    Ok((path, Written { claims: tables.claims, faults: link_faults.terminal }))
}

/// `formation report`: the figures and tables for any run folders.
#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    /// Run folders (from `formation sim`, `formation paper` or a networked
    /// run's monitor). Each is labelled by its folder name.
    #[arg(required = true, value_name = "RUN_DIR")]
    pub runs: Vec<PathBuf>,
    /// Report folder to write.
    #[arg(long, default_value = "runs/report")]
    pub out: PathBuf,
    /// Print nothing but errors.
    #[arg(long, short)]
    pub quiet: bool,
}

/// Runs `formation report`.
pub fn run(a: &ReportArgs) -> Result<(), CliError> {
    let mut cases = Vec::with_capacity(a.runs.len());
    let mut used = BTreeMap::<String, usize>::new();
    for dir in &a.runs {
        let base = dir
            .canonicalize()
            .ok()
            .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
            .unwrap_or_else(|| dir.display().to_string());
        // Two folders of the same name (different parents) get -2, -3, ….
        let n = used.entry(base.clone()).or_insert(0);
        *n += 1;
        let label = if *n == 1 { base } else { format!("{base}-{n}") };
        cases.push(Case::load(dir, label)?);
    }
    let command = std::iter::once("formation report".to_string())
        .chain(a.runs.iter().map(|p| p.display().to_string()))
        .chain(["--out".to_string(), a.out.display().to_string()])
        .collect::<Vec<_>>()
        .join(" ");
    // Run folders do not record gains: the claims' thresholds are SPEC §10's.
    let notes = vec!["Run folders do not record their gains, so the claims are checked against SPEC §10's values \
         (C₁ = 3, B = 2, max v_r = √2, F4 starting at x̂ = 5, so a 15 m/s jump); for other scenarios use \
         `formation paper --scenario FILE`."
        .to_string()];
    let ctx = Context { paper: false, command, params: tables::ClaimParams::paper_defaults(), notes, study: None };
    let (path, built) = write_report(&a.out, &cases, &ctx)?;
    if !a.quiet {
        print!("{}", tables::claims_text(&built.claims));
        print!("{}", built.faults);
        println!("wrote {}", path.display());
    }
    Ok(())
}
