//! docs/model.md §12: what the paper scenario must show, each claim a test, on the
//! paper scenario with noise on and its fixed seed. Every assertion prints
//! the number it measured.

use std::path::Path;

use formation_record::{FollowerMetrics, Row};
use formation_scenario::Scenario;
use formation_sim::{NoRecord, Observer, Simulation};

fn scenario(overrides: &[&str]) -> Scenario {
    let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    Scenario::load(&path, &overrides).expect("paper scenario loads")
}

fn run(overrides: &[&str]) -> (Scenario, Vec<FollowerMetrics>) {
    let s = scenario(overrides);
    let metrics = Simulation::new(&s).run(&mut NoRecord, |_| {}).expect("run completes");
    (s, metrics)
}

/// Each follower's v_c at step 0.
#[derive(Default)]
struct FirstCommand(std::collections::BTreeMap<usize, f64>);

impl Observer for FirstCommand {
    fn leader(&mut self, _: u64, _: &formation_leader::LeaderState) -> std::io::Result<()> {
        Ok(())
    }
    fn follower(&mut self, index: usize, k: u64, row: &Row, _: bool) -> std::io::Result<()> {
        if k == 0 {
            self.0.insert(index, row.v_c);
        }
        Ok(())
    }
}

/// Model §12 as stated: F4's v_c(0) = C_1 · x̂_4(0) = 15 m/s to 1e-9, and
/// its peak |v_c| within 0.05 m/s of it (noise moves the robot before the
/// peak).
#[test]
fn conventional_backstepping_jumps_to_c1_times_initial_error() {
    let s = scenario(&["kinematic=conventional"]);
    let mut first = FirstCommand::default();
    let m = Simulation::new(&s).run(&mut first, |_| {}).expect("run completes");
    let i = s.index_of(4).unwrap();
    // F4 starts with x̂(0) = 5 and v_ir(0) = v_r(0) = 0: v_c(0) = C_1 · 5 = 15 m/s.
    let expected = s.control.kinematic_gains.c1 * 5.0;
    let vc0 = first.0[&i];
    assert!((vc0 - expected).abs() <= 1e-9, "conventional v_c(0) of F4 = {vc0} m/s, expected {expected}");
    let peak = m[i].vc_peak.expect("a complete run measures every metric");
    assert!((peak - expected).abs() <= 0.05, "conventional peak v_c of F4 = {peak} m/s, expected {expected} ± 0.05");
}

#[test]
fn bioinspired_backstepping_has_no_speed_jump() {
    let (s, m) = run(&[]);
    let k = &s.control.kinematic_gains;
    let bound = k.c1 * k.shunting.b + s.leader_profile.max_speed();
    for (f, m) in s.followers.iter().zip(&m) {
        let vc_peak = m.vc_peak.expect("measured");
        assert!(vc_peak <= bound, "F{}: peak v_c {vc_peak} > C1·B + max v_r = {bound}", f.id);
        assert!(vc_peak < 4.0, "F{}: peak v_c {vc_peak} m/s is not below 4 m/s", f.id);
    }
}

#[test]
fn normal_case_asif_equals_kf_within_two_percent() {
    let (s, asif) = run(&["filter=asif"]);
    let (_, kf) = run(&["filter=kf"]);
    for ((f, a), k) in s.followers.iter().zip(&asif).zip(&kf) {
        for (name, a, k) in [("linear", a.rmse_v, k.rmse_v), ("angular", a.rmse_w, k.rmse_w)] {
            let (a, k) = (a.expect("measured"), k.expect("measured"));
            let rel = (a - k).abs() / k;
            assert!(rel <= 0.02, "F{} {name}: ASIF {a:.5} vs KF {k:.5} differ by {:.2} %", f.id, rel * 100.0);
            for (filter, x) in [("ASIF", a), ("KF", k)] {
                assert!(
                    (0.006..=0.015).contains(&x),
                    "F{} {name} {filter} RMSE {:.3}e-2 outside 0.6–1.5e-2",
                    f.id,
                    x * 100.0
                );
            }
        }
    }
}

#[test]
fn fault_case_asif_halves_the_kf_linear_error() {
    let (s, asif) = run(&["filter=asif", "fault.time=10"]);
    let (_, kf) = run(&["filter=kf", "fault.time=10"]);
    for ((f, a), k) in s.followers.iter().zip(&asif).zip(&kf) {
        let [av, aw, kv, kw] = [a.rmse_v, a.rmse_w, k.rmse_v, k.rmse_w].map(|x| x.expect("measured"));
        assert!(av <= 0.5 * kv, "F{} linear: ASIF {av:.5} > half of KF {kv:.5}", f.id);
        assert!(aw <= kw, "F{} angular: ASIF {aw:.5} > KF {kw:.5}", f.id);
    }
}

#[test]
fn conventional_smc_chatters_super_twisting_less_bioinspired_least() {
    let (s, bio) = run(&["dynamic=bio"]);
    let (_, smc) = run(&["dynamic=smc"]);
    let (_, st) = run(&["dynamic=super-twisting"]);
    for (i, f) in s.followers.iter().enumerate() {
        let [b, c, t] = [bio[i].torque_tv, smc[i].torque_tv, st[i].torque_tv].map(|x| x.expect("measured"));
        assert!(c >= 50.0 * b, "F{}: SMC torque variation {c:.1} N m/s < 50 × bioinspired {b:.2}", f.id);
        assert!(b < t && t < c, "F{}: super-twisting {t:.1} not between bioinspired {b:.2} and SMC {c:.1}", f.id);
    }
}

#[test]
fn estimator_converges_from_the_leader_start() {
    let (s, m) = run(&[]);
    for (f, m) in s.followers.iter().zip(&m) {
        let e = m.estimator_error_final.expect("measured");
        assert!(e < 0.01, "F{}: estimator error {e} m at t = T", f.id);
    }
}

/// Records the largest estimator position error at given steps.
struct ErrorAt {
    steps: Vec<u64>,
    worst: Vec<f64>,
}

impl Observer for ErrorAt {
    fn follower(&mut self, _index: usize, k: u64, row: &Row, _last: bool) -> std::io::Result<()> {
        if let Some(i) = self.steps.iter().position(|&s| s == k) {
            self.worst[i] = self.worst[i].max(row.estimator_error);
        }
        Ok(())
    }
}

#[test]
fn estimator_converges_from_zero_at_rate_k() {
    let s = scenario(&["estimate_init=zero", "duration=6"]);
    let at = |t: f64| (t / s.dt_s).round() as u64;
    let mut obs = ErrorAt { steps: vec![0, at(4.0), at(6.0)], worst: vec![0.0; 3] };
    Simulation::new(&s).run(&mut obs, |_| {}).expect("run completes");
    // Starting 3 m off, e^(−t) gives 0.055 m at 4 s and 0.0074 m at 6 s (eq. 16, k_i = 1).
    assert!((obs.worst[0] - 3.0).abs() < 1e-9, "initial error {} m, expected 3 m", obs.worst[0]);
    assert!(obs.worst[1] < 0.1, "estimator error {} m at t = 4 s", obs.worst[1]);
    assert!(obs.worst[2] < 0.02, "estimator error {} m at t = 6 s", obs.worst[2]);
}

#[test]
fn formation_error_is_bounded() {
    let (s, m) = run(&[]);
    for (f, m) in s.followers.iter().zip(&m) {
        let rms = m.formation_rms_last10.expect("measured");
        assert!(rms < 0.2, "F{}: formation RMS over the last 10 s = {rms} m", f.id);
    }
}

#[test]
fn paper_graph_reports_lambda_min() {
    let s = scenario(&[]);
    let l = s.graph.lambda_min_h().expect("computed for 4 followers");
    assert!((l - 0.186).abs() < 1e-3, "λ_min(H) = {l}");
}

#[test]
fn initial_body_errors_match_the_spec() {
    // docs/model.md §10: x = (5, 2, 5, 2), y = 3 + Δy, θ = 0.
    let s = scenario(&[]);
    for (f, x) in s.followers.iter().zip([5.0, 2.0, 5.0, 2.0]) {
        assert!(
            (f.pose.x - x).abs() < 1e-12 && (f.pose.y - 3.0 - f.offset[1]).abs() < 1e-12 && f.pose.theta == 0.0,
            "F{}: {:?}",
            f.id,
            f.pose
        );
    }
}

/// scenarios/paper-tables.toml (docs/paper-results.md, "Calibrating the
/// decided values"): with the decided values fitted to the paper's tables,
/// every entry of Tables I and II is within 10 % (Table I) or 15 % (Table
/// II) of the paper, the normal case's KF and ASIF within 2 %, and the
/// ASIF's fault-case advantage shows on both channels; the price the
/// documentation states is there too: a formation error above 0.2 m.
/// (The mean of 5 seeds, as the tables are means; `formation paper
/// --scenario paper-tables --seeds 20` gives the same.)
#[test]
fn the_fitted_values_reproduce_both_tables_at_the_formations_expense() {
    use formation_report::tables::{PAPER_TABLE_I, PAPER_TABLE_II};
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper-tables.toml");
    let run = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let s = Scenario::load(&path, &sets).expect("paper-tables loads");
        Simulation::new(&s).run(&mut NoRecord, |_| {}).expect("run completes")
    };
    let cases: [(&[&str], usize, usize); 4] = [
        (&["filter=kf"], 0, 0),
        (&["filter=asif"], 0, 1),
        (&["filter=kf", "fault.time=10"], 1, 0),
        (&["filter=asif", "fault.time=10"], 1, 1),
    ];
    const SEEDS: u64 = 5;
    let first = Scenario::load(&path, &[]).expect("paper-tables loads").seed;
    let mut got = [[[0.0; 4]; 4]; 2];
    let mut formation: f64 = 0.0;
    // Each seed's normal case: [follower][KF linear, ASIF linear, KF angular, ASIF angular].
    let mut normal = vec![[[0.0; 4]; 4]; SEEDS as usize];
    for (sets, table, filter) in cases {
        for n in 0..SEEDS {
            let seed = format!("seed={}", first + n);
            let sets: Vec<&str> = sets.iter().copied().chain([seed.as_str()]).collect();
            for (i, m) in run(&sets).iter().enumerate() {
                let (v, w) = (m.rmse_v.expect("measured") * 100.0, m.rmse_w.expect("measured") * 100.0);
                got[table][i][filter] += v / SEEDS as f64;
                got[table][i][2 + filter] += w / SEEDS as f64;
                if table == 0 {
                    normal[n as usize][i][filter] = v;
                    normal[n as usize][i][2 + filter] = w;
                }
                if (table, filter) == (0, 1) {
                    formation = formation.max(m.formation_rms_last10.expect("measured"));
                }
            }
        }
    }
    let cols = ["KF linear", "ASIF linear", "KF angular", "ASIF angular"];
    for (t, (paper, tol)) in [(PAPER_TABLE_I, 0.10), (PAPER_TABLE_II, 0.15)].iter().enumerate() {
        for (f, row) in paper.iter().enumerate() {
            for (c, &want) in row.iter().enumerate() {
                let x = got[t][f][c];
                assert!(
                    (x / want - 1.0).abs() <= *tol,
                    "Table {}, F{} {}: {x:.3} against the paper's {want} ({:+.1} %, allowed ±{:.0} %)",
                    ["I", "II"][t],
                    f + 1,
                    cols[c],
                    (x / want - 1.0) * 100.0,
                    tol * 100.0
                );
            }
        }
    }
    for (n, seed) in normal.iter().enumerate() {
        for (f, row) in seed.iter().enumerate() {
            for (ch, (k, a)) in [("linear", (row[0], row[1])), ("angular", (row[2], row[3]))] {
                let gap = (a - k).abs() / k;
                assert!(
                    gap <= 0.02,
                    "seed {}, F{} {ch}, normal case: ASIF {a:.4} against KF {k:.4}",
                    first + n as u64,
                    f + 1
                );
            }
        }
    }
    for (f, row) in got[1].iter().enumerate() {
        assert!(row[3] < 0.7 * row[2], "F{} fault, angular: ASIF {:.3} not well below KF {:.3}", f + 1, row[3], row[2]);
    }
    assert!(formation > 0.2, "the formation error {formation:.3} m: the fitted values no longer cost the 0.2 m bound");
}
