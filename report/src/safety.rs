//! The report's safety section (docs/model.md §16): for every case whose
//! scenario has robot limits or a safety distance, how close the robots
//! came and what the limits and the filter did, as `safety.csv` and a table.

use std::fmt::Write as _;
use std::path::Path;

use crate::case::Case;
use formation_exit::Error;
use formation_record::at_path;

const HEADER: &str = "case,safety_distance_m,filter,closest_m,closest_pair,closest_t_s,steps_below,\
                      first_below_t_s,follower_steps,saturated,filtered,change_max_m_s,infeasible,blind,deadlocks,sidestep_steps";

/// Writes `safety.csv` and returns the section's markdown (empty when no
/// case has limits or a safety distance).
pub fn write(out: &Path, cases: &[Case]) -> Result<String, Error> {
    let rows: Vec<(&Case, Vec<String>)> = cases.iter().filter_map(|c| Some((c, row(c)?))).collect();
    if rows.is_empty() {
        return Ok(String::new());
    }
    let mut csv = format!("{HEADER}\n");
    for (_, r) in &rows {
        let _ = writeln!(csv, "{}", r.join(","));
    }
    let path = out.join("safety.csv");
    std::fs::write(&path, csv).map_err(at_path(&path, "cannot write"))?;
    let mut md = String::from(
        "## Safety (docs/model.md §16)\n\nHow close any two robots' centres came, which pair and when, and what the \
         limits and the safety filter did to the commands, over every follower-step.\n\n\
         | case | safety distance | filter | closest (pair, t) | steps closer | a limit clipped | the filter changed \
         (largest) | stopped | deadlocks |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    );
    for (c, _) in &rows {
        let s = c.summary();
        let p = s.safety.as_ref();
        let g = s.guard_total();
        let pct = |n: u64| g.map_or(0.0, |g| 100.0 * n as f64 / g.steps.max(1) as f64);
        let closest = p
            .and_then(|p| p.closest)
            .map_or("n/a".into(), |c| format!("{:.3} m ({} and {}, {:.2} s)", c.distance, c.pair[0], c.pair[1], c.t));
        let below = p.map_or("n/a".into(), |p| match p.first_below {
            Some(f) => format!("**{}** (from {:.2} s)", p.steps_below, f.t),
            None => "0".into(),
        });
        let _ = writeln!(
            md,
            "| {} | {} | {} | {closest} | {below} | {} | {} | {} | {} |",
            c.label,
            p.map_or("none".into(), |p| format!("{} m", p.distance)),
            if p.is_some_and(|p| p.filter) { "on" } else { "off" },
            g.map_or("n/a".into(), |g| format!("{} ({:.1} %)", g.saturated, pct(g.saturated))),
            g.map_or("n/a".into(), |g| format!("{} ({:.1} %, {:.3} m/s)", g.filtered, pct(g.filtered), g.change_max)),
            g.map_or("n/a".into(), |g| format!("{} infeasible, {} stale", g.infeasible, g.blind)),
            g.map_or("n/a".into(), |g| format!("{} ({} steps sidestepping)", g.deadlocks, g.sidestep)),
        );
    }
    md += "\nData: [safety.csv](safety.csv).\n\n";
    Ok(md)
}

/// The case's `safety.csv` row; None without limits or a safety distance.
fn row(c: &Case) -> Option<Vec<String>> {
    let s = c.summary();
    let (p, g) = (s.safety.as_ref(), s.guard_total());
    if p.is_none() && g.is_none() {
        return None;
    }
    let opt = |v: Option<String>| v.unwrap_or_default();
    let closest = p.and_then(|p| p.closest);
    Some(vec![
        c.label.replace(',', ";"),
        opt(p.map(|p| p.distance.to_string())),
        p.is_some_and(|p| p.filter).to_string(),
        opt(closest.map(|c| c.distance.to_string())),
        opt(closest.map(|c| format!("{}-{}", c.pair[0], c.pair[1]))),
        opt(closest.map(|c| c.t.to_string())),
        opt(p.map(|p| p.steps_below.to_string())),
        opt(p.and_then(|p| p.first_below).map(|f| f.t.to_string())),
        opt(g.map(|g| g.steps.to_string())),
        opt(g.map(|g| g.saturated.to_string())),
        opt(g.map(|g| g.filtered.to_string())),
        opt(g.map(|g| g.change_max.to_string())),
        opt(g.map(|g| g.infeasible.to_string())),
        opt(g.map(|g| g.blind.to_string())),
        opt(g.map(|g| g.deadlocks.to_string())),
        opt(g.map(|g| g.sidestep.to_string())),
    ])
}
