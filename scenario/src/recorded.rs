//! `leader.source = "recorded"`: a run's `leader.csv` read back as the
//! leader of another run (docs/model.md §18). Row k is the leader's state
//! at step k (t = k Δt, its pose, v_r and ω_r; Ṗ_r follows from eq. 6), so
//! a human's or a robot's leader is simulated again bit for bit. Refused,
//! in one line: a file that is not a leader record, a row that is not
//! finite, steps that are not the scenario's `dt` apart or that skip one,
//! and a record shorter than the run.

use std::path::{Path, PathBuf};

use formation_leader::LeaderState;
use formation_plant::Pose;

/// The header a leader record starts with (the run folder's `leader.csv`).
pub const HEADER: &str = "t,x,y,theta,v,w";

/// The file `path` names: `path/leader.csv` for a run folder.
pub fn file_of(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join("leader.csv")
    } else {
        path.to_path_buf()
    }
}

/// The leader's states of steps 0..=`steps`, read from `path` (a run
/// folder or a leader CSV), each row's t checked against k Δt.
pub fn read(path: &Path, dt_s: f64, steps: u64) -> Result<Vec<LeaderState>, String> {
    let file = file_of(path);
    let text = std::fs::read_to_string(&file).map_err(|e| format!("{}: {e}", file.display()))?;
    parse(&text, dt_s, steps).map_err(|e| format!("{}: {e}", file.display()))
}

/// [`read`]'s work on the text of a record.
pub fn parse(text: &str, dt_s: f64, steps: u64) -> Result<Vec<LeaderState>, String> {
    let mut lines = text.lines();
    if lines.next().map(str::trim) != Some(HEADER) {
        return Err(format!("not a leader record (its first line must be `{HEADER}`, as a run folder's leader.csv)"));
    }
    let mut states = Vec::new();
    for (k, line) in lines.enumerate().take(steps as usize + 1) {
        let row = k + 2;
        let fields: Vec<f64> =
            line.split(',').map(|f| f.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|_| {
                format!("row {row} (`{}`) is not six numbers", line.chars().take(60).collect::<String>())
            })?;
        let [t, x, y, theta, v, w] = fields[..] else {
            return Err(format!("row {row} has {} fields, not the six of `{HEADER}`", fields.len()));
        };
        if !fields.iter().all(|f| f.is_finite()) {
            return Err(format!("row {row} holds a value that is not finite"));
        }
        let want = k as f64 * dt_s;
        if (t - want).abs() > 1e-9 * want.abs().max(1.0) {
            return Err(if k == 1 {
                format!(
                    "its rows are {t} s apart; the scenario's dt is {dt_s} s (a record of another dt, or one written \
                     with --every: a leader is played from every step)"
                )
            } else {
                format!("row {row} is at t = {t} s, not step {k}'s {want} s: a step is missing or dt differs")
            });
        }
        let (s, c) = theta.sin_cos();
        states.push(LeaderState { pose: Pose::new(x, y, theta), pose_rate: Pose::new(v * c, v * s, w), v, w });
    }
    if (states.len() as u64) < steps + 1 {
        let end = states.len().saturating_sub(1) as f64 * dt_s;
        return Err(format!(
            "it ends at t = {end} s ({} steps); the scenario runs {} s: set duration ≤ {end}",
            states.len().saturating_sub(1),
            steps as f64 * dt_s
        ));
    }
    Ok(states)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(rows: &[[f64; 6]]) -> String {
        let mut s = format!("{HEADER}\n");
        for r in rows {
            let f: Vec<String> = r.iter().map(f64::to_string).collect();
            s += &(f.join(",") + "\n");
        }
        s
    }

    #[test]
    fn a_record_reads_back_with_its_rates_from_eq_6() {
        let text = record(&[[0.0, 1.0, 2.0, 0.5, 0.0, 0.0], [0.02, 1.0, 2.0, 0.5, 0.2, -0.1]]);
        let states = parse(&text, 0.02, 1).expect("two steps");
        assert_eq!(states[1].pose, Pose::new(1.0, 2.0, 0.5));
        assert_eq!(states[1].pose_rate, Pose::new(0.2 * 0.5f64.cos(), 0.2 * 0.5f64.sin(), -0.1));
        assert_eq!(parse(&text, 0.02, 0).expect("a shorter run").len(), 1, "rows past the run are not read");
    }

    #[test]
    fn every_bad_record_is_refused_in_one_line() {
        let ok = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let cases: [(String, f64, u64, &str); 6] = [
            ("x,y\n0,0\n".into(), 0.02, 0, "not a leader record"),
            (
                record(&[ok, [0.01, 0.0, 0.0, 0.0, 0.0, 0.0]]),
                0.02,
                1,
                "rows are 0.01 s apart; the scenario's dt is 0.02 s",
            ),
            (record(&[ok, [0.02, 0.0, 0.0, 0.0, 0.0, 0.0], [0.06, 0.0, 0.0, 0.0, 0.0, 0.0]]), 0.02, 2, "missing"),
            (record(&[ok, [0.02, 0.0, f64::NAN, 0.0, 0.0, 0.0]]), 0.02, 1, "not finite"),
            (format!("{HEADER}\n0,0,0\n"), 0.02, 0, "3 fields"),
            (record(&[ok]), 0.02, 50, "ends at t = 0 s (0 steps); the scenario runs 1 s"),
        ];
        for (text, dt, steps, says) in cases {
            let e = parse(&text, dt, steps).expect_err(says);
            assert!(e.contains(says) && !e.contains('\n'), "{e:?} should say {says:?}");
        }
    }
}
