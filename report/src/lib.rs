//! Reports over run folders: the paper's figures (Fig. 3–6) and tables
//! (Tables I–II, speed jump and chattering), the docs/model.md §12 claims as pass or
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
//!
//! # Examples
//!
//! The tables' cells: a mean over seeds with its 95 % confidence interval
//! (Student's t), as `formation paper` prints it.
//!
//! ```
//! use formation_report::stats::Stat;
//!
//! let rms = Stat::of(&[0.010, 0.012, 0.011, 0.013, 0.009]).expect("five seeds");
//! assert_eq!(rms.n, 5);
//! assert!((rms.mean - 0.011).abs() < 1e-12);
//! assert!(rms.ci_low < rms.mean && rms.mean < rms.ci_high);
//! assert!(Stat::of(&[]).is_none());
//! ```

//!
//! No network, no async runtime: this crate reads run folders and runs the
//! simulator, whoever wrote the folders.

pub mod calibrate;
pub mod case;
pub mod error;
pub mod explain;
pub mod faults;
mod network;
pub mod outdir;
pub mod paper;
pub mod plots;
pub mod progress;
mod safety;
pub mod stats;
pub mod study;
pub mod tables;
pub mod words;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

use formation_exit::Error;
use formation_record::at_path;

pub use case::{Case, ClaimParams, Context, Role, SeedRecord, Study, ESTIMATOR_CHECK_TIMES_S, SEEDS_FILE};

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
pub fn write_report(out: &Path, cases: &[Case], ctx: &Context) -> Result<(PathBuf, Written), Error> {
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
             reproduced on the scenario of docs/model.md §10.\n"
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

    let _ = writeln!(md, "## Claims (docs/model.md §12)\n");
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
    md += &safety::write(out, cases)?;
    let networked: Vec<&Case> = cases.iter().filter(|c| c.networked).collect();
    md += &network::write(out, &networked)?;
    md += &explain::write(out, &networked)?;
    let path = out.join("report.md");
    fs::write(&path, md).map_err(at_path(&path, "cannot write"))?;
    Ok((path, Written { claims: tables.claims, faults: link_faults.terminal }))
}

/// `formation report`: the figures and tables for any run folders.
#[derive(Debug)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct ReportArgs {
    /// Run folders (from `formation sim`, `formation paper` or a networked
    /// run's monitor). Each is labelled by its folder name.
    #[cfg_attr(feature = "clap", arg(required = true, value_name = "RUN_DIR"))]
    pub runs: Vec<PathBuf>,
    /// Report folder to write.
    #[cfg_attr(feature = "clap", arg(long, default_value = "runs/report"))]
    pub out: PathBuf,
    /// Print nothing but errors.
    #[cfg_attr(feature = "clap", arg(long, short))]
    pub quiet: bool,
}

/// Runs `formation report`.
pub fn run(a: &ReportArgs) -> Result<(), Error> {
    crate::error::check_out("--out", &a.out)?;
    // The report's files go into --out: never into one of the folders it reads.
    if let Ok(out) = a.out.canonicalize() {
        if let Some(dir) = a.runs.iter().find(|d| d.canonicalize().is_ok_and(|d| d == out)) {
            return Err(Error::Input(format!(
                "--out {} is the run folder {}: the report would write its files among what it reads (choose \
                 another --out)",
                a.out.display(),
                dir.display()
            )));
        }
    }
    crate::outdir::check(&a.out, crate::outdir::Kind::Report)?;
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
    // Run folders do not record gains: the claims' thresholds are docs/model.md §10's.
    let notes =
        vec!["Run folders do not record their gains, so the claims are checked against docs/model.md §10's values \
         (C₁ = 3, B = 2, max v_r = √2, F4 starting at x̂ = 5, so a 15 m/s jump); for other scenarios use \
         `formation paper --scenario FILE`."
            .to_string()];
    let ctx = Context { paper: false, command, params: ClaimParams::paper_defaults(), notes, study: None };
    let output = crate::outdir::Output::begin(&a.out, crate::outdir::Kind::Report)?;
    let (_, built) = write_report(output.dir(), &cases, &ctx)?;
    let path = output.finish()?.join("report.md");
    if !a.quiet {
        print!("{}", tables::claims_text(&built.claims));
        print!("{}", built.faults);
        println!("wrote {}", path.display());
    }
    Ok(())
}
