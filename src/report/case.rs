//! What a report compares: a *case* (a run folder, with its seeds), its
//! role in the paper, and the context a report is made in. Every part of a
//! report (tables, figures, faults, network) reads these; none reads
//! another part's types through them.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use formation_agent::{kinematic, KinematicKind};
use formation_record::{at_path, read_columns, Summary};
use formation_topology::Scenario;
use serde::{Deserialize, Serialize};

use crate::error::CliError;

/// File, in a case folder, with every seed's record (written by `formation paper`).
pub const SEEDS_FILE: &str = "seeds.json";

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
        let table = read_columns(&dir.join(format!("follower_{id}.csv")), &["t", "estimator_error"])?;
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
        Self { c1: k.c1, shunting_b: k.shunting.b, vr_max: s.leader_profile.max_speed(), jump_follower, jump_expected }
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
