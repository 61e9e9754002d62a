//! End to end: a run that did not complete is never reported as passing.
//! Its `summary.json` says `"complete": false` and which followers are
//! short, a metric whose window was not reached is null (not 0), and
//! `formation report` shows every claim on it as N/A with the reason.

use crate::common;

use common::run_ok;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use formation_record::{FollowerMetrics, MetricsAccumulator, Row, Summary};
use formation_scenario::Scenario;
use serde_json::{json, Value};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_formation"))
}

fn paper_toml() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml")
}

fn run(cmd: &mut Command) -> Output {
    cmd.output().expect("formation runs")
}

fn read_json(path: &Path) -> Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `formation report` on one run folder: its printed claims and claims.csv
/// as (claim, result) pairs.
fn report(run_dir: &Path, out: &Path) -> (String, Vec<(String, String)>) {
    let o = run_ok(bin().arg("report").arg(run_dir).arg("--out").arg(out));
    let mut r = csv::Reader::from_path(out.join("claims.csv")).expect("claims.csv");
    let rows = r
        .deserialize::<BTreeMap<String, String>>()
        .map(|row| {
            let row = row.expect("claims.csv row");
            (row["claim"].clone(), row["result"].clone())
        })
        .collect();
    (String::from_utf8_lossy(&o.stdout).into_owned(), rows)
}

/// The printed line of the claim that contains `part`.
fn line<'a>(stdout: &'a str, part: &str) -> &'a str {
    stdout.lines().find(|l| l.contains(part)).unwrap_or_else(|| panic!("no claim with {part} in:\n{stdout}"))
}

const FORMATION_CLAIM: &str = "formation-error RMS over the last 10 s below 0.2 m";
const ESTIMATOR_CLAIM: &str = "below 0.01 m at t = T";

#[test]
fn a_run_cut_short_is_incomplete_and_report_shows_its_claims_as_na_with_the_reason() {
    let tmp = tempfile::tempdir().unwrap();
    let full = tmp.path().join("proposed");
    // 12 s at 1 ms: 12001 samples; "the last 10 s" start at step 2000.
    run_ok(bin().arg("sim").arg(paper_toml()).args(["--set", "duration=12", "--every", "1", "-q", "--out"]).arg(&full));
    let scenario = Scenario::load(&paper_toml(), &["duration=12".to_string()]).expect("scenario");
    assert_eq!(scenario.steps() + 1, 12001);
    let text = std::fs::read_to_string(full.join("summary.json")).unwrap();
    // A complete run's summary.json is what it was before `complete` existed.
    assert!(!text.contains("\"complete\""), "a complete run writes no `complete` key:\n{text}");
    assert!(!text.contains("\"incomplete\""), "a complete run has no shortfall:\n{text}");
    let summary: Summary = serde_json::from_str(&text).unwrap();
    for (id, m) in &summary.followers {
        assert!(
            m.formation_rms_last10.is_some() && m.estimator_error_final.is_some(),
            "F{id} of a complete run: {m:?}"
        );
    }

    // Follower 3 stops after 1500 samples (t = 1.499 s): its CSV rows replayed
    // through the metrics the simulator and the monitor use.
    let rows: Vec<Row> = csv::Reader::from_path(full.join("follower_3.csv"))
        .unwrap()
        .deserialize()
        .collect::<Result<_, _>>()
        .expect("follower_3.csv rows");
    assert_eq!(rows.len(), 12001, "--every 1 writes every sample");
    let replay = |n: usize| -> FollowerMetrics {
        let mut acc = MetricsAccumulator::new(scenario.steps(), scenario.dt_s);
        for (k, r) in rows[..n].iter().enumerate() {
            acc.push(k as u64, r, None);
        }
        acc.finish()
    };
    let (again, recorded) = (replay(rows.len()), summary.followers[&3]);
    let (a, b) = (again.formation_rms_last10.unwrap(), recorded.formation_rms_last10.unwrap());
    assert!((a - b).abs() <= 1e-12 * b, "replayed rows give the run's formation RMS: {a} vs {b}");

    let cut = tmp.path().join("proposed-cut");
    std::fs::create_dir(&cut).unwrap();
    for f in ["leader.csv", "follower_1.csv", "follower_2.csv", "follower_4.csv"] {
        std::fs::copy(full.join(f), cut.join(f)).unwrap();
    }
    let csv3 = std::fs::read_to_string(full.join("follower_3.csv")).unwrap();
    let kept: Vec<&str> = csv3.lines().take(1 + 1500).collect();
    std::fs::write(cut.join("follower_3.csv"), kept.join("\n") + "\n").unwrap();
    let mut followers = summary.followers.clone();
    followers.insert(3, replay(1500));
    std::fs::write(cut.join("summary.json"), Summary::new(&scenario, followers).to_json()).unwrap();

    let v = read_json(&cut.join("summary.json"));
    assert_eq!(v["complete"], false, "summary.json of the cut run: {v}");
    assert_eq!(v["incomplete"], json!({ "3": { "recorded": 1500, "expected": 12001 } }));
    let f3 = &v["followers"]["3"];
    for key in ["formation_rms_last10", "formation_final", "heading_final", "estimator_error_final"] {
        assert!(f3[key].is_null(), "F3 {key}: window not reached, so null, got {}", f3[key]);
    }
    assert!(f3["vc_peak"].is_f64() && f3["samples"] == 1500, "F3 measured over what it recorded: {f3}");
    let (f1, f1_full) = (&v["followers"]["1"]["formation_rms_last10"], &summary.followers[&1].formation_rms_last10);
    assert!((f1.as_f64().unwrap() - f1_full.unwrap()).abs() <= 1e-15, "F1 unchanged: {f1} vs {f1_full:?}");

    // The complete run passes the claims the cut run must not.
    let (full_out, full_claims) = report(&full, &tmp.path().join("report-full"));
    let formation = line(&full_out, FORMATION_CLAIM);
    assert!(formation.starts_with("PASS"), "the complete 12 s run: {formation}");
    let passed: Vec<&String> = full_claims.iter().filter(|(_, r)| r == "PASS").map(|(c, _)| c).collect();
    assert!(passed.len() >= 3, "claims passed by the complete run: {passed:?}");

    // An older summary.json of the same run: no `complete`, zeros where the
    // windows were not reached.
    let legacy = tmp.path().join("proposed-legacy");
    std::fs::create_dir(&legacy).unwrap();
    let mut old = v.clone();
    old.as_object_mut().unwrap().remove("complete");
    old.as_object_mut().unwrap().remove("incomplete");
    for key in ["formation_rms_last10", "formation_final", "heading_final", "estimator_error_final"] {
        old["followers"]["3"][key] = json!(0.0);
    }
    std::fs::write(legacy.join("summary.json"), serde_json::to_string_pretty(&old).unwrap()).unwrap();

    for (dir, name) in [(&cut, "proposed-cut"), (&legacy, "proposed-legacy")] {
        let (out, claims) = report(dir, &tmp.path().join(format!("report-{name}")));
        let pass: Vec<&str> = out.lines().filter(|l| l.starts_with("PASS")).collect();
        assert!(pass.is_empty(), "{name}: an incomplete run passes nothing, got {pass:?}");
        for claim in &passed {
            let result = &claims.iter().find(|(c, _)| c == *claim).expect("same claims").1;
            assert_eq!(result, "N/A", "{name}: {claim} (PASS on the complete run)");
        }
        let why = format!("{name}: follower 3 recorded 1500 of 12001 samples (to t = 1.499 s of T = 12 s)");
        let formation = line(&out, FORMATION_CLAIM);
        assert!(
            formation.starts_with("N/A") && formation.contains(&format!("n/a: {why}, the last 10 s not reached")),
            "{name}: {formation}"
        );
        let estimator = line(&out, ESTIMATOR_CLAIM);
        assert!(
            estimator.starts_with("N/A") && estimator.contains(&format!("{why}, the sample at t = T not reached")),
            "{name}: {estimator}"
        );
        let md = std::fs::read_to_string(tmp.path().join(format!("report-{name}/report.md"))).unwrap();
        assert!(md.contains(&format!("INCOMPLETE: {}", &why[name.len() + 2..])), "{name}: the case says so");
        let f3_row = md.lines().find(|l| l.starts_with(&format!("| {name} | 3 |"))).expect("F3 in the metrics table");
        assert!(f3_row.contains("| n/a |"), "{name}: F3's null metrics show as n/a: {f3_row}");
    }
}

#[test]
fn a_diverged_sim_keeps_an_incomplete_summary_that_report_never_passes() {
    let tmp = tempfile::tempdir().unwrap();
    // Forward Euler with k_a Δt = 1000 is unstable: the estimate blows up.
    let text = std::fs::read_to_string(paper_toml()).unwrap().replace("ka = [20.0, 20.0]", "ka = [1e6, 1e6]");
    let file = tmp.path().join("diverging.toml");
    std::fs::write(&file, text).unwrap();
    let out = tmp.path().join("run");
    let o = run(bin().arg("sim").arg(&file).args(["--set", "duration=12", "-q", "--out"]).arg(&out));
    assert_eq!(o.status.code(), Some(1), "diverges: {}", String::from_utf8_lossy(&o.stderr));

    let partial = tmp.path().join("run.partial");
    let v = read_json(&partial.join("summary.json"));
    assert_eq!(v["complete"], false, "{v}");
    let short = v["incomplete"].as_object().expect("the short followers");
    assert!(!short.is_empty(), "{v}");
    for (id, s) in short {
        let (recorded, expected) = (s["recorded"].as_u64().unwrap(), s["expected"].as_u64().unwrap());
        assert!(recorded < 2000 && expected == 12001, "F{id}: recorded {recorded} of {expected}, diverged early");
        let f = &v["followers"][id];
        assert!(f["formation_rms_last10"].is_null() && f["estimator_error_final"].is_null(), "F{id}: {f}");
    }

    let (stdout, claims) = report(&partial, &tmp.path().join("report"));
    assert!(claims.iter().all(|(_, r)| r != "PASS"), "nothing passes on a diverged run: {claims:?}");
    let formation = line(&stdout, FORMATION_CLAIM);
    assert!(
        formation.starts_with("N/A")
            && formation.contains("run.partial: follower ")
            && formation.contains(" of 12001 samples"),
        "{formation}"
    );
}
