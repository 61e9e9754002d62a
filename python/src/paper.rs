//! The paper as data: Tables I and II (velocity RMSE per follower, KF and
//! ASIF, normal and fault case, over seeds) and every docs/model.md §12
//! claim — the cases `formation paper` runs (the same scenarios, seeds and
//! checks), held as numbers beside the paper's.

use std::path::{Path, PathBuf};

use formation_record::FollowerMetrics;
use formation_report::paper::{case_scenario, run_seed, PaperCase, CASES};
use formation_report::tables::{claims as check_claims, Check, PAPER_TABLE_I, PAPER_TABLE_II};
use formation_report::{Case, ClaimParams, Role, SeedRecord};
use formation_scenario::Scenario;
use rayon::prelude::*;

/// One table: `values[s][f]` is seed `seeds[s]`'s row for follower
/// `ids[f]`, in the paper's column order (linear KF, linear ASIF, angular
/// KF, angular ASIF), ×10⁻² like the paper; NaN where a run does not reach
/// the metric's window.
#[derive(Clone, Debug, PartialEq)]
pub struct PaperTable {
    pub title: &'static str,
    pub seeds: Vec<u64>,
    pub ids: Vec<u32>,
    pub values: Vec<Vec<[f64; 4]>>,
    /// The paper's rows, follower 1 to 4.
    pub paper: [[f64; 4]; 4],
}

/// What `formation paper` checks, from one set of runs: Tables I and II,
/// and the claims as its `claims.csv` gives them.
#[derive(Clone, Debug)]
pub struct Paper {
    pub tables: Vec<PaperTable>,
    pub claims: Vec<Check>,
}

/// The four columns' cases of Table I (normal) and Table II (fault): KF then ASIF.
const TABLE_CASES: [(&str, [&str; 2], &[[f64; 4]; 4]); 2] = [
    ("Table I: velocity RMSE under the normal case (×10⁻²)", ["kf-normal", "proposed"], &PAPER_TABLE_I),
    ("Table II: velocity RMSE under the fault case (×10⁻²)", ["kf-fault", "asif-fault"], &PAPER_TABLE_II),
];

/// Every case of `formation paper` for the scenario at `path` with `user`
/// assignments (only the tables' four without `claims`), `seeds` seeds from
/// its own (s, s+1, …), the runs on `threads` threads; the tables and
/// claims built from them.
pub fn paper(path: &Path, user: &[String], seeds: u64, threads: usize, claims: bool) -> Result<Paper, String> {
    if seeds == 0 {
        return Err("seeds must be at least 1".into());
    }
    let base = Scenario::load(path, user).map_err(|e| e.to_string())?;
    let in_tables = |name: &str| TABLE_CASES.iter().any(|(_, names, _)| names.contains(&name));
    let picked: Vec<&PaperCase> = CASES.iter().filter(|c| claims || in_tables(c.name)).collect();
    let scenarios = picked
        .iter()
        .map(|c| case_scenario(path, user, c).map_err(|e| e.to_string()))
        .collect::<Result<Vec<_>, _>>()?;
    let seed_list: Vec<u64> = (0..seeds).map(|i| base.seed.wrapping_add(i)).collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads.max(1))
        .build()
        .map_err(|e| format!("cannot start {threads} threads: {e}"))?;
    let jobs: Vec<(usize, u64)> = (0..scenarios.len()).flat_map(|c| seed_list.iter().map(move |&s| (c, s))).collect();
    let runs = pool.install(|| {
        jobs.par_iter()
            .map(|&(c, seed)| run_seed(&scenarios[c], seed, None).map_err(|e| e.to_string()))
            .collect::<Result<Vec<SeedRecord>, String>>()
    })?;
    let mut runs = runs.into_iter();
    // Each case as `formation paper`'s report loads it from its folder.
    let cases: Vec<Case> = picked
        .iter()
        .map(|c| {
            let mut seeds: Vec<SeedRecord> = runs.by_ref().take(seed_list.len()).collect();
            seeds.iter_mut().for_each(|r| r.summary.mark_unreached());
            let role = Role::of(&seeds[0].summary);
            Case { label: c.name.into(), dir: PathBuf::from(c.name), seeds, role, has_csv: false, networked: false }
        })
        .collect();
    let tables = TABLE_CASES.iter().map(|(title, names, paper)| table(&cases, title, names, paper)).collect();
    let claims = if claims { check_claims(&cases, &ClaimParams::from_scenario(&base)) } else { Vec::new() };
    Ok(Paper { tables, claims })
}

/// A table from its KF and ASIF cases, seeds paired by position.
fn table(cases: &[Case], title: &'static str, names: &[&str; 2], paper: &[[f64; 4]; 4]) -> PaperTable {
    let [kf, asif] = names.map(|n| cases.iter().find(|c| c.label == n).expect("a case of formation paper"));
    let ids = kf.follower_ids();
    let values = kf
        .seeds
        .iter()
        .zip(&asif.seeds)
        .map(|(k, a)| {
            ids.iter()
                .map(|id| {
                    let (kf, asif) = (k.summary.followers.get(id), a.summary.followers.get(id));
                    // ×10⁻² as the paper; NaN where the run does not reach the window.
                    let pct = |x: Option<f64>| x.map_or(f64::NAN, |x| x * 100.0);
                    let v = |m: Option<&FollowerMetrics>| pct(m.and_then(|m| m.rmse_v));
                    let w = |m: Option<&FollowerMetrics>| pct(m.and_then(|m| m.rmse_w));
                    [v(kf), v(asif), w(kf), w(asif)]
                })
                .collect()
        })
        .collect();
    PaperTable { title, seeds: kf.seeds.iter().map(|r| r.seed).collect(), ids, values, paper: *paper }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The table's numbers are the runs' own: seed 1's KF row for follower
    /// 1 is `formation sim`'s rmse_v of the kf-normal case ×100; the claims
    /// are checked on the same runs (conventional backstepping's jump is
    /// that case's v_c(0) of F4).
    #[test]
    fn a_tables_entry_and_a_claims_value_are_the_runs_own() {
        let user = vec!["duration=12".to_string()];
        let p = paper(Path::new("paper"), &user, 2, 2, true).expect("paper");
        let t = &p.tables;
        assert_eq!(t.len(), 2);
        assert_eq!(t[0].seeds, vec![1, 2]);
        assert_eq!(t[0].ids, vec![1, 2, 3, 4]);
        assert_eq!(t[1].paper[0], [6.43, 1.18, 2.10, 1.03]);
        let run = |name: &str, seed| {
            let case = CASES.iter().find(|c| c.name == name).unwrap();
            run_seed(&case_scenario(Path::new("paper"), &user, case).unwrap(), seed, None).unwrap()
        };
        assert_eq!(t[0].values[0][0][0], run("kf-normal", 1).summary.followers[&1].rmse_v.unwrap() * 100.0);
        // The fault case (fault at 10 s) differs from the normal one.
        assert_ne!(t[0].values[0][0][0], t[1].values[0][0][0]);

        let jump = p.claims.iter().find(|c| c.claim.contains("v_c(0)")).expect("the jump claim");
        assert_eq!(jump.cases, ["conventional-backstepping"]);
        assert_eq!(
            jump.values,
            [run("conventional-backstepping", 1).vc_initial[&4], run("conventional-backstepping", 2).vc_initial[&4]]
        );
        assert_eq!(jump.result(), "PASS", "{jump:?}");
        // A 12 s run cannot show the last 10 s of a 20 s run: said, never passed.
        let na: Vec<&str> = p.claims.iter().filter(|c| c.result() == "N/A").map(|c| c.claim.as_str()).collect();
        assert!(p.claims.len() > 8 && na.len() < p.claims.len(), "{} claims, N/A: {na:?}", p.claims.len());
        assert!(paper(Path::new("paper"), &user, 0, 1, true).unwrap_err().contains("at least 1"));
        // The tables alone: the same four cases' numbers, no claims.
        let alone = paper(Path::new("paper"), &user, 2, 2, false).expect("paper");
        assert_eq!((alone.tables, alone.claims.len()), (p.tables, 0));
    }
}
