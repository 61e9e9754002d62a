//! A run as data: one [`Row`] per follower and step, the metrics of
//! docs/model.md §11 computed from the rows (and §14's under faults), and
//! the run folder (a CSV per follower, `leader.csv`, `summary.json`,
//! `run.mcap`) read and written. The simulator and the monitor both record
//! through this crate, so their folders have the same shape and, for the
//! same rows, the same numbers.
//!
//! Modules, each using only those listed before it: [`row`], [`columns`],
//! [`outage`], [`metrics`], [`summary`], [`hearing`], [`mcap`], [`folder`],
//! [`live`].
//!
//! # Examples
//!
//! A run folder's CSV read back by column, and a damaged one refused with
//! its line and column:
//!
//! ```
//! use formation_record::read_columns;
//!
//! let dir = std::env::temp_dir().join(format!("formation-record-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! let csv = dir.join("follower_1.csv");
//! std::fs::write(&csv, "t,e_x,e_y\n0,0.5,0.1\n0.01,0.25,0.05\n").unwrap();
//! assert_eq!(read_columns(&csv, &["e_x", "t"]).unwrap(), [vec![0.5, 0.25], vec![0.0, 0.01]]);
//!
//! std::fs::write(&csv, "t,e_x\n0,0.5\n0.01,oops\n").unwrap();
//! let refused = read_columns(&csv, &["e_x"]).unwrap_err().to_string();
//! assert!(refused.contains("line 3"), "{refused}");
//! std::fs::remove_dir_all(&dir).unwrap();
//! ```

pub mod bounded;
pub mod columns;
pub mod folder;
pub mod hearing;
pub mod live;
pub mod mcap;
pub mod metrics;
pub mod out_path;
pub mod outage;
pub mod proximity;
pub mod rosbag2;
pub mod row;
pub mod stall;
pub mod summary;

pub use columns::{read_columns, read_columns_checked, RecordError};
pub use folder::{at_path, refuse_foreign_folder, refuse_replacing_foreign, RecordOptions, RunWriter};
pub use hearing::{FollowerHearing, Heard, HeardRuns, HearingRecord, HEARING_FILE};
pub use live::LiveSink;
pub use metrics::{last10_from_k, FollowerMetrics, MetricsAccumulator};
pub use outage::{FaultSummary, OutageMetrics};
pub use proximity::{PairAt, Proximity};
pub use row::{leader_csv_fields, FollowerSample, Row, FOLLOWER_HEADER, LEADER_HEADER};
pub use summary::{name, Shortfall, Summary};

#[cfg(test)]
mod tests {
    use std::path::Path;

    use formation_scenario::Scenario;

    use super::*;

    /// T = 20 s at Δt = 0.01 s: 2000 steps, 2001 samples, the last 10 s from k = 1000.
    const STEPS: u64 = 2000;
    const DT: f64 = 0.01;

    fn row(k: u64) -> Row {
        let x = k as f64 * 1e-3;
        Row {
            t: k as f64 * DT,
            v: 1.0,
            v_hat: 1.0 + x,
            v_c: 2.0 - x,
            tau_l: x,
            tau_r: -x,
            formation_error: x,
            heading_error: 0.5 * x,
            estimator_error: 0.25 * x,
            ..Default::default()
        }
    }

    /// The metrics of the samples of steps 0..n.
    fn metrics_of(n: u64) -> FollowerMetrics {
        let mut acc = MetricsAccumulator::new(STEPS, DT);
        for k in 0..n {
            acc.push(k, &row(k), None);
        }
        acc.finish()
    }

    fn scenario() -> Scenario {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        Scenario::load(&path, &["dt=0.01".to_string(), "duration=20".to_string()]).expect("scenario")
    }

    #[test]
    fn a_run_cut_before_the_last_10_s_has_null_windows_not_zeros() {
        assert_eq!(last10_from_k(STEPS, DT), 1000, "T − 10 = 10 s is step 1000");
        // Samples k = 0..=799: t ≤ 7.99 s < T − 10.
        let m = metrics_of(800);
        assert_eq!(m.samples, 800);
        assert_eq!(m.formation_rms_last10, None, "no sample with t ≥ 10 s, got {:?}", m.formation_rms_last10);
        for (name, x) in [
            ("formation_final", m.formation_final),
            ("heading_final", m.heading_final),
            ("estimator_error_final", m.estimator_error_final),
            ("estimator_v_error_final", m.estimator_v_error_final),
            ("estimator_w_error_final", m.estimator_w_error_final),
        ] {
            assert_eq!(x, None, "{name}: the sample at t = T was not recorded, got {x:?}");
        }
        // Whole-run metrics are measured over what was recorded.
        let rmse_v = (0..800).map(|k| (k as f64 * 1e-3).powi(2)).sum::<f64>() / 800.0;
        assert!((m.rmse_v.unwrap() - rmse_v.sqrt()).abs() < 1e-12, "rmse_v {:?} vs {}", m.rmse_v, rmse_v.sqrt());
        assert_eq!(m.vc_peak, Some(2.0), "peak |v_c| at k = 0: {:?}", m.vc_peak);
        // Σ|Δτ| = 2 · 799 · 1e-3 over the recorded 7.99 s, not over T = 20 s.
        let tv = m.torque_tv.unwrap();
        assert!((tv - 2.0 * 799.0 * 1e-3 / 7.99).abs() < 1e-9, "torque_tv {tv}");
        let json = serde_json::to_value(m).unwrap();
        assert!(json["formation_rms_last10"].is_null() && json["formation_final"].is_null(), "{json}");
    }

    #[test]
    fn a_run_cut_inside_the_last_10_s_has_its_rms_but_no_final_values() {
        // Samples k = 0..=1499: 500 of them in the last 10 s, none at t = T.
        let m = metrics_of(1500);
        let want = ((1000..1500).map(|k| (k as f64 * 1e-3).powi(2)).sum::<f64>() / 500.0).sqrt();
        let rms = m.formation_rms_last10.expect("500 samples with t ≥ 10 s");
        assert!((rms - want).abs() < 1e-12, "formation RMS over the recorded last 10 s {rms} vs {want}");
        assert_eq!(m.formation_final, None, "formation_final {:?} without the sample at t = T", m.formation_final);
        assert_eq!(m.estimator_error_final, None, "estimator_error_final {:?}", m.estimator_error_final);
    }

    #[test]
    fn a_complete_run_measures_everything_and_no_samples_measure_nothing() {
        let m = metrics_of(STEPS + 1);
        assert_eq!(m.formation_final, Some(2.0), "final formation error = row(2000).formation_error");
        assert_eq!(m.heading_final, Some(1.0));
        assert_eq!(m.estimator_error_final, Some(0.5));
        let tv = m.torque_tv.unwrap();
        assert!((tv - 2.0 * 2000.0 * 1e-3 / 20.0).abs() < 1e-9, "torque_tv {tv} = Σ|Δτ| / T");
        assert!(m.formation_rms_last10.is_some());
        assert_eq!(metrics_of(0), FollowerMetrics::default(), "no samples: every metric null");
    }

    #[test]
    fn summary_says_which_followers_are_short_and_older_zeros_become_null() {
        let s = scenario();
        let full = Summary::new(&s, s.followers.iter().map(|f| (f.id, metrics_of(STEPS + 1))).collect());
        assert!(full.complete && full.incomplete.is_empty());
        let json = full.to_json();
        // Complete: no key at all, so the file is what it was before the key existed.
        assert!(!json.contains("complete"), "{json}");
        let v: serde_json::Value = serde_json::from_str(&json).unwrap();
        let mut metrics = v["followers"].as_object().unwrap().values().flat_map(|m| m.as_object().unwrap().values());
        assert!(metrics.all(serde_json::Value::is_number), "a complete run has no null metric: {json}");

        let mut followers = full.followers.clone();
        followers.insert(3, metrics_of(800));
        let cut = Summary::new(&s, followers);
        assert!(!cut.complete);
        assert_eq!(cut.incomplete.len(), 1, "{:?}", cut.incomplete);
        assert_eq!(
            cut.incomplete[&3],
            Shortfall { recorded: 800, expected: 2001, in_gaps: 0, left: None, joined_at_k: None }
        );
        let v: serde_json::Value = serde_json::from_str(&cut.to_json()).unwrap();
        assert_eq!(v["complete"], false);
        assert_eq!(v["incomplete"]["3"], serde_json::json!({ "recorded": 800, "expected": 2001 }));
        assert!(v["followers"]["3"]["formation_rms_last10"].is_null(), "{}", v["followers"]["3"]);
        assert_eq!(
            cut.shortfall_text().as_deref(),
            Some("follower 3 recorded 800 of 2001 samples (to t = 7.99 s of T = 20 s)")
        );
        assert!(cut.table().contains("incomplete run: follower 3 recorded 800 of 2001"), "{}", cut.table());

        // An older file: no `complete`, zeros for the windows not reached.
        let mut old = v.clone();
        old.as_object_mut().unwrap().remove("complete");
        old.as_object_mut().unwrap().remove("incomplete");
        for key in ["formation_rms_last10", "formation_final", "heading_final", "estimator_error_final"] {
            old["followers"]["3"][key] = 0.0.into();
        }
        let mut read: Summary = serde_json::from_value(old).expect("older summary.json loads");
        assert_eq!(read.followers[&3].formation_rms_last10, Some(0.0), "as written");
        read.mark_unreached();
        let cut: Summary = serde_json::from_value(v).unwrap();
        assert_eq!(read, cut, "an older file reads as the same incomplete run");
    }
}
