//! The paper's Tables I and II as data: velocity RMSE per follower, KF and
//! ASIF, normal and fault case, over seeds — the runs `formation paper`
//! makes for those tables (the same cases and scenarios), held as numbers
//! beside the paper's.

use std::path::Path;

use formation_record::FollowerMetrics;
use formation_report::paper::{case_scenario, run_seed, CASES};
use formation_report::tables::{PAPER_TABLE_I, PAPER_TABLE_II};
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

/// The four columns' cases of Table I (normal) and Table II (fault): KF then ASIF.
const TABLE_CASES: [(&str, [&str; 2], &[[f64; 4]; 4]); 2] = [
    ("Table I: velocity RMSE under the normal case (×10⁻²)", ["kf-normal", "proposed"], &PAPER_TABLE_I),
    ("Table II: velocity RMSE under the fault case (×10⁻²)", ["kf-fault", "asif-fault"], &PAPER_TABLE_II),
];

/// Tables I and II for the scenario at `path` with `user` assignments,
/// `seeds` seeds from its own (s, s+1, …), the runs on `threads` threads.
pub fn tables(path: &Path, user: &[String], seeds: u64, threads: usize) -> Result<Vec<PaperTable>, String> {
    if seeds == 0 {
        return Err("seeds must be at least 1".into());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads.max(1))
        .build()
        .map_err(|e| format!("cannot start {threads} threads: {e}"))?;
    TABLE_CASES
        .iter()
        .map(|(title, names, paper)| pool.install(|| table(path, user, seeds, title, names, paper)))
        .collect()
}

fn table(
    path: &Path,
    user: &[String],
    seeds: u64,
    title: &'static str,
    names: &[&str; 2],
    paper: &[[f64; 4]; 4],
) -> Result<PaperTable, String> {
    let scenarios = names
        .iter()
        .map(|name| {
            let case = CASES.iter().find(|c| c.name == *name).expect("a case of formation paper");
            case_scenario(path, user, case).map_err(|e| e.to_string())
        })
        .collect::<Result<Vec<_>, String>>()?;
    let ids: Vec<u32> = scenarios[0].followers.iter().map(|f| f.id).collect();
    let first = scenarios[0].seed;
    let seed_list: Vec<u64> = (0..seeds).map(|i| first.wrapping_add(i)).collect();
    let jobs: Vec<(usize, u64)> = (0..2).flat_map(|c| seed_list.iter().map(move |&s| (c, s))).collect();
    let runs = jobs
        .par_iter()
        .map(|&(c, seed)| run_seed(&scenarios[c], seed, None).map(|r| r.summary).map_err(|e| e.to_string()))
        .collect::<Result<Vec<_>, String>>()?;
    let n = seed_list.len();
    let values = (0..n)
        .map(|s| {
            ids.iter()
                .map(|id| {
                    let (kf, asif) = (runs[s].followers.get(id), runs[n + s].followers.get(id));
                    // ×10⁻² as the paper; NaN where the run does not reach the window.
                    let pct = |x: Option<f64>| x.map_or(f64::NAN, |x| x * 100.0);
                    let v = |m: Option<&FollowerMetrics>| pct(m.and_then(|m| m.rmse_v));
                    let w = |m: Option<&FollowerMetrics>| pct(m.and_then(|m| m.rmse_w));
                    [v(kf), v(asif), w(kf), w(asif)]
                })
                .collect()
        })
        .collect();
    Ok(PaperTable { title, seeds: seed_list, ids, values, paper: *paper })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The table's numbers are the runs' own: seed 1's KF row for follower
    /// 1 is `formation sim`'s rmse_v of the kf-normal case ×100.
    #[test]
    fn a_tables_entry_is_its_runs_rmse() {
        let user = vec!["duration=12".to_string()];
        let t = tables(Path::new("paper"), &user, 2, 2).expect("tables");
        assert_eq!(t.len(), 2);
        assert_eq!(t[0].seeds, vec![1, 2]);
        assert_eq!(t[0].ids, vec![1, 2, 3, 4]);
        assert_eq!(t[1].paper[0], [6.43, 1.18, 2.10, 1.03]);
        let case = CASES.iter().find(|c| c.name == "kf-normal").unwrap();
        let s = case_scenario(Path::new("paper"), &user, case).unwrap();
        let r = run_seed(&s, 1, None).unwrap();
        assert_eq!(t[0].values[0][0][0], r.summary.followers[&1].rmse_v.unwrap() * 100.0);
        // The fault case (fault at 10 s) differs from the normal one.
        assert_ne!(t[0].values[0][0][0], t[1].values[0][0][0]);
        assert!(tables(Path::new("paper"), &user, 0, 1).unwrap_err().contains("at least 1"));
    }
}
