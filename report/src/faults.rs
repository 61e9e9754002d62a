//! Link faults in reports (docs/model.md §14): the table of metrics around each fault
//! window for every case that has faults (over its seeds), the figure of
//! estimator and formation error with the windows shaded, and `formation
//! paper`'s outage study: `adopt` against `consensus`, bioinspired against
//! conventional backstepping, the loss sweep, and what their numbers show.
//!
//! Every sentence about the study is computed from the numbers in the
//! tables; none is written in advance.

use std::fmt::Write as _;
use std::path::Path;

use crate::case::{Case, Study};
use crate::plots::{self, Figure, FigureSpec, Line, Panel};
use crate::stats::Stat;
use crate::tables::{csv_field, md_cell, sig, stat_fields, stat_text, Table, STAT_HEADER};
use formation_exit::Error;
use formation_record::outage::{OutageMetrics, AFTER_S, RECOVERED_M, STAY_S};
use formation_record::{at_path, Summary};

/// The follower whose links the outage study cuts.
pub const STUDY_NODE: u32 = 3;

/// Cases shown in the outage figure at most (two panels each).
const MAX_FIGURE_CASES: usize = 8;

/// Reads one metric around a fault window (`None`: not measured).
type OutageFn = fn(&OutageMetrics) -> Option<f64>;

/// The metrics around a fault window: key, header, unit, reader. The
/// markdown table shows all but ω̇_c; the CSV has all.
const OUTAGE_METRICS: [(&str, &str, &str, OutageFn); 7] = [
    ("peak_estimator_error", "peak estimator error", "m", |m| m.peak_estimator_error),
    ("recovery_s", "recovery", "s", |m| m.recovery_s),
    ("peak_formation_error", "peak formation error", "m", |m| m.peak_formation_error),
    ("peak_vc", "peak |v_c|", "m/s", |m| m.peak_vc),
    ("peak_vc_rate", "peak |v̇_c|", "m/s²", |m| m.peak_vc_rate),
    ("peak_torque", "peak |τ|", "N m", |m| m.peak_torque),
    ("peak_wc_rate", "peak |ω̇_c|", "rad/s²", |m| m.peak_wc_rate),
];
/// Positions in [`OUTAGE_METRICS`].
const ESTIMATOR: usize = 0;
const RECOVERY: usize = 1;
const FORMATION: usize = 2;
const VC: usize = 3;
const VC_RATE: usize = 4;
const TORQUE: usize = 5;
/// The markdown table shows the first six.
const SHOWN: usize = 6;

/// One quantity over a case's seeds: the values of the seeds that measured
/// it and how many seeds there are.
#[derive(Clone, Debug, Default)]
struct Values {
    values: Vec<f64>,
    seeds: usize,
}

impl Values {
    fn stat(&self) -> Option<Stat> {
        Stat::of(&self.values)
    }

    fn mean(&self) -> Option<f64> {
        self.stat().map(|s| s.mean)
    }

    /// A table cell; `recovery` says "not recovered" for the missing seeds.
    fn cell(&self, recovery: bool) -> String {
        let missing = self.seeds - self.values.len();
        match self.stat() {
            _ if self.seeds == 0 => "–".into(),
            None if recovery && self.seeds == 1 => "not recovered".into(),
            None if recovery => format!("not recovered ({0} of {0} seeds)", self.seeds),
            None => "n/a".into(),
            Some(s) if missing == 0 => stat_text(&s, 4),
            Some(s) if recovery => format!("{} (not recovered: {missing} of {} seeds)", stat_text(&s, 4), self.seeds),
            Some(s) => format!("{} ({} of {} seeds)", stat_text(&s, 4), s.n, self.seeds),
        }
    }
}

/// A quantity of each seed's summary over a case's seeds.
fn over_seeds(case: &Case, f: impl Fn(&Summary) -> Option<Option<f64>>) -> Values {
    let per_seed: Vec<Option<f64>> = case.seeds.iter().filter_map(|s| f(&s.summary)).collect();
    Values { seeds: per_seed.len(), values: per_seed.into_iter().flatten().collect() }
}

/// Follower `id`'s metric around fault `i` over the seeds that have it.
fn outage_values(case: &Case, i: usize, id: u32, f: OutageFn) -> Values {
    over_seeds(case, |s| Some(f(s.faults.get(i)?.followers.get(&id)?)))
}

/// The table of metrics around every fault window of every case, with
/// statistics over seeds.
fn fault_table(cases: &[&Case]) -> Table {
    let mut md = String::from("| case | rejoin | fault | follower |");
    for (_, header, unit, _) in &OUTAGE_METRICS[..SHOWN] {
        let _ = write!(md, " {} ({unit}) |", md_cell(header));
    }
    md += "\n| --- | --- | --- | --- |";
    md += &" --- |".repeat(SHOWN);
    md.push('\n');
    let mut csv = format!("case,rejoin,fault,follower,metric,unit,{STAT_HEADER},seeds\n");
    for c in cases {
        let rejoin = c.summary().rejoin.clone().unwrap_or_default();
        for (i, fault) in c.summary().faults.iter().enumerate() {
            for &id in fault.followers.keys() {
                let _ = write!(md, "| {} | {rejoin} | {} | {id} |", c.label, md_cell(&fault.fault));
                for (m, (key, _, unit, f)) in OUTAGE_METRICS.iter().enumerate() {
                    let v = outage_values(c, i, id, *f);
                    if m < SHOWN {
                        let _ = write!(md, " {} |", v.cell(m == RECOVERY));
                    }
                    if let Some(s) = v.stat() {
                        let _ = writeln!(
                            csv,
                            "{},{rejoin},{},{id},{key},{unit},{},{}",
                            csv_field(&c.label),
                            csv_field(&fault.fault),
                            stat_fields(&s),
                            v.seeds
                        );
                    }
                }
                md.push('\n');
            }
        }
    }
    md += &format!(
        "\nPeaks from each window's start until {AFTER_S} s after its end (v̇_c from consecutive steps); recovery: \
         from the window's end until the estimator position error is below {RECOVERED_M} m and stays there for \
         {STAY_S} s, over the seeds that recovered by the end of the run.\n"
    );
    Table {
        file: "table_outage".into(),
        title: "Metrics around each fault window (docs/model.md §14)".into(),
        markdown: md,
        csv,
    }
}

/// The sweep's per-seed quantities: key, unit, series, header, reader
/// (from a summary and the study's node).
type SweepFn = fn(&Summary, u32) -> Option<Option<f64>>;
const SWEEP_SERIES: [(&str, &str, &str, &str, SweepFn); 4] = [
    ("formation_rms_last10", "m", "follower", "formation-error RMS, last 10 s", |s, node| {
        Some(s.followers.get(&node)?.formation_rms_last10)
    }),
    ("formation_rms_last10", "m", "worst other", "formation-error RMS, last 10 s", |s, node| {
        let others = s.followers.iter().filter(|(&id, _)| id != node);
        Some(others.map(|(_, m)| m.formation_rms_last10).try_fold(0.0_f64, |a, v| Some(a.max(v?))))
    }),
    ("peak_estimator_error", "m", "follower", "peak estimator error", |s, node| {
        Some(s.faults.first()?.followers.get(&node)?.peak_estimator_error)
    }),
    ("peak_estimator_error", "m", "worst other", "peak estimator error", |s, node| {
        let others = s.faults.first()?.followers.iter().filter(|(&id, _)| id != node);
        Some(others.map(|(_, m)| m.peak_estimator_error).try_fold(0.0_f64, |a, v| Some(a.max(v?))))
    }),
];

/// The loss of a sweep case: its first fault's.
fn loss(c: &Case) -> f64 {
    c.summary().faults.first().map_or(f64::NAN, |f| f.loss)
}

fn series_name(series: &str, node: u32) -> String {
    match series {
        "follower" => format!("follower {node}"),
        _ => "worst of the others".into(),
    }
}

fn sweep_table(study: &Study) -> Table {
    let node = study.node;
    let mut md = String::from("| p | case |");
    for (_, unit, series, header, _) in &SWEEP_SERIES {
        let _ = write!(md, " {}: {header} ({unit}) |", series_name(series, node));
    }
    md += "\n| --- | --- |";
    md += &" --- |".repeat(SWEEP_SERIES.len());
    md.push('\n');
    let mut csv = format!("case,loss,series,metric,unit,{STAT_HEADER},seeds\n");
    for c in &study.sweep {
        let p = loss(c);
        let _ = write!(md, "| {p} | {} |", c.label);
        for (key, unit, series, _, f) in &SWEEP_SERIES {
            let v = over_seeds(c, |s| f(s, node));
            let _ = write!(md, " {} |", v.cell(false));
            if let Some(s) = v.stat() {
                let name = series_name(series, node);
                let _ =
                    writeln!(csv, "{},{p},{name},{key},{unit},{},{}", csv_field(&c.label), stat_fields(&s), v.seeds);
            }
        }
        md.push('\n');
    }
    md += &format!(
        "\nEvery message on follower {node}'s links lost with probability p over the whole run. \"Worst of the \
         others\": per seed, the largest value over the other followers. The peak estimator error is taken over \
         the whole run.{}\n",
        if study.sweep.first().is_some_and(|c| c.summary().duration <= 10.0) {
            " With T ≤ 10 s \"the last 10 s\" is the whole run, start-up included."
        } else {
            ""
        }
    );
    Table { file: "table_loss_sweep".into(), title: format!("Loss on follower {node}'s links"), markdown: md, csv }
}

/// Estimator and formation error of every follower of each case (first
/// seed, from its CSVs), log scale, with its fault windows shaded.
fn outage_figure(cases: &[&Case]) -> Result<Option<FigureSpec>, Error> {
    let drawn: Vec<&&Case> = cases.iter().filter(|c| c.has_csv).take(MAX_FIGURE_CASES).collect();
    let cut = cases.iter().filter(|c| c.has_csv).count() > drawn.len();
    let mut panels = Vec::new();
    for (n, c) in drawn.iter().enumerate() {
        let shade: Vec<(f64, f64)> = c.summary().faults.iter().map(|f| (f.from, f.to)).collect();
        let mut columns = [Vec::new(), Vec::new()];
        for (k, id) in c.follower_ids().into_iter().enumerate() {
            let path = c.dir.join(format!("follower_{id}.csv"));
            let t = formation_record::read_columns(&path, &["t", "estimator_error", "formation_error"])?;
            for (col, lines) in columns.iter_mut().enumerate() {
                lines.push(Line {
                    label: format!("Follower {id}"),
                    colour: plots::follower_colour(k),
                    width: 2,
                    points: plots::envelope(&t[0], &t[col + 1]),
                    legend: true,
                    intervals: vec![],
                });
            }
        }
        for (col, lines) in columns.into_iter().enumerate() {
            let what = ["estimator error", "formation error"][col];
            panels.push(Panel {
                caption: format!("{}: {what}", c.label),
                x_label: "t (s)".into(),
                y_label: format!("{what} (m)"),
                lines,
                outlines: vec![],
                equal_aspect: false,
                legend: n == 0 && col == 0,
                headroom: 0.6,
                shade: shade.clone(),
                log_y: true,
            });
        }
    }
    if panels.is_empty() {
        return Ok(None);
    }
    let rows = drawn.len() as u32;
    Ok(Some(FigureSpec {
        figure: Figure {
            file: "fig_outage_errors".into(),
            title: "Link faults: estimator and formation error of every follower".into(),
            caption: format!(
                "Estimator position error ‖(x_ir, y_ir) − (x_r, y_r)‖ (left) and formation error (right) of every \
                 follower against time, log scale, first seed of each case; grey: the fault windows. Values of 0 \
                 sit on the bottom edge.{}",
                if cut {
                    format!(" Only the first {MAX_FIGURE_CASES} cases with CSVs are shown.")
                } else {
                    String::new()
                }
            ),
        },
        panels,
        cols: 2,
        size: (1600, 420 * rows),
        csv_xy: ("t_s", "error_m"),
    }))
}

/// Formation RMS and peak estimator error against the loss, for the study's
/// follower and the worst of the others: means with 95 % intervals.
fn sweep_figure(study: &Study) -> Option<FigureSpec> {
    if study.sweep.is_empty() {
        return None;
    }
    let node = study.node;
    let colours = [plots::follower_colour(2), plots::follower_colour(7)];
    let mut panels = Vec::new();
    for (panel, pair) in SWEEP_SERIES.chunks(2).enumerate() {
        let lines = pair
            .iter()
            .zip(colours)
            .map(|((_, _, series, _, f), colour)| {
                let stats: Vec<(f64, Stat)> =
                    study.sweep.iter().filter_map(|c| Some((loss(c), over_seeds(c, |s| f(s, node)).stat()?))).collect();
                Line {
                    label: capitalise(&series_name(series, node)),
                    colour,
                    width: 2,
                    points: stats.iter().map(|(p, s)| (*p, s.mean)).collect(),
                    legend: true,
                    intervals: stats.iter().map(|(_, s)| (s.ci_low, s.ci_high)).collect(),
                }
            })
            .collect();
        let (_, unit, _, header, _) = pair[0];
        panels.push(Panel {
            caption: capitalise(header),
            x_label: format!("loss probability p on follower {node}'s links"),
            y_label: format!("{header} ({unit})"),
            lines,
            outlines: vec![],
            equal_aspect: false,
            legend: panel == 0,
            headroom: 0.4,
            shade: vec![],
            log_y: true,
        });
    }
    Some(FigureSpec {
        figure: Figure {
            file: "fig_loss_sweep".into(),
            title: format!("Loss on follower {node}'s links over the whole run"),
            caption: format!(
                "Formation-error RMS over the last 10 s (left) and peak estimator position error (right) against \
                 the probability p that a message on follower {node}'s links is lost, for follower {node} and the \
                 worst of the others (per seed, the largest over them); mean over seeds with its 95 % confidence \
                 interval (Student's t), log scale."
            ),
        },
        panels,
        cols: 2,
        size: (1600, 620),
        csv_xy: ("p", "value_m"),
    })
}

fn capitalise(s: &str) -> String {
    let mut c = s.chars();
    c.next().map(|f| f.to_uppercase().collect::<String>() + c.as_str()).unwrap_or_default()
}

/// "a against b" with the ratio, each mean to 3 significant digits.
fn against(a: f64, b: f64, unit: &str) -> String {
    let ratio = if b != 0.0 { format!(", {}×", sig(a / b, 2)) } else { String::new() };
    format!("{} against {} {unit}{ratio}", sig(a, 3), sig(b, 3))
}

/// A recovery over seeds in words: "0.0 s" or "2.89 s (3 of 20 seeds not recovered)".
fn recovery_words(v: &Values) -> String {
    let missing = v.seeds - v.values.len();
    match v.mean() {
        None => "never (no seed recovered)".into(),
        Some(m) if missing == 0 => format!("{} s", sig(m, 3)),
        Some(m) => format!("{} s ({missing} of {} seeds not recovered)", sig(m, 3), v.seeds),
    }
}

/// The outage case of a kinematic controller and rejoin policy.
fn find<'a>(study: &'a Study, kinematic: &str, rejoin: &str) -> Option<&'a Case> {
    study.outage.iter().find(|c| c.summary().kinematic == kinematic && c.summary().rejoin.as_deref() == Some(rejoin))
}

fn kinematic_name(k: &str) -> &str {
    match k {
        "bio" => "Bioinspired",
        "conventional" => "Conventional",
        other => other,
    }
}

/// What the study shows, as sentences computed from its numbers.
fn findings(study: &Study) -> Vec<String> {
    let node = study.node;
    let metric = |i: usize| OUTAGE_METRICS[i];
    let mut out = Vec::new();
    for kinematic in ["bio", "conventional"] {
        let (Some(a), Some(c)) = (find(study, kinematic, "adopt"), find(study, kinematic, "consensus")) else {
            continue;
        };
        let mean = |case: &Case, i: usize| outage_values(case, 0, node, metric(i).3).mean();
        let mut text = format!(
            "{} backstepping, follower {node} after its outage: `adopt` recovers in {}, `consensus` in {}.",
            kinematic_name(kinematic),
            recovery_words(&outage_values(a, 0, node, metric(RECOVERY).3)),
            recovery_words(&outage_values(c, 0, node, metric(RECOVERY).3)),
        );
        let (mut worse, mut better) = (Vec::new(), Vec::new());
        let mut parts = Vec::new();
        for i in [RECOVERY, VC_RATE, TORQUE, VC, FORMATION] {
            let (_, header, unit, _) = metric(i);
            let (Some(x), Some(y)) = (mean(a, i), mean(c, i)) else { continue };
            if i != RECOVERY {
                parts.push(format!("{header} {}", against(x, y, unit)));
            }
            // Lower is better for every one of them; within 1 % is a tie.
            if x > y * 1.01 {
                worse.push(header);
            } else if x < y * 0.99 {
                better.push(header);
            }
        }
        if !parts.is_empty() {
            let _ = write!(text, " `adopt` against `consensus`: {}.", parts.join("; "));
        }
        if !worse.is_empty() {
            let _ = write!(text, " `adopt` is worse on {}", worse.join(", "));
            if !better.is_empty() {
                let _ = write!(text, " and better on {}", better.join(", "));
            }
            text.push('.');
        } else if !better.is_empty() {
            let _ = write!(text, " `adopt` is no worse on any of them and better on {}.", better.join(", "));
        }
        if let Some(change) = others_change(study, a, c) {
            text += &change;
        }
        out.push(text);
    }
    for rejoin in ["adopt", "consensus"] {
        let (Some(b), Some(c)) = (find(study, "bio", rejoin), find(study, "conventional", rejoin)) else { continue };
        let mut parts = Vec::new();
        for i in [VC, VC_RATE, TORQUE, FORMATION] {
            let (_, header, unit, f) = metric(i);
            let (Some(x), Some(y)) = (outage_values(c, 0, node, f).mean(), outage_values(b, 0, node, f).mean()) else {
                continue;
            };
            parts.push(format!("{} {}", header, against(x, y, unit)));
        }
        if !parts.is_empty() {
            out.push(format!(
                "With `{rejoin}`, follower {node} under conventional against bioinspired backstepping: {}.",
                parts.join("; ")
            ));
        }
    }
    if let Some(text) = sweep_findings(study) {
        out.push(text);
    }
    out
}

/// How much the rejoin policy changes the other followers: for their peak
/// estimator error, formation error and torque, the follower whose mean
/// changes most between `adopt` (case `a`) and `consensus` (case `c`).
fn others_change(study: &Study, a: &Case, c: &Case) -> Option<String> {
    let node = study.node;
    let ids: Vec<u32> = a.follower_ids().into_iter().filter(|&id| id != node).collect();
    let mut parts = Vec::new();
    for i in [ESTIMATOR, FORMATION, TORQUE] {
        let (_, header, unit, f) = OUTAGE_METRICS[i];
        let change = ids
            .iter()
            .filter_map(|&id| Some((id, outage_values(a, 0, id, f).mean()?, outage_values(c, 0, id, f).mean()?)))
            .map(|(id, x, y)| (id, x, y, if y != 0.0 { (x / y - 1.0).abs() } else { (x - y).abs() }))
            .max_by(|p, q| p.3.total_cmp(&q.3));
        match change {
            Some((_, _, _, d)) if d <= 0.01 => parts.push(format!("{header} within 1 %")),
            Some((id, x, y, _)) => parts.push(format!("{header} at most follower {id}'s, {}", against(x, y, unit))),
            None => {}
        }
    }
    (!parts.is_empty()).then(|| {
        format!(" The other followers, `adopt` against `consensus` (largest change among them): {}.", parts.join("; "))
    })
}

fn sweep_findings(study: &Study) -> Option<String> {
    let node = study.node;
    let means: Vec<(f64, [Option<f64>; 4])> = study
        .sweep
        .iter()
        .map(|c| (loss(c), SWEEP_SERIES.map(|(.., f)| over_seeds(c, |s| f(s, node)).mean())))
        .collect();
    let list = |k: usize| {
        means.iter().filter_map(|(p, m)| Some(format!("{} m at p = {p}", sig(m[k]?, 3)))).collect::<Vec<_>>().join(", ")
    };
    let first = means.first()?;
    let base = first.1[0]?;
    let doubled = means.iter().find(|(_, m)| m[0].is_some_and(|x| x > 2.0 * base)).map(|(p, _)| *p);
    let mut text = format!(
        "Loss on follower {node}'s links over the whole run: its formation-error RMS over the last 10 s is {}; its \
         peak estimator error {}.",
        list(0),
        list(2)
    );
    match doubled {
        Some(p) => {
            let _ = write!(text, " Its RMS first exceeds twice the value at p = {} at p = {p}.", first.0);
        }
        None => {
            let _ = write!(text, " Its RMS stays within twice the value at p = {} throughout.", first.0);
        }
    }
    let extreme = |k: usize, largest: bool| {
        let pick = means.iter().filter_map(|(p, m)| Some((*p, m[k]?)));
        let best =
            if largest { pick.max_by(|x, y| x.1.total_cmp(&y.1)) } else { pick.min_by(|x, y| x.1.total_cmp(&y.1)) };
        best.map(|(p, v)| format!("{} m at p = {p}", sig(v, 3)))
    };
    for (k, what) in [(1, "formation-error RMS"), (3, "peak estimator error")] {
        if let (Some(hi), Some(lo)) = (extreme(k, true), extreme(k, false)) {
            let _ = write!(text, " The worst of the others' {what}: largest {hi}, smallest {lo}.");
        }
    }
    Some(text)
}

/// A case's settings row for the study's list.
fn case_rows(cases: &[&Case]) -> String {
    let mut md = String::from("| case | settings | folder |\n| --- | --- | --- |\n");
    for c in cases {
        let _ = writeln!(md, "| {} | {} | `{}` |", c.label, md_cell(&c.settings()), c.dir.display());
    }
    md
}

/// Writes a figure and returns its markdown.
fn figure_markdown(out: &Path, spec: &FigureSpec) -> Result<String, Error> {
    plots::write_figure(out, spec)?;
    let f = &spec.figure;
    Ok(format!(
        "### {0}\n\n![{0}]({1}.png)\n\n{2}\n\nFiles: [{1}.svg]({1}.svg), [{1}.png]({1}.png), data [{1}.csv]({1}.csv).\n\n",
        f.title, f.file, f.caption
    ))
}

/// Writes a table's CSV and returns its markdown.
fn table_markdown(out: &Path, t: &Table) -> Result<String, Error> {
    let path = out.join(format!("{}.csv", t.file));
    std::fs::write(&path, &t.csv).map_err(at_path(&path, "cannot write"))?;
    Ok(format!("### {}\n\n{}\nData: [{f}.csv]({f}.csv).\n\n", t.title, t.markdown, f = t.file))
}

/// What [`write`] adds: report.md's section and the text for the terminal.
#[derive(Clone, Debug, Default)]
pub struct Written {
    pub markdown: String,
    pub terminal: String,
}

/// The link-fault section of a report: the cases with faults (and the
/// study, in `formation paper`), their figures and tables written into `out`.
pub fn write(out: &Path, faulted: &[&Case], study: Option<&Study>) -> Result<Written, Error> {
    let mut cases: Vec<&Case> = faulted.to_vec();
    if let Some(s) = study {
        cases.extend(s.outage.iter());
    }
    if cases.is_empty() && study.is_none() {
        return Ok(Written::default());
    }
    let mut md = String::from("## Link faults (docs/model.md §14)\n\n");
    let mut terminal = String::new();
    if let Some(s) = study {
        let _ = writeln!(md, "The outage study (`formation paper`; `--no-study` leaves it out):\n");
        for n in s.skipped.iter().chain(&s.notes) {
            let _ = writeln!(md, "- {n}");
        }
        for n in &s.skipped {
            let _ = writeln!(terminal, "{n}");
        }
        md.push('\n');
        let all: Vec<&Case> = s.outage.iter().chain(&s.sweep).collect();
        if !all.is_empty() {
            md += &case_rows(&all);
            md.push('\n');
        }
        let found = findings(s);
        if !found.is_empty() {
            let _ = writeln!(
                md,
                "### What the outage study shows\n\nMeans over seeds (the tables below have the spread and the 95 % \
                 intervals):\n"
            );
            for f in &found {
                let _ = writeln!(md, "- {f}");
                let _ = writeln!(terminal, "{f}");
            }
            md.push('\n');
        }
    } else {
        md += &case_rows(&cases);
        md.push('\n');
        for c in &cases {
            let first = if c.seeds.len() > 1 {
                format!(" (first seed; report.md has all {} seeds)", c.seeds.len())
            } else {
                String::new()
            };
            let _ = write!(
                terminal,
                "\n{}{first}:{}",
                c.label,
                formation_record::outage::table(&c.summary().faults, c.summary().recorded_until())
            );
        }
    }
    if !cases.is_empty() {
        if let Some(spec) = outage_figure(&cases)? {
            md += &figure_markdown(out, &spec)?;
        }
        md += &table_markdown(out, &fault_table(&cases))?;
    }
    if let Some(s) = study.filter(|s| !s.sweep.is_empty()) {
        if let Some(spec) = sweep_figure(s) {
            md += &figure_markdown(out, &spec)?;
        }
        md += &table_markdown(out, &sweep_table(s))?;
    }
    Ok(Written { markdown: md, terminal })
}
