//! The paper's tables (I: velocity RMSE, normal case; II: fault case), the
//! speed-jump and chattering table, a table of every metric, and the docs/model.md §12
//! claims checked on the cases. Each table comes as markdown and as a long
//! CSV (one row per case, follower and quantity, with its statistics).

use std::fmt::Write as _;

use crate::case::{Case, ClaimParams, Context, Role, SeedRecord, ESTIMATOR_CHECK_TIMES_S};
use crate::stats::Stat;
use formation_record::{last10_from_k, FollowerMetrics, Shortfall, Summary};

/// The paper's Table I (normal case) and Table II (fault case), ×10⁻²:
/// per follower (linear KF, linear ASIF, angular KF, angular ASIF), copied
/// from `formation-paper.tex`.
pub const PAPER_TABLE_I: [[f64; 4]; 4] =
    [[0.97, 0.97, 0.80, 0.80], [0.96, 0.96, 0.82, 0.82], [0.97, 0.97, 0.81, 0.81], [0.98, 0.98, 0.78, 0.78]];
pub const PAPER_TABLE_II: [[f64; 4]; 4] =
    [[6.43, 1.18, 2.10, 1.03], [6.50, 1.15, 1.83, 1.01], [5.37, 1.19, 2.14, 1.03], [5.75, 1.19, 2.03, 1.05]];

/// One table, ready to write.
#[derive(Clone, Debug)]
pub struct Table {
    /// File stem of its CSV.
    pub file: String,
    pub title: String,
    pub markdown: String,
    pub csv: String,
}

/// Every table and claim of a report.
#[derive(Clone, Debug)]
pub struct Tables {
    pub tables: Vec<Table>,
    pub claims: Vec<Check>,
}

/// Reads one metric of a follower (`None`: its window was not reached).
type MetricFn = fn(&FollowerMetrics) -> Option<f64>;

/// A column of a table: a case and its header.
struct Col<'a> {
    case: &'a Case,
    header: String,
}

/// Paper mode: the first case of each role, under the paper's header;
/// otherwise every case that `keep` accepts, under its label.
fn columns<'a>(cases: &'a [Case], ctx: &Context, roles: &[(Role, &str)], keep: impl Fn(&Case) -> bool) -> Vec<Col<'a>> {
    if ctx.paper {
        roles
            .iter()
            .filter_map(|&(role, header)| {
                cases.iter().find(|c| c.role == role).map(|case| Col { case, header: header.to_string() })
            })
            .collect()
    } else {
        cases.iter().filter(|c| keep(c)).map(|case| Col { case, header: case.label.clone() }).collect()
    }
}

/// One metric of one follower over a case's seeds: the statistics of the
/// seeds that measured it (a null metric, its window not reached, is
/// skipped, not read as 0) and how many seeds have the follower at all.
#[derive(Clone, Copy, Debug)]
struct Measured {
    stat: Option<Stat>,
    seeds: usize,
}

impl Measured {
    fn scaled(self, k: f64) -> Self {
        Self { stat: self.stat.map(|s| s.scaled(k)), ..self }
    }

    /// A table cell: `–` without the follower, `n/a` when no seed measured
    /// the metric, and how many seeds did when only some did.
    fn cell(&self, text: impl Fn(&Stat) -> String) -> String {
        match self.stat {
            _ if self.seeds == 0 => "–".into(),
            None => "n/a".into(),
            Some(s) if s.n < self.seeds => format!("{} ({} of {} seeds)", text(&s), s.n, self.seeds),
            Some(s) => text(&s),
        }
    }
}

fn metric_stat(case: &Case, id: u32, f: impl Fn(&FollowerMetrics) -> Option<f64>) -> Measured {
    let metrics: Vec<&FollowerMetrics> = case.seeds.iter().filter_map(|s| s.summary.followers.get(&id)).collect();
    let values: Vec<f64> = metrics.iter().filter_map(|m| f(m)).collect();
    Measured { stat: Stat::of(&values), seeds: metrics.len() }
}

/// Follower ids present in any of the columns, ascending.
fn follower_ids(cols: &[Col]) -> Vec<u32> {
    let mut ids: Vec<u32> = cols.iter().flat_map(|c| c.case.follower_ids()).collect();
    ids.sort_unstable();
    ids.dedup();
    ids
}

/// `n` significant digits, without exponent for ordinary magnitudes.
pub fn sig(x: f64, n: usize) -> String {
    if !x.is_finite() {
        return format!("{x}");
    }
    if x == 0.0 {
        return "0".into();
    }
    let mag = x.abs().log10().floor() as i32;
    if !(-4..6).contains(&mag) {
        return format!("{:.*e}", n.saturating_sub(1), x);
    }
    let decimals = (n as i32 - 1 - mag).max(0) as usize;
    format!("{x:.decimals$}")
}

/// A cell's statistics: the value for one seed, `mean ± sd [low, high]` for several.
pub(super) fn stat_text(s: &Stat, digits: usize) -> String {
    if s.n <= 1 {
        return sig(s.mean, digits);
    }
    format!("{} ± {} [{}, {}]", sig(s.mean, digits), sig(s.sd, 2), sig(s.ci_low, digits), sig(s.ci_high, digits))
}

pub(super) const STAT_HEADER: &str = "n,mean,sd,ci_low,ci_high,min,max";

pub(super) fn stat_fields(s: &Stat) -> String {
    format!("{},{:?},{:?},{:?},{:?},{:?},{:?}", s.n, s.mean, s.sd, s.ci_low, s.ci_high, s.min, s.max)
}

/// Quotes a CSV field if it needs it.
pub(super) fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// Builds every table and claim.
pub fn build(cases: &[Case], ctx: &Context) -> Tables {
    let mut tables = vec![
        rmse_table(cases, ctx, false),
        rmse_table(cases, ctx, true),
        controller_table(cases, ctx),
        all_metrics_table(cases),
        agreement_table(cases),
    ];
    tables.retain(|t| !t.csv.is_empty());
    Tables { tables, claims: claims(cases, &ctx.params) }
}

/// Table I (`fault = false`) or II: velocity RMSE ×10⁻² per follower, KF and ASIF, beside the paper's.
fn rmse_table(cases: &[Case], ctx: &Context, fault: bool) -> Table {
    let (file, title, paper, roles) = if fault {
        (
            "table2_fault",
            "Table II: velocity RMSE under the fault case (×10⁻²)",
            &PAPER_TABLE_II,
            [(Role::KfFault, "KF"), (Role::AsifFault, "ASIF")],
        )
    } else {
        (
            "table1_normal",
            "Table I: velocity RMSE under the normal case (×10⁻²)",
            &PAPER_TABLE_I,
            [(Role::KfNormal, "KF"), (Role::Proposed, "ASIF")],
        )
    };
    // A run with no velocity filter (a velocity-commanded robot) has no
    // velocity RMSE to set beside the paper's.
    let cols =
        columns(cases, ctx, &roles, |c| c.summary().fault_time.is_some() == fault && c.summary().filter != "none");
    if cols.is_empty() {
        return Table { file: file.into(), title: title.into(), markdown: String::new(), csv: String::new() };
    }
    let ids = follower_ids(&cols);
    let paper_of = |id: u32, channel: usize, filter: &str| -> Option<f64> {
        let row = paper.get((id as usize).checked_sub(1)?)?;
        match filter {
            "kf" => Some(row[2 * channel]),
            "asif" => Some(row[2 * channel + 1]),
            _ => None,
        }
    };
    let channels: [(&str, MetricFn); 2] = [("linear", |m| m.rmse_v), ("angular", |m| m.rmse_w)];

    let mut md = String::from("| Follower |");
    let mut rule = String::from("| --- |");
    for (name, _) in &channels {
        for c in &cols {
            let _ = write!(md, " {} {} |", capitalise(name), c.header);
            rule += " --- |";
        }
        let _ = write!(md, " {} KF (paper) | {} ASIF (paper) |", capitalise(name), capitalise(name));
        rule += " --- | --- |";
    }
    let _ = writeln!(md, "\n{rule}");
    let mut csv = format!("case,filter,follower,channel,{STAT_HEADER},paper\n");
    for &id in &ids {
        let _ = write!(md, "| {id} |");
        for (ch, (name, f)) in channels.iter().enumerate() {
            for c in &cols {
                let m = metric_stat(c.case, id, f).scaled(100.0);
                let _ = write!(md, " {} |", m.cell(|s| stat_text(s, 3)));
                if let Some(s) = m.stat {
                    let filter = &c.case.summary().filter;
                    let p = paper_of(id, ch, filter).map(|p| format!("{p}")).unwrap_or_default();
                    let _ =
                        writeln!(csv, "{},{},{id},{name},{},{p}", csv_field(&c.case.label), filter, stat_fields(&s));
                }
            }
            let p = |filter| paper_of(id, ch, filter).map(|p| format!("{p:.2}")).unwrap_or_else(|| "–".into());
            let _ = write!(md, " {} | {} |", p("kf"), p("asif"));
        }
        md.push('\n');
    }
    let mut note = String::new();
    if !ctx.paper {
        note =
            "\nColumns are the run folders of this condition; the paper's KF and ASIF values are beside them.\n".into();
    }
    Table { file: file.into(), title: title.into(), markdown: md + &note, csv }
}

/// Speed jump (peak |v_c|) and chattering (torque variation per second, peak |τ|).
fn controller_table(cases: &[Case], ctx: &Context) -> Table {
    let roles = [
        (Role::ConventionalBackstepping, "Conventional backstepping"),
        (Role::ConventionalSmc, "Conventional SMC"),
        (Role::SuperTwisting, "Second-order SMC (super-twisting)"),
        (Role::Proposed, "Bioinspired backstepping + bioinspired SMC"),
    ];
    let cols = columns(cases, ctx, &roles, |_| true);
    let file = "table3_speed_jump_chattering";
    let title = "Speed jump and chattering";
    if cols.is_empty() {
        return Table { file: file.into(), title: title.into(), markdown: String::new(), csv: String::new() };
    }
    let ids = follower_ids(&cols);
    let metrics: [(&str, &str, &str, MetricFn); 3] = [
        ("vc_peak", "m/s", "Speed jump: peak |v_c| (m/s)", |m| m.vc_peak),
        ("torque_tv", "N m/s", "Chattering: torque variation Σ|Δτ_L| + |Δτ_R| per second (N m/s)", |m| {
            m.torque_tv
        }),
        ("torque_peak", "N m", "Peak torque |τ| over both wheels (N m)", |m| m.torque_peak),
    ];
    let mut md = String::new();
    let mut csv = format!("case,kinematic,dynamic,follower,metric,unit,{STAT_HEADER}\n");
    for (key, unit, heading, f) in &metrics {
        let _ = writeln!(md, "**{heading}**\n");
        md += "| Follower |";
        for c in &cols {
            let _ = write!(md, " {} |", c.header);
        }
        md += "\n| --- |";
        md += &" --- |".repeat(cols.len());
        md.push('\n');
        for &id in &ids {
            let _ = write!(md, "| {id} |");
            for c in &cols {
                let m = metric_stat(c.case, id, f);
                let _ = write!(md, " {} |", m.cell(|s| stat_text(s, 4)));
                if let Some(s) = m.stat {
                    let sum = c.case.summary();
                    let _ = writeln!(
                        csv,
                        "{},{},{},{id},{key},{unit},{}",
                        csv_field(&c.case.label),
                        sum.kinematic,
                        sum.dynamic,
                        stat_fields(&s)
                    );
                }
            }
            md.push('\n');
        }
        md.push('\n');
    }
    Table { file: file.into(), title: title.into(), markdown: md, csv }
}

/// Every metric of [`FollowerMetrics`] but the sample count: name, unit, value.
const ALL_METRICS: [(&str, &str, MetricFn); 9] = [
    ("formation_rms_last10", "m", |m| m.formation_rms_last10),
    ("formation_final", "m", |m| m.formation_final),
    ("heading_final", "rad", |m| m.heading_final),
    ("estimator_error_final", "m", |m| m.estimator_error_final),
    ("vc_peak", "m/s", |m| m.vc_peak),
    ("torque_tv", "N m/s", |m| m.torque_tv),
    ("torque_peak", "N m", |m| m.torque_peak),
    ("rmse_v", "m/s", |m| m.rmse_v),
    ("rmse_w", "rad/s", |m| m.rmse_w),
];

/// Every docs/model.md §11 metric of every case and follower.
fn all_metrics_table(cases: &[Case]) -> Table {
    let metrics = ALL_METRICS;
    let mut md = String::from("| case | follower |");
    for (k, u, _) in &metrics {
        let _ = write!(md, " {k} ({u}) |");
    }
    md += "\n| --- | --- |";
    md += &" --- |".repeat(metrics.len());
    md.push('\n');
    let mut csv = format!("case,follower,metric,unit,{STAT_HEADER}\n");
    for c in cases {
        for id in c.follower_ids() {
            let _ = write!(md, "| {} | {id} |", c.label);
            for (key, unit, f) in &metrics {
                let m = metric_stat(c, id, f);
                // Means only here (with sd for several seeds); the CSV has the intervals.
                let text =
                    m.cell(|s| if s.n > 1 { format!("{} ± {}", sig(s.mean, 4), sig(s.sd, 2)) } else { sig(s.mean, 4) });
                let _ = write!(md, " {text} |");
                if let Some(s) = m.stat {
                    let _ = writeln!(csv, "{},{id},{key},{unit},{}", csv_field(&c.label), stat_fields(&s));
                }
            }
            md.push('\n');
        }
    }
    Table {
        file: "table4_all_metrics".into(),
        title: "Every metric of every case (docs/model.md §11)".into(),
        markdown: md,
        csv,
    }
}

/// Text for a markdown table cell (`|` escaped).
pub fn md_cell(s: &str) -> String {
    s.replace('|', "\\|")
}

/// A number in Unicode subscript digits (x̂₄).
fn subscript(n: u32) -> String {
    n.to_string().chars().map(|c| char::from_u32(0x2080 + c.to_digit(10).unwrap_or(0)).unwrap_or(c)).collect()
}

/// Cases with the same settings as an earlier one (a networked run beside
/// the simulator's, say): the largest difference of each metric over the
/// followers, first seeds compared.
fn agreement_table(cases: &[Case]) -> Table {
    let same = |a: &Summary, b: &Summary| {
        (&a.kinematic, &a.dynamic, &a.filter, &a.estimate_init)
            == (&b.kinematic, &b.dynamic, &b.filter, &b.estimate_init)
            && (a.seed, a.noise, a.steps, a.fault_time) == (b.seed, b.noise, b.steps, b.fault_time)
            && a.dt == b.dt
            && a.followers.keys().eq(b.followers.keys())
            // The same link faults (window and loss, in the label) and rejoin policy.
            && a.rejoin == b.rejoin
            && a.faults.iter().map(|f| &f.fault).eq(b.faults.iter().map(|f| &f.fault))
    };
    let mut md = String::from("| case | compared with |");
    for (k, u, _) in &ALL_METRICS {
        let _ = write!(md, " {k} ({u}) |");
    }
    md += "\n| --- | --- |";
    md += &" --- |".repeat(ALL_METRICS.len());
    md.push('\n');
    let mut csv = String::new();
    for (i, c) in cases.iter().enumerate() {
        let Some(r) = cases[..i].iter().find(|r| same(c.summary(), r.summary())) else { continue };
        if csv.is_empty() {
            csv = "case,reference,metric,unit,max_abs_diff,max_rel_diff\n".into();
        }
        let _ = write!(md, "| {} | {} |", c.label, r.label);
        for (key, unit, f) in &ALL_METRICS {
            let (mut abs, mut rel) = (0.0_f64, 0.0_f64);
            // A null on either side (window not reached) leaves nothing to compare.
            let mut compared = true;
            for (id, m) in &c.summary().followers {
                let (Some(x), Some(y)) = (f(m), f(&r.summary().followers[id])) else {
                    compared = false;
                    break;
                };
                abs = abs.max((x - y).abs());
                if y != 0.0 {
                    rel = rel.max((x - y).abs() / y.abs());
                }
            }
            let (cell, abs, rel) = if compared {
                (sig(abs, 3), format!("{abs:?}"), format!("{rel:?}"))
            } else {
                ("n/a".into(), "".into(), "".into())
            };
            let _ = write!(md, " {cell} |");
            let _ = writeln!(csv, "{},{},{key},{unit},{abs},{rel}", csv_field(&c.label), csv_field(&r.label));
        }
        md.push('\n');
    }
    md += "\nEach cell is the largest absolute difference over the followers (0: identical; n/a: a metric \
           whose window a run did not reach).\n";
    Table {
        file: "table5_agreement".into(),
        title: "Agreement of runs with the same settings".into(),
        markdown: md,
        csv,
    }
}

fn capitalise(s: &str) -> String {
    let mut c = s.chars();
    c.next().map(|f| f.to_uppercase().collect::<String>() + c.as_str()).unwrap_or_default()
}

/// What a claim requires of its measured quantity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Cond {
    Lt(f64),
    Le(f64),
    Gt(f64),
    Ge(f64),
    /// |x − target| ≤ tol.
    Near {
        target: f64,
        tol: f64,
    },
}

impl Cond {
    pub fn holds(&self, x: f64) -> bool {
        match *self {
            Cond::Lt(b) => x < b,
            Cond::Le(b) => x <= b,
            Cond::Gt(b) => x > b,
            Cond::Ge(b) => x >= b,
            Cond::Near { target, tol } => (x - target).abs() <= tol,
        }
    }

    pub fn text(&self) -> String {
        match *self {
            Cond::Lt(b) => format!("< {}", sig(b, 4)),
            Cond::Le(b) => format!("≤ {}", sig(b, 4)),
            Cond::Gt(b) => format!("> {}", sig(b, 4)),
            Cond::Ge(b) => format!("≥ {}", sig(b, 4)),
            Cond::Near { target, tol } => format!("{} ± {tol:e}", sig(target, 6)),
        }
    }
}

/// One checked statement of docs/model.md §12.
#[derive(Clone, Debug)]
pub struct Check {
    /// The statement, in docs/model.md §12's words.
    pub claim: String,
    /// What is measured, per seed.
    pub quantity: String,
    pub unit: &'static str,
    pub condition: Cond,
    /// The cases it was measured on.
    pub cases: Vec<String>,
    /// The quantity per seed (seeds of several cases paired by position).
    pub values: Vec<f64>,
    pub stat: Option<Stat>,
    /// Seeds for which the condition holds.
    pub holds: usize,
    /// Why the claim could not be checked.
    pub missing: Option<String>,
}

impl Check {
    /// `PASS` if the condition holds for every seed, `FAIL` if not, `N/A` if unchecked.
    pub fn result(&self) -> &'static str {
        match (&self.missing, self.values.is_empty()) {
            (Some(_), _) | (None, true) => "N/A",
            _ if self.holds == self.values.len() => "PASS",
            _ => "FAIL",
        }
    }

    /// The measured value as text: the value, or mean ± sd [CI] and the range.
    pub fn measured(&self) -> String {
        match (&self.missing, self.stat) {
            (Some(why), _) => format!("n/a: {why}"),
            (None, None) => "n/a".into(),
            (None, Some(s)) if s.n <= 1 => sig(s.mean, 5),
            (None, Some(s)) => format!(
                "{} ± {} [{}, {}], range {} to {}",
                sig(s.mean, 5),
                sig(s.sd, 2),
                sig(s.ci_low, 5),
                sig(s.ci_high, 5),
                sig(s.min, 5),
                sig(s.max, 5)
            ),
        }
    }
}

/// The largest (or, with `min`, smallest) of `f` over the followers of a seed;
/// `None` when there are none.
fn over_followers(r: &SeedRecord, min: bool, f: impl Fn(u32, &FollowerMetrics) -> Option<f64>) -> Option<f64> {
    let vals = r.summary.followers.iter().filter_map(|(&id, m)| f(id, m));
    if min {
        vals.reduce(f64::min)
    } else {
        vals.reduce(f64::max)
    }
}

/// The samples a claim's quantity needs: what an incomplete run did not reach.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Window {
    /// Every sample (peaks, RMSE, torque variation).
    Whole,
    /// The sample at t = T.
    Final,
    /// The samples with t ≥ T − 10.
    Last10,
    /// The sample at t (s).
    At(f64),
}

impl Window {
    /// What a follower that recorded `short.recorded` samples misses.
    fn unreached(self, short: &Shortfall, s: &Summary) -> String {
        let reached = |k: u64| short.recorded > k;
        match self {
            Window::Whole => "the run not complete".into(),
            Window::Final => "the sample at t = T not reached".into(),
            Window::Last10 if !reached(last10_from_k(s.steps, s.dt)) => "the last 10 s not reached".into(),
            Window::Last10 => "the last 10 s only partly recorded".into(),
            Window::At(t) if !reached((t / s.dt).round() as u64) => format!("t = {t} s not reached"),
            Window::At(_) => "the run not complete".into(),
        }
    }
}

/// Why the incomplete ones among `seeds` (of `cases`, paired) leave a claim
/// unchecked: "proposed: follower 3 recorded 8150 of 20001 samples (…), the
/// last 10 s not reached"; `None` when every run is complete.
fn incomplete_reason(cases: &[&Case], seeds: &[&SeedRecord], window: Window) -> Option<String> {
    let mut reasons: Vec<String> = cases
        .iter()
        .zip(seeds)
        .flat_map(|(c, r)| {
            let s = &r.summary;
            let run = if c.seeds.len() > 1 { format!("{} seed {}", c.label, r.seed) } else { c.label.clone() };
            s.incomplete.iter().map(move |(&id, short)| {
                format!("{run}: {}, {}", short.describe(id, s.dt, s.duration), window.unreached(short, s))
            })
        })
        .collect();
    // The first three say why; summary.json lists every short follower.
    if reasons.len() > 3 {
        let more = reasons.len() - 3;
        reasons.truncate(3);
        reasons.push(format!("and {more} more short followers"));
    }
    (!reasons.is_empty()).then(|| reasons.join("; "))
}

struct ClaimBuilder<'a> {
    cases: &'a [Case],
    out: Vec<Check>,
}

impl ClaimBuilder<'_> {
    /// Checks `per_seed` on the first case of each role, seeds paired by
    /// position. A claim on an incomplete run is N/A with the reason (it
    /// needs the samples of `window`), never PASS or FAIL.
    #[allow(clippy::too_many_arguments)]
    fn check(
        &mut self,
        claim: &str,
        quantity: &str,
        unit: &'static str,
        condition: Cond,
        roles: &[Role],
        window: Window,
        per_seed: impl Fn(&[&SeedRecord]) -> Option<f64>,
    ) {
        let found: Vec<Option<&Case>> = roles.iter().map(|r| self.cases.iter().find(|c| c.role == *r)).collect();
        let mut check = Check {
            claim: claim.into(),
            quantity: quantity.into(),
            unit,
            condition,
            cases: found.iter().flatten().map(|c| c.label.clone()).collect(),
            values: vec![],
            stat: None,
            holds: 0,
            missing: None,
        };
        if found.iter().any(Option::is_none) {
            let names: Vec<String> =
                roles.iter().zip(&found).filter(|(_, c)| c.is_none()).map(|(r, _)| role_name(*r).to_string()).collect();
            check.missing = Some(format!("no {} case", names.join(", ")));
        } else {
            let cases: Vec<&Case> = found.into_iter().flatten().collect();
            let n = cases.iter().map(|c| c.seeds.len()).min().unwrap_or(0);
            let mut incomplete = Vec::new();
            for i in 0..n {
                let seeds: Vec<&SeedRecord> = cases.iter().map(|c| &c.seeds[i]).collect();
                if let Some(why) = incomplete_reason(&cases, &seeds, window) {
                    incomplete.push(why);
                } else if let Some(v) = per_seed(&seeds) {
                    check.values.push(v);
                }
            }
            if let Some(first) = incomplete.first() {
                let more = match incomplete.len() {
                    1 => String::new(),
                    k => format!(" (and {} more incomplete seeds of {n})", k - 1),
                };
                check.values.clear();
                check.missing = Some(format!("{first}{more}"));
            } else if check.values.is_empty() {
                check.missing = Some("not measurable in these runs (too short for this claim)".into());
            }
            check.stat = Stat::of(&check.values);
            check.holds = check.values.iter().filter(|&&v| condition.holds(v)).count();
        }
        self.out.push(check);
    }
}

/// The case a role names, in words.
pub fn role_name(r: Role) -> &'static str {
    match r {
        Role::Proposed => "proposed (bio/bio/ASIF)",
        Role::ConventionalBackstepping => "conventional backstepping",
        Role::ConventionalSmc => "conventional SMC",
        Role::SuperTwisting => "super-twisting SMC",
        Role::KfNormal => "KF normal",
        Role::KfFault => "KF fault",
        Role::AsifFault => "ASIF fault",
        Role::ZeroInit => "zero-initialised estimator",
        Role::Other => "other",
    }
}

/// Every docs/model.md §12 claim, checked on the first case of the roles it needs.
pub fn claims(cases: &[Case], p: &ClaimParams) -> Vec<Check> {
    let mut b = ClaimBuilder { cases, out: vec![] };
    backstepping_claims(&mut b, p);
    normal_case_claims(&mut b);
    fault_case_claims(&mut b);
    chattering_claims(&mut b);
    estimator_claims(&mut b);
    formation_claims(&mut b);
    b.out
}

/// The kinematic controllers: conventional backstepping's jump, the
/// bioinspired one's bounded peaks.
fn backstepping_claims(b: &mut ClaimBuilder<'_>, p: &ClaimParams) {
    use Role::*;
    let jump = p.jump_follower;
    // As the model states it (§12): the jump at t = 0 is exact; the peak
    // comes within 0.05 m/s of it (noise moves the robot before the peak).
    b.check(
        &format!(
            "Conventional backstepping: v_c(0) of F{jump} = C₁·x̂{}(0) = {} m/s (to 1e-9)",
            subscript(jump),
            sig(p.jump_expected, 4)
        ),
        &format!("v_c of F{jump} at t = 0"),
        "m/s",
        Cond::Near { target: p.jump_expected, tol: 1e-9 },
        &[ConventionalBackstepping],
        Window::Whole,
        |s| s[0].vc_initial.get(&jump).copied(),
    );
    b.check(
        &format!("Conventional backstepping: peak |v_c| of F{jump} within 0.05 m/s of C₁·x̂{}(0)", subscript(jump)),
        &format!("peak |v_c| of F{jump}"),
        "m/s",
        Cond::Near { target: p.jump_expected, tol: 0.05 },
        &[ConventionalBackstepping],
        Window::Whole,
        |s| s[0].summary.followers.get(&jump).and_then(|m| m.vc_peak),
    );
    let bound = p.c1 * p.shunting_b + p.vr_max;
    b.check(
        "Bioinspired backstepping: every peak v_c ≤ C₁B + max v_r",
        "largest peak |v_c| over followers",
        "m/s",
        Cond::Le(bound),
        &[Proposed],
        Window::Whole,
        |s| over_followers(s[0], false, |_, m| m.vc_peak),
    );
    b.check(
        "Bioinspired backstepping: every peak v_c below 4 m/s",
        "largest peak |v_c| over followers",
        "m/s",
        Cond::Lt(4.0),
        &[Proposed],
        Window::Whole,
        |s| over_followers(s[0], false, |_, m| m.vc_peak),
    );
}

/// The normal case: ASIF against KF, and both filters' RMSE band.
fn normal_case_claims(b: &mut ClaimBuilder<'_>) {
    use Role::*;
    b.check(
        "Normal case: ASIF and KF velocity RMSE within 2 % of each other",
        "largest |ASIF − KF| / KF over followers and channels",
        "%",
        Cond::Le(2.0),
        &[Proposed, KfNormal],
        Window::Whole,
        |s| {
            over_followers(s[0], false, |id, a| {
                let k = s[1].summary.followers.get(&id)?;
                let rel = |a: Option<f64>, k: Option<f64>| Some((a? - k?).abs() / k?);
                Some(rel(a.rmse_v, k.rmse_v)?.max(rel(a.rmse_w, k.rmse_w)?) * 100.0)
            })
        },
    );
    let rmse_extreme = |s: &[&SeedRecord], min: bool| {
        let all = s.iter().flat_map(|r| r.summary.followers.values().flat_map(|m| [m.rmse_v, m.rmse_w]).flatten());
        let x = if min { all.reduce(f64::min) } else { all.reduce(f64::max) };
        x.map(|x| x * 100.0)
    };
    b.check(
        "Normal case: KF and ASIF RMSE within 0.6–1.5 ×10⁻² on each channel (lower end)",
        "smallest RMSE over filters, followers, channels",
        "×10⁻²",
        Cond::Ge(0.6),
        &[Proposed, KfNormal],
        Window::Whole,
        |s| rmse_extreme(s, true),
    );
    b.check(
        "Normal case: KF and ASIF RMSE within 0.6–1.5 ×10⁻² on each channel (upper end)",
        "largest RMSE over filters, followers, channels",
        "×10⁻²",
        Cond::Le(1.5),
        &[Proposed, KfNormal],
        Window::Whole,
        |s| rmse_extreme(s, false),
    );
}

/// The fault case: ASIF against KF after the change of mass and inertia.
fn fault_case_claims(b: &mut ClaimBuilder<'_>) {
    use Role::*;
    b.check(
        "Fault case: ASIF linear RMSE at most half the KF's, for every follower",
        "largest ASIF / KF linear RMSE over followers",
        "ratio",
        Cond::Le(0.5),
        &[AsifFault, KfFault],
        Window::Whole,
        |s| {
            faulted(s)?;
            over_followers(s[0], false, |id, a| Some(a.rmse_v? / s[1].summary.followers.get(&id)?.rmse_v?))
        },
    );
    b.check(
        "Fault case: ASIF angular RMSE no larger than the KF's",
        "largest ASIF / KF angular RMSE over followers",
        "ratio",
        Cond::Le(1.0),
        &[AsifFault, KfFault],
        Window::Whole,
        |s| {
            faulted(s)?;
            over_followers(s[0], false, |id, a| Some(a.rmse_w? / s[1].summary.followers.get(&id)?.rmse_w?))
        },
    );
}

/// Chattering: the torque variation of the three sliding-mode controllers.
fn chattering_claims(b: &mut ClaimBuilder<'_>) {
    use Role::*;
    b.check(
        "Chattering: conventional SMC torque variation ≥ 50× the bioinspired SMC's",
        "smallest SMC / bioinspired torque variation over followers",
        "ratio",
        Cond::Ge(50.0),
        &[ConventionalSmc, Proposed],
        Window::Whole,
        |s| over_followers(s[0], true, |id, c| Some(c.torque_tv? / s[1].summary.followers.get(&id)?.torque_tv?)),
    );
    b.check(
        "Chattering: super-twisting above the bioinspired SMC",
        "smallest super-twisting / bioinspired torque variation over followers",
        "ratio",
        Cond::Gt(1.0),
        &[SuperTwisting, Proposed],
        Window::Whole,
        |s| over_followers(s[0], true, |id, t| Some(t.torque_tv? / s[1].summary.followers.get(&id)?.torque_tv?)),
    );
    b.check(
        "Chattering: super-twisting below the conventional SMC",
        "largest super-twisting / conventional SMC torque variation over followers",
        "ratio",
        Cond::Lt(1.0),
        &[SuperTwisting, ConventionalSmc],
        Window::Whole,
        |s| over_followers(s[0], false, |id, t| Some(t.torque_tv? / s[1].summary.followers.get(&id)?.torque_tv?)),
    );
}

/// The estimator: from the leader's state, and from zero estimates.
fn estimator_claims(b: &mut ClaimBuilder<'_>) {
    use Role::*;
    b.check(
        "Estimator: position error of every follower below 0.01 m at t = T",
        "largest estimator position error at t = T",
        "m",
        Cond::Lt(0.01),
        &[Proposed],
        Window::Final,
        |s| over_followers(s[0], false, |_, m| m.estimator_error_final),
    );
    b.check(
        "Estimator from zero estimates (3 m off): below 0.1 m by t = 4 s",
        "largest estimator position error at t = 4 s",
        "m",
        Cond::Lt(0.1),
        &[ZeroInit],
        Window::At(ESTIMATOR_CHECK_TIMES_S[0]),
        |s| s[0].estimator_error_4s.values().copied().reduce(f64::max),
    );
    b.check(
        "Estimator from zero estimates (3 m off): below 0.02 m by t = 6 s",
        "largest estimator position error at t = 6 s",
        "m",
        Cond::Lt(0.02),
        &[ZeroInit],
        Window::At(ESTIMATOR_CHECK_TIMES_S[1]),
        |s| s[0].estimator_error_6s.values().copied().reduce(f64::max),
    );
}

/// The formation: bounded over the last 10 s.
fn formation_claims(b: &mut ClaimBuilder<'_>) {
    use Role::*;
    b.check(
        "Formation: bounded, every follower's formation-error RMS over the last 10 s below 0.2 m",
        "largest formation-error RMS over the last 10 s",
        "m",
        Cond::Lt(0.2),
        &[Proposed],
        Window::Last10,
        // With T ≤ 10 s "the last 10 s" is the whole run, start-up included:
        // not the claim's quantity, so not measured.
        |s| (s[0].summary.duration > 10.0).then(|| over_followers(s[0], false, |_, m| m.formation_rms_last10))?,
    );
}

/// `Some` when every run's fault happens before its end: the fault claims
/// are not measurable in runs shorter than the fault time.
fn faulted(s: &[&SeedRecord]) -> Option<()> {
    s.iter().all(|r| r.summary.fault_time.is_some_and(|f| f < r.summary.duration)).then_some(())
}

/// The claims as a markdown table, with a count line.
pub fn claims_markdown(checks: &[Check]) -> String {
    let count = |r| checks.iter().filter(|c| c.result() == r).count();
    let mut md = format!(
        "{} PASS, {} FAIL, {} N/A. A claim passes when it holds for every seed.\n\n",
        count("PASS"),
        count("FAIL"),
        count("N/A")
    );
    md += "| # | Claim | Measured quantity | Cases | Measured | Required | Result |\n";
    md += "| --- | --- | --- | --- | --- | --- | --- |\n";
    for (i, c) in checks.iter().enumerate() {
        let seeds = if c.values.len() > 1 { format!(" ({}/{} seeds)", c.holds, c.values.len()) } else { String::new() };
        let _ = writeln!(
            md,
            "| {} | {} | {} ({}) | {} | {} | {} | **{}**{} |",
            i + 1,
            md_cell(&c.claim),
            md_cell(&c.quantity),
            c.unit,
            c.cases.join(", "),
            c.measured(),
            c.condition.text(),
            c.result(),
            seeds
        );
    }
    md
}

/// The claims as aligned text lines, for the terminal.
pub fn claims_text(checks: &[Check]) -> String {
    let mut s = String::new();
    for c in checks {
        let seeds = if c.values.len() > 1 { format!(" [{}/{} seeds]", c.holds, c.values.len()) } else { String::new() };
        let unit = if c.stat.is_some() { format!(" {}", c.unit) } else { String::new() };
        let _ = writeln!(
            s,
            "{:<4} {}: {} = {}{unit} (required {}){}",
            c.result(),
            c.claim,
            c.quantity,
            c.measured(),
            c.condition.text(),
            seeds
        );
    }
    s
}

/// The claims as CSV.
pub fn claims_csv(checks: &[Check]) -> String {
    let mut s = format!("claim,quantity,unit,cases,{STAT_HEADER},required,holds,result\n");
    for c in checks {
        let stat = c.stat.map(|s| stat_fields(&s)).unwrap_or_else(|| "0,,,,,,".into());
        let _ = writeln!(
            s,
            "{},{},{},{},{stat},{},{},{}",
            csv_field(&c.claim),
            csv_field(&c.quantity),
            c.unit,
            csv_field(&c.cases.join(" ")),
            csv_field(&c.condition.text()),
            c.holds,
            c.result()
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use std::path::{Path, PathBuf};

    use formation_scenario::Scenario;

    use super::*;
    use formation_record::{MetricsAccumulator, Row};

    /// The paper's settings (the proposed method) at T = 20 s, Δt = 0.01 s: 2001 samples.
    fn scenario() -> Scenario {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        Scenario::load(&path, &["dt=0.01".to_string(), "duration=20".to_string()]).expect("scenario")
    }

    /// A follower that recorded steps 0..n with a formation error of 0.05 m,
    /// estimator error 1 mm and peak |v_c| 1 m/s: well inside every claim.
    fn metrics(s: &Scenario, n: u64) -> FollowerMetrics {
        let mut acc = MetricsAccumulator::new(s.steps(), s.dt_s);
        let r = Row { formation_error: 0.05, estimator_error: 1e-3, v_c: 1.0, v_hat: 0.01, ..Default::default() };
        for k in 0..n {
            acc.push(k, &r, None);
        }
        acc.finish()
    }

    /// A proposed case, one seed per (seed, samples follower 3 recorded).
    fn case(s: &Scenario, seeds: &[(u64, u64)]) -> Case {
        let seeds = seeds
            .iter()
            .map(|&(seed, n3)| {
                let n = |id: u32| if id == 3 { n3 } else { s.steps() + 1 };
                let mut summary = Summary::new(s, s.followers.iter().map(|f| (f.id, metrics(s, n(f.id)))).collect());
                summary.seed = seed;
                SeedRecord {
                    seed,
                    summary,
                    estimator_error_4s: Default::default(),
                    estimator_error_6s: Default::default(),
                    vc_initial: Default::default(),
                }
            })
            .collect();
        Case {
            label: "proposed".into(),
            dir: PathBuf::from("proposed"),
            seeds,
            role: Role::Proposed,
            has_csv: false,
            networked: false,
        }
    }

    fn claim<'a>(checks: &'a [Check], part: &str) -> &'a Check {
        checks.iter().find(|c| c.claim.contains(part)).unwrap_or_else(|| panic!("no claim with {part}"))
    }

    #[test]
    fn a_claim_on_an_incomplete_run_is_na_with_the_reason_never_pass() {
        let s = scenario();
        let p = ClaimParams::paper_defaults();
        let complete = claims(&[case(&s, &[(1, s.steps() + 1)])], &p);
        for part in ["Formation", "at t = T", "every peak v_c below 4 m/s", "C₁B + max v_r"] {
            let c = claim(&complete, part);
            assert_eq!(c.result(), "PASS", "complete run, {}: {}", c.claim, c.measured());
        }

        // Follower 3 stopped at t = 7.99 s, before T − 10 = 10 s.
        let cut = claims(&[case(&s, &[(1, 800)])], &p);
        for c in &cut {
            assert_ne!(c.result(), "PASS", "{}: {} on an incomplete run", c.claim, c.measured());
        }
        let why = "proposed: follower 3 recorded 800 of 2001 samples (to t = 7.99 s of T = 20 s)";
        for (part, unreached) in [
            ("Formation", "the last 10 s not reached"),
            ("at t = T", "the sample at t = T not reached"),
            ("every peak v_c below 4 m/s", "the run not complete"),
        ] {
            let c = claim(&cut, part);
            assert_eq!(c.result(), "N/A", "{}: {}", c.claim, c.measured());
            assert_eq!(c.measured(), format!("n/a: {why}, {unreached}"), "{}", c.claim);
            assert!(c.values.is_empty() && c.stat.is_none(), "{}: values {:?}", c.claim, c.values);
        }
        let text = claims_text(&cut);
        assert!(text.lines().any(|l| l.starts_with("N/A") && l.contains("the last 10 s not reached")), "{text}");
    }

    #[test]
    fn statistics_over_seeds_skip_nulls_and_say_how_many_seeds_measured() {
        let s = scenario();
        let full = s.steps() + 1;
        let c = case(&s, &[(1, full), (2, 800), (3, full)]);
        let m = metric_stat(&c, 3, |m| m.formation_rms_last10);
        let stat = m.stat.expect("two seeds measured it");
        assert_eq!((stat.n, m.seeds), (2, 3), "seeds that measured F3's formation RMS, of all");
        assert!(
            (stat.mean - 0.05).abs() < 1e-12,
            "mean {} of the measured seeds (a 0 would pull it to 0.033)",
            stat.mean
        );
        assert_eq!(m.cell(|s| sig(s.mean, 3)), "0.0500 (2 of 3 seeds)");
        let none = metric_stat(&case(&s, &[(2, 800)]), 3, |m| m.formation_rms_last10);
        assert_eq!(none.cell(|s| sig(s.mean, 3)), "n/a");
        let t = all_metrics_table(std::slice::from_ref(&c));
        assert!(t.markdown.contains("0.05000 ± 0 (2 of 3 seeds)"), "{}", t.markdown);

        let checks = claims(&[c], &ClaimParams::paper_defaults());
        let f = claim(&checks, "Formation");
        assert_eq!(f.result(), "N/A", "{}", f.measured());
        assert!(
            f.measured().contains("proposed seed 2: follower 3 recorded 800 of 2001 samples"),
            "the incomplete seed named: {}",
            f.measured()
        );
    }
}
