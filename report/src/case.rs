//! What a report compares: a *case* (a run folder, with its seeds), its
//! role in the paper, and the context a report is made in. Every part of a
//! report (tables, figures, faults, network) reads these; none reads
//! another part's types through them.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use formation_control::{kinematic, KinematicKind};
use formation_record::{at_path, read_columns_checked, Summary};
use formation_scenario::Scenario;
use serde::{Deserialize, Serialize};

use formation_exit::Error;

pub use crate::outdir::SEEDS_FILE;

/// Times (s) at which docs/model.md §12 checks the estimator started from zero.
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
    /// The kinematic controller's v_c at t = 0 (m/s), by follower id: the
    /// speed jump of conventional backstepping is stated there (model §12).
    #[serde(default)]
    pub vc_initial: BTreeMap<u32, f64>,
}

/// The part a case plays in the paper's comparisons (docs/model.md §12), read from
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
    pub fn load(dir: &Path, label: String) -> Result<Case, Error> {
        if !dir.is_dir() {
            return Err(Error::Input(format!("{}: no such run folder", dir.display())));
        }
        let summary_path = dir.join("summary.json");
        let text = fs::read_to_string(&summary_path).map_err(|e| {
            Error::Input(format!("{}: not a run folder (cannot read summary.json: {e})", dir.display()))
        })?;
        let mut summary: Summary = serde_json::from_str(&text).map_err(|e| json_error(&summary_path, &text, &e))?;
        summary.mark_unreached();
        let ids: Vec<u32> = summary.followers.keys().copied().collect();
        let has_csv = has_csv(dir, &ids)?;
        // A damaged CSV is refused here, before the report writes anything:
        // a field that is not a number, or, in a complete run, not finite.
        let finite = summary.complete;
        if has_csv {
            read_columns_checked(&dir.join("leader.csv"), &[], finite)?;
        }
        let seeds_path = dir.join(SEEDS_FILE);
        let seeds = if seeds_path.is_file() {
            // (Without seeds.json the follower CSVs are read just below.)
            if has_csv {
                for id in &ids {
                    read_columns_checked(&dir.join(format!("follower_{id}.csv")), &[], finite)?;
                }
            }
            let text = fs::read_to_string(&seeds_path).map_err(at_path(&seeds_path, "cannot read"))?;
            let mut seeds: Vec<SeedRecord> =
                serde_json::from_str(&text).map_err(|e| json_error(&seeds_path, &text, &e))?;
            for r in &mut seeds {
                r.summary.mark_unreached();
            }
            if seeds.is_empty() {
                return Err(Error::Input(format!("{}: no seeds", seeds_path.display())));
            }
            seeds
        } else {
            let (e4, e6, vc0) = if has_csv {
                estimator_checkpoints_from_csv(dir, &ids, summary.dt, finite)?
            } else {
                Default::default()
            };
            vec![SeedRecord {
                seed: summary.seed,
                summary,
                estimator_error_4s: e4,
                estimator_error_6s: e6,
                vc_initial: vc0,
            }]
        };
        let role = Role::of(&seeds[0].summary);
        Ok(Case { label, dir: dir.to_path_buf(), seeds, role, has_csv, networked: dir.join("network.json").is_file() })
    }
}

/// Whether a run folder holds its CSVs: `leader.csv` and one per follower,
/// or none of them (a run with `--no-csv`). Some of them is a damaged folder.
fn has_csv(dir: &Path, ids: &[u32]) -> Result<bool, Error> {
    let files: Vec<String> =
        std::iter::once("leader.csv".to_string()).chain(ids.iter().map(|id| format!("follower_{id}.csv"))).collect();
    let (present, missing): (Vec<&String>, Vec<&String>) = files.iter().partition(|f| dir.join(f).is_file());
    match (present.first(), missing.first()) {
        (_, None) => Ok(true),
        (None, Some(_)) => Ok(false),
        (Some(there), Some(gone)) => {
            let more = match missing.len() {
                1 => " is".to_string(),
                n => format!(" and {} more are", n - 1),
            };
            Err(Error::Input(format!(
                "{}: {gone}{more} missing, though {there} is there (a run writes every CSV, or none with \
                 --no-csv): a damaged run folder",
                dir.display()
            )))
        }
    }
}

/// A JSON file's error in one line: the file, the line and column, the key
/// the value at fault belongs to, and what is wrong with it.
pub fn json_error(path: &Path, text: &str, e: &serde_json::Error) -> Error {
    let words = e.to_string();
    let words = words.split(" at line ").next().unwrap_or(&words).to_string();
    let at = if e.line() == 0 { String::new() } else { format!(":{}:{}", e.line(), e.column()) };
    let key = match e.classify() {
        serde_json::error::Category::Data => key_at(text, e.line(), e.column()).map(|k| format!("`{k}`: ")),
        _ => None,
    };
    let hint = match e.classify() {
        serde_json::error::Category::Eof => " (the file is cut short)",
        serde_json::error::Category::Syntax => " (not valid JSON)",
        _ => "",
    };
    Error::Input(format!("{}{at}: {}{words}{hint}", path.display(), key.unwrap_or_default()))
}

/// The dotted key (`followers.2.rms`) of the value that starts before
/// `line`:`column` (1-based) of a JSON text: the last key named in each
/// object still open there.
fn key_at(text: &str, line: usize, column: usize) -> Option<String> {
    let start: usize = text.split_inclusive('\n').take(line.saturating_sub(1)).map(str::len).sum();
    let end = text.len().min(start + column);
    let bytes = &text.as_bytes()[..end];
    // One entry per open object ({) or array ([): the object's last key.
    let mut open: Vec<Option<String>> = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'{' | b'[' => open.push(None),
            b'}' | b']' => {
                open.pop();
            }
            b'"' => {
                let from = i + 1;
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    i += if bytes[i] == b'\\' { 2 } else { 1 };
                }
                let word = String::from_utf8_lossy(&bytes[from..i.min(bytes.len())]).into_owned();
                let mut j = i + 1;
                while j < bytes.len() && bytes[j].is_ascii_whitespace() {
                    j += 1;
                }
                if bytes.get(j) == Some(&b':') {
                    if let Some(top) = open.last_mut() {
                        *top = Some(word);
                    }
                }
            }
            _ => {}
        }
        i += 1;
    }
    let keys: Vec<String> = open.into_iter().flatten().collect();
    (!keys.is_empty()).then(|| keys.join("."))
}

/// A value per follower id.
type ErrorById = BTreeMap<u32, f64>;

/// The estimator position error at t = 4 s and 6 s from a folder's CSVs:
/// the sample within half a step of the time, if there is one; and v_c at
/// t = 0 (the CSVs print every value in full, so it is exact).
fn estimator_checkpoints_from_csv(
    dir: &Path,
    ids: &[u32],
    dt_s: f64,
    finite: bool,
) -> Result<(ErrorById, ErrorById, ErrorById), Error> {
    let mut at = [BTreeMap::new(), BTreeMap::new()];
    let mut vc0 = BTreeMap::new();
    for &id in ids {
        let path = dir.join(format!("follower_{id}.csv"));
        let table = read_columns_checked(&path, &["t", "estimator_error", "v_c"], finite)?;
        if table[0].first() == Some(&0.0) {
            vc0.insert(id, table[2][0]);
        }
        for (slot, &time) in at.iter_mut().zip(&ESTIMATOR_CHECK_TIMES_S) {
            let hit = table[0].iter().position(|&t| (t - time).abs() <= 0.5 * dt_s + 1e-9);
            if let Some(i) = hit {
                slot.insert(id, table[1][i]);
            }
        }
    }
    let [a, b] = at;
    Ok((a, b, vc0))
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
    pub params: ClaimParams,
    /// Extra lines for the report's header (seeds, wall time, …).
    pub notes: Vec<String>,
    /// `formation paper`'s outage study, when it ran.
    pub study: Option<Study>,
}

/// The scenario values the claims are checked against.
#[derive(Clone, Debug, PartialEq)]
pub struct ClaimParams {
    /// C_1 of the backstepping controllers.
    pub c1: f64,
    /// B of the kinematic shunting model.
    pub shunting_b: f64,
    /// An upper bound of the leader's speed, m/s.
    pub vr_max: f64,
    /// The follower with the largest initial error x̂(0) (F4 in the paper)…
    pub jump_follower: u32,
    /// …and its conventional command at t = 0, C_1 x̂(0) + v_ir(0) cos θ̂(0), m/s.
    pub jump_expected: f64,
}

impl ClaimParams {
    /// docs/model.md §10's values (used for folders, which do not record gains):
    /// C_1 = 3, B = 2, max v_r = √2, F4 jumps to 3 · 5 = 15 m/s.
    pub fn paper_defaults() -> Self {
        Self { c1: 3.0, shunting_b: 2.0, vr_max: std::f64::consts::SQRT_2, jump_follower: 4, jump_expected: 15.0 }
    }

    /// The values of a scenario, with x̂(0) from its initial estimate.
    pub fn from_scenario(s: &Scenario) -> Self {
        let est = s.initial_estimate();
        let k = &s.control.kinematic_gains;
        let (jump_follower, jump_expected) = s
            .followers
            .iter()
            .map(|f| {
                // v_c(0) of conventional backstepping: C_1 x̂(0) + v_ir cos θ̂ (eq. 29, 35).
                let e = kinematic::body_error(&est.pose, f.offset, &f.pose);
                let v_c = kinematic::command(KinematicKind::Conventional, k, 0.0, &e, est.v, est.w).v;
                (f.id, v_c)
            })
            .fold((0, 0.0_f64), |best, x| if x.1.abs() > best.1.abs() { x } else { best });
        Self { c1: k.c1, shunting_b: k.shunting.b, vr_max: s.leader_max_speed(), jump_follower, jump_expected }
    }
}

/// `formation paper`'s outage study, loaded.
#[derive(Clone, Debug)]
pub struct Study {
    /// The follower whose links are cut.
    pub node: u32,
    /// The outage cases (none when the run is too short for them).
    pub outage: Vec<Case>,
    /// The loss cases, in ascending loss.
    pub sweep: Vec<Case>,
    /// What the cases are.
    pub notes: Vec<String>,
    /// What was skipped, and why.
    pub skipped: Vec<String>,
}
