//! The Python package (python/, docs/python.md) under pytest: runs from
//! Python equal `formation sim`'s CSVs bit for bit, every `--set` error of
//! tests/it/hostile_inputs.rs raises `ValueError` with the command line's
//! message, a lock-step `launch` folder read from Python equals the
//! simulator, a networked run replayed from Python equals its folder (and
//! on the model's hearing, the simulator), the paper's tables equal
//! `formation paper`'s, and another Python thread runs while a simulation
//! runs (the GIL released). Here, not in `it`: it starts lock-step
//! launches, and holds a lock-step run's share of the cores
//! (`common::cores(Load::Lockstep)`); no verdict of it depends on time.
//!
//! The package must be installed in the Python named by
//! `FORMATION_PYTHON_PACKAGE` (.ci/run: a virtual environment with
//! `pip install ./python pytest`). Without it the test says so and passes,
//! unless `FORMATION_PYTHON_REQUIRED=1` (CI).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::SystemTime;

use crate::common;

/// The Python with `formation` and pytest installed, or None (with a line
/// saying why; a failure under FORMATION_PYTHON_REQUIRED=1).
fn package_python() -> Option<PathBuf> {
    let python = std::env::var_os("FORMATION_PYTHON_PACKAGE").map(PathBuf::from);
    let why = match &python {
        None => "FORMATION_PYTHON_PACKAGE is not set".to_string(),
        Some(p) => match Command::new(p).args(["-c", "import formation, pytest"]).output() {
            Ok(o) if o.status.success() => return python,
            Ok(o) => String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or("").to_string(),
            Err(e) => format!("cannot run {}: {e}", p.display()),
        },
    };
    let line =
        format!("{why} (python -m venv V && V/bin/pip install ./python pytest; FORMATION_PYTHON_PACKAGE=V/bin/python)");
    assert!(std::env::var("FORMATION_PYTHON_REQUIRED").as_deref() != Ok("1"), "{line}");
    common::skipped(&line);
    None
}

/// The newest source file of the crates the package is compiled from.
fn newest_source() -> (SystemTime, PathBuf) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut newest = (SystemTime::UNIX_EPOCH, PathBuf::new());
    let mut dirs: Vec<PathBuf> = [
        "python/src",
        "report/src",
        "replay/src",
        "recorder/src",
        "exit/src",
        "protocol/src",
        "sim/src",
        "record/src",
        "scenario/src",
        "control/src",
        "plant/src",
        "leader/src",
    ]
    .iter()
    .map(|d| root.join(d))
    .collect();
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).expect("source folder").flatten() {
            let path = entry.path();
            if path.is_dir() {
                dirs.push(path);
            } else if let Ok(m) = entry.metadata().and_then(|m| m.modified()) {
                if m > newest.0 {
                    newest = (m, path);
                }
            }
        }
    }
    newest
}

#[test]
fn the_python_package_equals_the_command_line_under_pytest() {
    let _cores = common::cores(common::Load::Lockstep);
    let Some(python) = package_python() else { return };
    // The package is built by pip, not by cargo: one older than its
    // sources would test code that is no longer there.
    let o = Command::new(&python)
        .args(["-c", "import formation._formation as m; print(m.__file__)"])
        .output()
        .expect("python");
    let module = PathBuf::from(String::from_utf8_lossy(&o.stdout).trim());
    let built = std::fs::metadata(&module).and_then(|m| m.modified()).expect("the installed module");
    let (newest, source) = newest_source();
    assert!(
        built >= newest,
        "the installed formation package ({}) is older than {}: pip install ./python again",
        module.display(),
        source.display()
    );
    // Two launches (python/tests: a lock-step run, then one with an
    // outage): the first takes these 6 ports, the second the next 6.
    let ports = common::Ports::free(2 * common::LAUNCH_PORTS);
    let base = ports.release();
    let out = Command::new(&python)
        .args(["-m", "pytest", "-q", "-s", "-p", "no:cacheprovider"])
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("python/tests"))
        .env("FORMATION_BIN", env!("CARGO_BIN_EXE_formation"))
        .env("FORMATION_BASE_PORT", base.to_string())
        .output()
        .expect("pytest");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    eprintln!("{text}");
    assert!(out.status.success(), "pytest python/tests failed ({}):\n{text}", out.status);
    let passed = text.lines().rev().find(|l| l.contains(" passed")).unwrap_or("").to_string();
    assert!(!passed.contains(" skipped"), "pytest python/tests skipped tests: {passed}\n{text}");
}
