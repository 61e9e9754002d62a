//! `formation sim` from the outside: bad input gives one clear line and exit
//! status 2 with no run folder left behind; runs are deterministic; every
//! `--set` the issue names works.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn paper_text() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml")).unwrap()
}

fn formation(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_formation")).args(args).output().expect("formation runs")
}

/// Writes `text` as a scenario into a fresh temp dir and runs `formation sim`
/// on it with `extra` arguments, into `<tmp>/out`.
fn sim_text(text: &str, extra: &[&str]) -> (Output, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("s.toml");
    std::fs::write(&file, text).unwrap();
    let out = dir.path().join("out");
    let mut args = vec!["sim", file.to_str().unwrap(), "--out", out.to_str().unwrap(), "-q"];
    args.extend_from_slice(extra);
    (formation(&args), dir)
}

/// Asserts exit status 2, a single-line message containing every `needle`,
/// and no run folder.
fn assert_rejected(text: &str, extra: &[&str], needles: &[&str]) {
    let (out, dir) = sim_text(text, extra);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "exit status for {needles:?}; stderr: {stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "one line expected, got: {stderr}");
    for n in needles {
        assert!(stderr.contains(n), "message should contain {n:?}: {stderr}");
    }
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left.len(), 1, "a run folder was left behind: {left:?}");
}

fn replace(from: &str, to: &str) -> String {
    let t = paper_text();
    assert!(t.contains(from), "paper.toml has no {from:?}");
    t.replacen(from, to, 1)
}

#[test]
fn unknown_key_is_named_with_its_line() {
    assert_rejected(
        &replace("mass = 10.0", "mass = 10.0\nmas = 3"),
        &[],
        &["s.toml:74:", "[robot]: unknown key `mas`"],
    );
}

#[test]
fn missing_required_values_are_named() {
    let t = paper_text();
    let start = t.find("edges = ").unwrap();
    let end = start + t[start..].find('\n').unwrap();
    assert_rejected(&format!("{}{}", &t[..start], &t[end..]), &[], &["missing key `edges`"]);
    assert_rejected(&replace("body_error = [5.0, 0.0, 0.0]\n", ""), &[], &["followers[3].pose", "missing"]);
}

#[test]
fn wrong_type_is_named_with_its_line() {
    assert_rejected(
        &replace("c1 = 3.0", "c1 = \"three\""),
        &[],
        &["s.toml:59:", "backstepping.c1: expected a number, found the string \"three\""],
    );
}

#[test]
fn non_positive_physical_values_are_rejected() {
    for (from, to, field) in [
        ("mass = 10.0", "mass = -1.0", "robot.mass"),
        ("inertia = 5.0", "inertia = 0.0", "robot.inertia"),
        ("wheel_radius = 0.05", "wheel_radius = -0.05", "robot.wheel_radius"),
        ("dt = 0.001", "dt = 0.0", "dt"),
        ("duration = 30.0", "duration = -5.0", "duration"),
    ] {
        let text = replace(from, to);
        let line = text.lines().position(|l| l.starts_with(to)).unwrap() + 1;
        assert_rejected(&text, &[], &[&format!("s.toml:{line}: {field}: must be positive")]);
    }
}

#[test]
fn non_finite_numbers_are_rejected() {
    assert_rejected(&replace("mass = 10.0", "mass = inf"), &[], &["robot.mass", "finite"]);
    assert_rejected(&replace("offset = [4.0, 4.0]", "offset = [nan, 4.0]"), &[], &["followers[1].offset", "finite"]);
}

#[test]
fn graph_errors_are_named() {
    assert_rejected(&replace("[3, 4]]", "[3, 9]]"), &[], &["edges[3]", "unknown follower 9"]);
    assert_rejected(&replace("id = 2", "id = 1"), &[], &["duplicate follower id 1"]);
    assert_rejected(&replace("[3, 4]]", "[3, 4], [4, 3]]"), &[], &["edges[4]", "duplicate edge 4–3"]);
    assert_rejected(&replace("[3, 4]]", "[3, 4], [2, 2]]"), &[], &["edges[4]", "self-loop"]);
}

#[test]
fn lemma_1_violation_names_the_unreachable_followers() {
    // Without edges 2–4 and 3–4, follower 4 hears nobody who hears the leader.
    assert_rejected(
        &replace("[[1, 2], [1, 3], [2, 4], [3, 4]]", "[[1, 2], [1, 3]]"),
        &[],
        &["Lemma 1", "followers 4 "],
    );
    assert_rejected(
        &replace("leader_link = true", "leader_link = false"),
        &[],
        &["no follower hears the leader", "leader_link = true"],
    );
}

#[test]
fn bad_overrides_are_rejected() {
    let t = paper_text();
    assert_rejected(&t, &["--set", "nosuch=1"], &["--set nosuch=1", "unknown key `nosuch`"]);
    assert_rejected(&t, &["--set", "robot.colour=1"], &["unknown key `robot.colour` (the keys here are `model`"]);
    // Said once (it read "unknown key `nosuch` (unknown key `nosuch` (…))").
    let (out, _dir) = sim_text(&t, &["--set", "nosuch=1"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.matches("unknown key").count(), 1, "{stderr}");
    assert_rejected(&t, &["--set", "duration=abc"], &["--set duration=abc", "expected a number"]);
    assert_rejected(&t, &["--set", "filter=ukf"], &["--set filter=ukf", "`ukf` is not one of: asif, kf, none"]);
    assert_rejected(&t, &["--set", "duration"], &["expected KEY=VALUE"]);
    assert_rejected(&t, &["--set", "robot.mass=0"], &["robot.mass: must be positive"]);
    // Both assignments an error of two keys depends on (it named only the last).
    assert_rejected(
        &t,
        &["--set", "dt=0.3", "--set", "duration=1"],
        &["--set dt=0.3 --set duration=1: duration: 1 s is not a whole number of steps of 0.3 s"],
    );
    // The file's rejoin_after under half of a Δt the user set: the Δt is named, with the way out.
    assert_rejected(
        &t,
        &["--set", "dt=0.3"],
        &["--set dt=0.3: network.rejoin_after: 0.1 s is less than half a step", "--set network.rejoin_after=0.3"],
    );
    // No value (it read "`` is not a TOML value").
    assert_rejected(&t, &["--set", "duration="], &["--set duration=: no value after `=`"]);
}

/// The 1-based line of the first line of `text` that starts with `start`.
fn line_of(text: &str, start: &str) -> usize {
    text.lines().position(|l| l.starts_with(start)).unwrap_or_else(|| panic!("no line starts with {start:?}")) + 1
}

#[test]
fn an_array_longer_than_its_field_is_rejected_naming_the_field() {
    for (from, to, field, want) in [
        ("offset = [4.0, 4.0]", "offset = [4.0, 4.0, 9.0]", "followers[1].offset", "expected 2 numbers, got 3"),
        (
            "edges = [[1, 2], [1, 3], [2, 4], [3, 4]]",
            "edges = [[1, 2], [1, 3], [2, 4, 1], [3, 4]]",
            "edges[2]",
            "expected 2 follower ids, got 3",
        ),
        ("ka = [20.0, 20.0]", "ka = [20.0, 20.0, 5.0]", "estimator.ka", "expected 2 numbers, got 3"),
    ] {
        let text = replace(from, to);
        assert_rejected(&text, &[], &[&format!("s.toml:{}: {field}: {want}", line_of(&text, to))]);
    }
}

#[test]
fn a_set_never_takes_the_blame_for_an_error_in_the_file() {
    // The file's error, with its line, whatever --set is given besides.
    let text = replace("ka = [20.0, 20.0]", "ka = [20.0, 20.0, 5.0]");
    let want = format!("s.toml:{}: estimator.ka: expected 2 numbers, got 3", line_of(&text, "ka = "));
    let (out, dir) = sim_text(&text, &["--set", "duration=1"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.trim_end(), format!("error: {}/{want}", dir.path().display()), "{stderr}");
    assert!(!stderr.contains("--set"), "a --set took the blame: {stderr}");
    assert_rejected(&text, &["--set", "duration=1", "--set", "seed=3"], &[&want]);
    let text = replace("mass = 10.0", "mass = -1.0");
    assert_rejected(
        &text,
        &["--set", "duration=1"],
        &[&format!("s.toml:{}: robot.mass: must be positive", line_of(&text, "mass = -1.0"))],
    );
}

#[test]
fn an_error_in_a_set_value_names_the_set_not_a_file_line() {
    let t = paper_text();
    let (out, _dir) = sim_text(&t, &["--set", "duration=1", "--set", "robot.mass=-1"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert_eq!(stderr.trim_end(), "error: --set robot.mass=-1: robot.mass: must be positive, got -1", "{stderr}");
    // A --set that makes a value of the file wrong is named, not the file's line.
    assert_rejected(&t, &["--set", "dt=0.007"], &["--set dt=0.007: duration: 30 s is not a whole number of steps"]);
    assert_rejected(&t, &["--set", "edges=[[1, 2]]"], &["--set edges=[[1, 2]]: graph: H is not positive definite"]);
    assert_rejected(
        &t,
        &["--set", "estimator.ka=[1, 2, 3]"],
        &["--set estimator.ka=[1, 2, 3]: `estimator.ka`: expected 2 numbers, got 3"],
    );
}

#[test]
fn every_zero_is_refused() {
    let (out, dir) = sim_text(&paper_text(), &["--set", "duration=0.1", "--every", "0"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert_eq!(stderr.trim_end(), "error: --every must be at least 1, not 0", "{stderr}");
    assert!(!dir.path().join("out").exists() && !dir.path().join("out.partial").exists(), "a folder was written");
    let out = formation(&["paper", "--every", "0", "--out", dir.path().join("p").to_str().unwrap(), "-q"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert_eq!(stderr.trim_end(), "error: --every must be at least 1, not 0", "{stderr}");
}

#[test]
fn fault_time_beyond_the_run_is_refused() {
    let text = replace("mass_factor = 0.01", "time = 30.5\nmass_factor = 0.01");
    let line = line_of(&text, "time = 30.5");
    assert_rejected(
        &text,
        &[],
        &[&format!("s.toml:{line}: fault.time: must lie within [0, duration] = [0, 30] s, got 30.5")],
    );
    let t = paper_text();
    assert_rejected(
        &t,
        &["--set", "duration=1", "--set", "fault.time=10"],
        &["--set fault.time=10: fault.time: must lie within [0, duration] = [0, 1] s, got 10"],
    );
    // A fault in the file, a --set duration that ends the run before it.
    assert_rejected(
        &replace("mass_factor = 0.01", "time = 10.0\nmass_factor = 0.01"),
        &["--set", "duration=5"],
        &["--set duration=5: fault.time: must lie within"],
    );
}

/// Runs `formation sim` on the paper scenario into `out` and returns exit status and stderr.
fn sim_into(out: &Path) -> (Option<i32>, String) {
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", scenario.to_str().unwrap(), "--set", "duration=0.1", "-q", "--out"])
        .arg(out)
        .output()
        .expect("formation runs");
    (o.status.code(), String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn out_errors_name_the_path() {
    let tmp = tempfile::tempdir().unwrap();
    // --out naming a regular file: refused up front, the file kept, nothing written.
    let file = tmp.path().join("notes.txt");
    std::fs::write(&file, "data").unwrap();
    let (code, stderr) = sim_into(&file);
    assert_eq!(code, Some(2), "{stderr}");
    assert_eq!(
        stderr.trim_end(),
        format!("error: {} exists and is not a folder: refusing to replace it", file.display())
    );
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "data");
    // A path through a file.
    let (code, stderr) = sim_into(&file.join("run"));
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.starts_with(&format!("error: {}", file.join("run").display())), "{stderr}");
    assert!(stderr.contains("cannot create the folder") && stderr.contains("os error"), "{stderr}");
    // An over-long name: refused up front (not by the OS after the run),
    // naming the name and its length.
    let long = tmp.path().join("a".repeat(300));
    let (code, stderr) = sim_into(&long);
    assert_eq!(code, Some(2), "{stderr}");
    assert_eq!(stderr.trim_end(), "error: --out: the name `aaaaaaaaaaaaaaaaaaaa…` is 300 bytes long, at most 200");
    let left: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left, vec![std::ffi::OsString::from("notes.txt")], "nothing written");
}

#[test]
fn duration_must_be_a_whole_number_of_steps() {
    assert_rejected(
        &replace("duration = 30.0", "duration = 10.0005"),
        &[],
        &["duration", "not a whole number of steps"],
    );
}

#[test]
fn out_never_replaces_a_folder_that_is_not_a_run_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let keep = tmp.path().join("keep");
    std::fs::create_dir(&keep).unwrap();
    std::fs::write(keep.join("important.txt"), "data").unwrap();
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    let out =
        formation(&["sim", scenario.to_str().unwrap(), "--out", keep.to_str().unwrap(), "--set", "duration=0.1", "-q"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("not a run folder"), "{stderr}");
    assert_eq!(std::fs::read_to_string(keep.join("important.txt")).unwrap(), "data");
    // A run folder is replaced by the next run into it.
    let run = tmp.path().join("run");
    for _ in 0..2 {
        let o = formation(&[
            "sim",
            scenario.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--set",
            "duration=0.1",
            "-q",
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    // A folder that looks like a run (a summary.json) but holds the user's
    // files, a run folder the user added notes to, and a `.partial` left
    // beside it that holds a file of the user's: refused, nothing deleted.
    let sim = |out: &Path| {
        formation(&["sim", scenario.to_str().unwrap(), "--out", out.to_str().unwrap(), "--set", "duration=0.1", "-q"])
    };
    let lookalike = tmp.path().join("lookalike");
    std::fs::create_dir(&lookalike).unwrap();
    std::fs::write(lookalike.join("summary.json"), "garbage").unwrap();
    std::fs::write(lookalike.join("thesis.tex"), "precious").unwrap();
    std::fs::write(run.join("notes.txt"), "mine").unwrap();
    let beside = tmp.path().join("fresh");
    let partial = tmp.path().join("fresh.partial");
    std::fs::create_dir(&partial).unwrap();
    std::fs::write(partial.join("mine.txt"), "mine").unwrap();
    for (out, file, kept) in [
        (&lookalike, "thesis.tex", lookalike.join("thesis.tex")),
        (&run, "notes.txt", run.join("notes.txt")),
        (&beside, "mine.txt", partial.join("mine.txt")),
    ] {
        let o = sim(out);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{}: {stderr}", out.display());
        assert!(stderr.contains(&format!("holds {file}, which no run writes")), "{}: {stderr}", out.display());
        assert_eq!(stderr.trim().lines().count(), 1, "one line, not {stderr}");
        assert!(kept.exists(), "{} was deleted", kept.display());
    }
    assert_eq!(std::fs::read_to_string(run.join("notes.txt")).unwrap(), "mine");
}

#[test]
fn missing_file_is_a_clear_error() {
    let out = formation(&["sim", "/nonexistent/scenario.toml", "-q"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/scenario.toml: cannot read"));
}

#[test]
fn a_diverging_run_names_follower_step_and_quantity() {
    // Forward Euler with k_a Δt = 1000 is unstable: the estimate blows up.
    let (out, dir) = sim_text(&replace("ka = [20.0, 20.0]", "ka = [1e6, 1e6]"), &["--set", "duration=2"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "stderr: {stderr}");
    assert!(stderr.contains("follower ") && stderr.contains("at step ") && stderr.contains("not finite"), "{stderr}");
    let quantities = ["leader estimate", "shunting", "sliding-mode", "filtered velocity", "torque", "robot"];
    assert!(quantities.iter().any(|q| stderr.contains(q)), "no quantity named: {stderr}");
    // What was recorded up to the failure is kept.
    assert!(dir.path().join("out.partial/follower_1.csv").exists(), "partial data kept");
}

fn read(dir: &Path, name: &str) -> Vec<u8> {
    std::fs::read(dir.join(name)).unwrap_or_else(|e| panic!("{}: {e}", dir.join(name).display()))
}

fn run_paper(dir: &Path, name: &str, extra: &[&str]) -> PathBuf {
    let out = dir.join(name);
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    let mut args = vec!["sim", scenario.to_str().unwrap(), "--out", out.to_str().unwrap(), "-q", "--set", "duration=3"];
    args.extend_from_slice(extra);
    let o = formation(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    out
}

#[test]
fn same_seed_gives_identical_files_and_another_seed_differs() {
    let tmp = tempfile::tempdir().unwrap();
    let a = run_paper(tmp.path(), "a", &[]);
    let b = run_paper(tmp.path(), "b", &[]);
    let c = run_paper(tmp.path(), "c", &["--set", "seed=7"]);
    for f in ["summary.json", "follower_1.csv", "follower_4.csv", "leader.csv"] {
        assert_eq!(read(&a, f), read(&b, f), "{f} differs between two runs of the same seed");
    }
    assert_ne!(read(&a, "follower_1.csv"), read(&c, "follower_1.csv"), "seed 7 drew the same noise");
    assert_eq!(read(&a, "leader.csv"), read(&c, "leader.csv"), "the leader has no noise");
}

#[test]
fn run_folder_has_a_csv_per_follower_and_the_summary_keys() {
    let tmp = tempfile::tempdir().unwrap();
    let a = run_paper(tmp.path(), "a", &["--every", "10"]);
    let csv = String::from_utf8(read(&a, "follower_2.csv")).unwrap();
    let mut lines = csv.lines();
    assert!(lines.next().unwrap().starts_with("t,x,y,theta,v,w,v_hat,w_hat,x_ir"));
    // 3 s at 1 ms = 3001 samples; every 10th is 301 rows.
    assert_eq!(lines.count(), 301);
    let summary: serde_json::Value = serde_json::from_slice(&read(&a, "summary.json")).unwrap();
    for id in ["1", "2", "3", "4"] {
        let m = &summary["followers"][id];
        for key in [
            "formation_rms_last10",
            "formation_final",
            "heading_final",
            "estimator_error_final",
            "vc_peak",
            "torque_tv",
            "torque_peak",
            "rmse_v",
            "rmse_w",
        ] {
            assert!(m[key].is_f64(), "follower {id}: {key} missing in {m}");
        }
    }
}

#[test]
fn every_named_override_takes_effect() {
    let tmp = tempfile::tempdir().unwrap();
    let cases: &[(&str, &str, serde_json::Value)] = &[
        ("noise=false", "noise", false.into()),
        ("filter=kf", "filter", "kf".into()),
        ("filter=none", "filter", "none".into()),
        ("kinematic=conventional", "kinematic", "conventional".into()),
        ("dynamic=smc", "dynamic", "smc".into()),
        ("dynamic=super-twisting", "dynamic", "super-twisting".into()),
        ("fault.time=2", "fault_time", 2.0.into()),
        ("duration=5", "duration", 5.0.into()),
        ("seed=7", "seed", 7.into()),
        ("estimate_init=zero", "estimate_init", "zero".into()),
    ];
    for (i, (set, key, want)) in cases.iter().enumerate() {
        let dir = run_paper(tmp.path(), &format!("o{i}"), &["--set", set, "--no-csv"]);
        let summary: serde_json::Value = serde_json::from_slice(&read(&dir, "summary.json")).unwrap();
        assert_eq!(&summary[key], want, "--set {set}");
    }
}

#[test]
fn noise_free_runs_are_smooth() {
    // Without noise the filtered velocity equals the true one up to the
    // disturbance the filter does not model: RMSE far below the noise level.
    let tmp = tempfile::tempdir().unwrap();
    let dir = run_paper(tmp.path(), "quiet", &["--set", "noise=false", "--no-csv"]);
    let s: serde_json::Value = serde_json::from_slice(&read(&dir, "summary.json")).unwrap();
    let rmse = s["followers"]["1"]["rmse_v"].as_f64().unwrap();
    assert!(rmse < 1e-3, "noise-free linear RMSE {rmse}");
}

#[test]
fn a_communication_delay_beyond_the_limit_or_in_lockstep_is_refused() {
    assert_rejected(&paper_text(), &["--set", "network.delay_steps=1001"], &["network.delay_steps", "more than 1000"]);
    assert_rejected(&paper_text(), &["--set", "network.delay_steps=-1"], &["network.delay_steps"]);
    // A networked lock-step run uses each step's own messages: refused
    // before any process starts (the simulator runs it).
    let dir = tempfile::tempdir().unwrap();
    let scenario = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/paper.toml");
    let out = dir.path().join("out");
    let o = formation(&["launch", scenario, "-q", "--set", "network.delay_steps=1", "--out", out.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("network.delay_steps = 1") && stderr.contains("lock-step"), "{stderr}");
    assert!(!out.exists(), "a run folder was made for a refused launch");
}

/// A delay that makes the leader estimator unstable on the graph is said
/// in one warning line, with the growth per second, and the run still
/// goes; without the delay (or at the paper scenario) nothing is said.
#[test]
fn an_unstable_estimator_under_delay_is_warned_about() {
    let dir = tempfile::tempdir().unwrap();
    let ring = dir.path().join("ring50.toml");
    let o = formation(&[
        "generate",
        "--followers",
        "50",
        "--graph",
        "ring",
        "--chords",
        "10",
        "--seed",
        "1",
        "--out",
        ring.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "generate: {}", String::from_utf8_lossy(&o.stderr));
    let ring = std::fs::read_to_string(&ring).unwrap();
    let run = |text: &str, d: &str| {
        let (out, _dir) = sim_text(text, &["--set", "dt=0.01", "--set", "duration=0.5", "--set", d]);
        assert!(out.status.success(), "sim {d}: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let warned = run(&ring, "network.delay_steps=1");
    let line = warned.lines().find(|l| l.contains("unstable")).unwrap_or_else(|| panic!("no warning: {warned}"));
    // ×1.30 a second: 1.00265 a step (numpy's eigenvalues), 100 steps a second.
    let factor: f64 = line
        .split('×')
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|x| x.parse().ok())
        .unwrap_or_else(|| panic!("no growth factor in: {line}"));
    assert!((1.25..1.35).contains(&factor), "growth ×{factor} a second, expected about 1.30: {line}");
    assert!(line.contains("network.delay_steps = 1") && line.contains("estimator.k"), "{line}");
    let quiet = run(&ring, "network.delay_steps=0");
    assert!(!quiet.contains("unstable"), "no delay, no warning: {quiet}");
    let paper = run(&paper_text(), "network.delay_steps=2");
    assert!(!paper.contains("unstable"), "the paper scenario is stable under delay: {paper}");
}

/// Ctrl-C during `formation sim`: it stops between steps, says where and
/// what it kept, exits 130, and `<out>.partial` holds every step before the
/// stop with a summary.json saying the run is incomplete (it died with the
/// signal, its last rows unwritten and no summary).
#[test]
fn an_interrupted_sim_keeps_every_step_before_the_stop_and_says_so() {
    use std::os::unix::process::CommandExt;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("long");
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    let child = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", scenario.to_str().unwrap(), "--set", "duration=3000", "--every", "100", "-q", "--out"])
        .arg(&out)
        .stderr(std::process::Stdio::piped())
        .process_group(0)
        .spawn()
        .unwrap();
    let leader = tmp.path().join("long.partial").join("leader.csv");
    let t = std::time::Instant::now();
    while std::fs::metadata(&leader).map_or(0, |m| m.len()) == 0 {
        assert!(t.elapsed() < std::time::Duration::from_secs(60), "nothing written within 60 s");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    std::thread::sleep(std::time::Duration::from_millis(1000));
    assert!(Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap().success());
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{stderr}");
    assert!(stderr.contains("interrupted at t = ") && stderr.contains("long.partial holds every step"), "{stderr}");
    let partial = tmp.path().join("long.partial");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(partial.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["complete"], false, "{summary}");
    // Every follower's rows: one per 100th step recorded, through the last whole step.
    for id in 1..=4 {
        let recorded = summary["incomplete"][id.to_string()]["recorded"].as_u64().expect("recorded");
        assert!(recorded >= 1000, "follower {id}: only {recorded} steps in a second");
        let rows = std::fs::read_to_string(partial.join(format!("follower_{id}.csv"))).unwrap().lines().count() as u64;
        assert_eq!(rows - 1, recorded.div_ceil(100), "follower {id}: {rows} lines for {recorded} steps");
    }
}
