//! `formation generate`: every graph kind gives a scenario `formation sim`
//! runs; a disconnected request is refused naming the unreachable
//! followers; the file is a function of the request and its seed.

use std::path::Path;
use std::process::Command;

fn formation(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_formation")).args(args).output().expect("formation")
}

fn generate(out: &Path, args: &[&str]) -> std::process::Output {
    let o = out.display().to_string();
    let mut all = vec!["generate", "--out", &o, "--force"];
    all.extend_from_slice(args);
    formation(&all)
}

#[test]
fn every_graph_kind_gives_a_scenario_that_sim_runs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    for (kind, extra, edges) in [
        ("ring", &["--chords", "4"][..], 16),
        ("grid", &[][..], 17),
        ("random-geometric", &[][..], 0),
        ("complete", &[][..], 66),
        ("line", &["--leader-links", "2"][..], 11),
    ] {
        let file = tmp.path().join(format!("{kind}.toml"));
        let mut args = vec!["--followers", "12", "--graph", kind];
        args.extend_from_slice(extra);
        let o = generate(&file, &args);
        let said = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "{kind}: {}", String::from_utf8_lossy(&o.stderr));
        assert!(said.contains("12 followers") && said.contains("λ_min(H)"), "{kind}: {said}");
        if edges > 0 {
            assert!(said.contains(&format!("with {edges} edges")), "{kind}: expected {edges} edges: {said}");
        }
        let out = tmp.path().join(format!("{kind}-run"));
        let o = formation(&[
            "sim",
            &file.display().to_string(),
            "-q",
            "--set",
            "duration=1",
            "--out",
            &out.display().to_string(),
        ]);
        assert!(o.status.success(), "{kind}: formation sim: {}", String::from_utf8_lossy(&o.stderr));
        let summary: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary")).expect("json");
        let followers = summary["followers"].as_object().map_or(0, |m| m.len());
        assert_eq!(followers, 12, "{kind}: the run has {followers} followers");
    }
}

#[test]
fn a_disconnected_request_is_refused_naming_the_unreachable_followers() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let file = tmp.path().join("rg.toml");
    let o = generate(&file, &["--followers", "6", "--graph", "random-geometric", "--radius", "0.01"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("are not connected") && err.lines().count() == 1, "{err}");
    let unreachable = (1..=6).filter(|i| err.contains(&i.to_string())).count();
    assert_eq!(unreachable, 5, "5 of 6 followers cannot be reached with no edges: {err}");
    assert!(!file.exists(), "a refused request wrote {}", file.display());
    for (bad, says) in [
        (&["--followers", "0", "--graph", "ring"][..], "--followers"),
        (&["--followers", "5", "--graph", "line", "--chords", "2"][..], "--chords"),
        (&["--followers", "5", "--graph", "ring", "--leader-links", "9"][..], "--leader-links"),
        (&["--followers", "4", "--graph", "ring", "--chords", "9"][..], "--chords"),
        (&["--followers", "5", "--graph", "star"][..], "star"),
    ] {
        let o = generate(&file, bad);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{bad:?}: {err}");
        assert!(err.contains(says), "{bad:?}: {err}");
    }
}

#[test]
fn the_file_is_a_function_of_the_request_and_seed() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (a, b, c) = (tmp.path().join("a.toml"), tmp.path().join("b.toml"), tmp.path().join("c.toml"));
    let req = ["--followers", "40", "--graph", "random-geometric", "--leader-links", "3", "--seed", "5"];
    assert!(generate(&a, &req).status.success());
    assert!(generate(&b, &req).status.success());
    let mut other = req.to_vec();
    other[7] = "6";
    assert!(generate(&c, &other).status.success());
    let read = |p: &Path| std::fs::read(p).expect("file");
    assert!(read(&a) == read(&b), "the same request and seed gave two different files");
    assert!(read(&a) != read(&c), "seeds 5 and 6 gave the same file");
    // An existing file is kept without --force.
    let o = formation(&["generate", "--followers", "3", "--graph", "line", "--out", &a.display().to_string()]);
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(read(&a) == read(&b), "generate replaced a file without --force");
}
