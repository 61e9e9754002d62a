//! `formation verify`: the networked formation at nominal timing, against
//! its model. Each study is a real-time run (the lab's namespaces, or
//! `formation launch` on this host) of a fault the model knows, run one at
//! a time with the machine to itself, and `formation sim` of the same
//! scenario with the fault as the run performed it; its figures beside the
//! model's, within the tolerance the model promises.
//!
//! The test command runs the same runs, but a test's verdict may not depend
//! on the host's speed: there a run whose own record shows it did not keep
//! the period is "not judged". Here too a study is judged only when its run
//! kept the period ([`Period::kept`]: at most 1.25 % of its source-steps
//! late), so that a figure off the model is the code's doing; the table
//! says for each run how late it was. Exit status 0 when every judged
//! figure is within its tolerance, 1 when one is not, 2 for bad arguments.
//!
//! The table goes to the terminal and, one row per figure, to
//! `OUT/verify.csv` and `OUT/verify.json`; each study's run and model
//! folders stay in `OUT/<study>/`.

use std::path::{Path, PathBuf};
use std::process::Command;

use formation_exit::Error;
use formation_recorder::period::{Period, KEPT_LATE_SHARE};

#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct VerifyArgs {
    /// The scenario every study varies (the paper's).
    #[cfg_attr(feature = "clap", arg(long, default_value = "scenarios/paper.toml"))]
    pub scenario: PathBuf,
    /// Where the table (verify.csv, verify.json) and each study's run and
    /// model folders go.
    #[cfg_attr(feature = "clap", arg(long, default_value = "runs/verify", value_name = "DIR"))]
    pub out: PathBuf,
    /// Only the studies whose name contains one of these words
    /// (comma-separated: `--only lab-join,ring`).
    #[cfg_attr(feature = "clap", arg(long, value_name = "WORDS"))]
    pub only: Option<String>,
    /// List the studies, what each runs and judges, and exit.
    #[cfg_attr(feature = "clap", arg(long))]
    pub list: bool,
}

/// How a study's run is made.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    /// `formation lab`: every node in a network namespace (root, nft).
    Lab,
    /// `formation launch` on this host, with `args`.
    Launch,
    /// `formation launch` of a generated ring of N followers (N/5 chords).
    Ring(u32),
}

/// A figure a study compares, and how far it may be from the model's.
#[derive(Clone, Copy, Debug)]
enum Allowed {
    /// Within this share of the model's value.
    Rel(f64),
    /// Within this much of it, in its unit.
    Abs(f64),
}

/// One figure of a run beside the model's.
#[derive(Clone, Debug)]
struct Figure {
    what: String,
    run: f64,
    model: f64,
    allowed: Allowed,
}

impl Figure {
    fn within(&self) -> bool {
        let off = (self.run - self.model).abs();
        match self.allowed {
            Allowed::Rel(r) => off <= r * self.model.abs(),
            Allowed::Abs(a) => off <= a,
        }
    }

    fn allowed(&self) -> String {
        match self.allowed {
            Allowed::Rel(r) => format!("±{:.0} %", 100.0 * r),
            Allowed::Abs(a) => format!("±{a}"),
        }
    }
}

/// What a study's run left: its folder's files, parsed.
struct Run {
    dir: PathBuf,
    summary: serde_json::Value,
    network: serde_json::Value,
    lab: serde_json::Value,
}

/// One study.
struct Study {
    name: &'static str,
    what: &'static str,
    kind: Kind,
    /// `--set`s of the run and of its model.
    sets: &'static [&'static str],
    /// The lab's or launch's own arguments.
    args: &'static [&'static str],
    /// The model's further `--set`s, from what the run performed.
    model: fn(&Run) -> Result<Vec<String>, String>,
    /// The figures compared.
    figures: fn(&Run, &serde_json::Value) -> Vec<Figure>,
}

const LAB20: &[&str] = &["timing=realtime", "duration=20", "network.delay_steps=5"];
const LAB12: &[&str] = &["timing=realtime", "duration=12", "network.delay_steps=5"];

fn num(v: &serde_json::Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// `metrics` of each of `ids` in summary.json, the run's beside the model's.
fn followers(run: &Run, model: &serde_json::Value, ids: &[u32], metrics: &[&str], allowed: Allowed) -> Vec<Figure> {
    let mut f = Vec::new();
    for id in ids {
        for m in metrics {
            let (a, b) = (&run.summary["followers"][id.to_string()][m], &model["followers"][id.to_string()][m]);
            f.push(Figure { what: format!("follower {id} {m}"), run: num(a), model: num(b), allowed });
        }
    }
    f
}

const BOTH: [&str; 2] = ["formation_rms_last10", "torque_tv"];

fn none(_: &Run) -> Result<Vec<String>, String> {
    Ok(Vec::new())
}

fn studies() -> Vec<Study> {
    let mut all = lab_studies();
    all.extend(membership_studies());
    all.extend(host_studies());
    all
}

/// The lab's faults of the network, each run in network namespaces (root).
fn lab_studies() -> Vec<Study> {
    vec![
        Study {
            name: "lab-free",
            what: "fault-free, clients through a router, 20 s at 1 kHz, 5 steps of delay",
            kind: Kind::Lab,
            sets: LAB20,
            args: &[],
            model: none,
            figures: |r, m| followers(r, m, &[1, 2, 3, 4], &BOTH, Allowed::Rel(0.10)),
        },
        Study {
            name: "lab-cut",
            what: "follower 3's link down 8-11 s (the paper's consensus rejoin)",
            kind: Kind::Lab,
            sets: &["timing=realtime", "duration=20", "network.delay_steps=5", "faults+={node=3, from=8, to=11}"],
            args: &["--mode", "client"],
            model: none,
            figures: |r, m| {
                // (Its recovery time is not defined with 5 steps of delay: the
                // estimator error stays above the 0.02 m it is measured at.)
                let k = "peak_estimator_error";
                let (a, b) = (&r.summary["faults"][0]["followers"]["3"][k], &m["faults"][0]["followers"]["3"][k]);
                let peak =
                    Figure { what: format!("follower 3 {k}"), run: num(a), model: num(b), allowed: Allowed::Rel(0.25) };
                let mut f = vec![peak];
                f.extend(followers(r, m, &[1, 2, 3, 4], &["formation_rms_last10"], Allowed::Rel(0.10)));
                f
            },
        },
        Study {
            name: "lab-clock",
            what: "follower 3's wall clock 1 s behind the leader's (libfaketime), 10 s",
            kind: Kind::Lab,
            sets: &["timing=realtime", "duration=10", "network.delay_steps=5"],
            args: &["--clock", "3=-1"],
            model: none,
            figures: |r, m| {
                let mut f = followers(r, m, &[1, 2, 3, 4], &BOTH, Allowed::Rel(0.10));
                // Against the unshifted followers' estimates: a step of the
                // host's own wall clock during the run (this VM's moved by
                // 50–150 ms in some runs) moves every node's alike.
                let offset = |id: &str| num(&r.network["nodes"][id]["clock"]["offset_ms"]);
                let others = (offset("1") + offset("2") + offset("4")) / 3.0;
                f.push(Figure {
                    what: "follower 3's leader clock less the others', ms".into(),
                    run: offset("3") - others,
                    model: 1000.0,
                    allowed: Allowed::Abs(1.0),
                });
                f
            },
        },
        Study {
            name: "lab-sites",
            what: "two sites (A: leader, monitor, 1, 2; B: 3, 4) cut apart 5-8 s, 12 s",
            kind: Kind::Lab,
            sets: LAB12,
            args: &["--sites", "A=leader,monitor,1,2;B=3,4", "--cut", "A:B@5:3"],
            model: |r| {
                let e = r.lab["events"].as_array().ok_or("lab.json has no events")?;
                let (from, to) = (e.first().map(|x| num(&x["performed_s"])), e.get(1).map(|x| num(&x["performed_s"])));
                let (Some(from), Some(to)) = (from, to) else { return Err("lab.json: the cut and the join".into()) };
                Ok(["[1, 3]", "[2, 4]"]
                    .iter()
                    .map(|l| format!("faults+={{link={l}, from={from:.3}, to={to:.3}}}"))
                    .collect())
            },
            figures: |r, m| followers(r, m, &[1, 2, 3, 4], &["formation_rms_last10"], Allowed::Rel(0.25)),
        },
    ]
}

/// The lab's changes of membership: a join, a leave, a quorum start, a
/// handover (root).
fn membership_studies() -> Vec<Study> {
    vec![
        Study {
            name: "lab-join",
            what: "follower 3 absent at a quorum start, its agent started at 8 s",
            kind: Kind::Lab,
            sets: LAB20,
            args: &["--quorum", "3", "--quorum-wait", "1", "--absent", "3", "--join", "3@8"],
            model: |r| {
                let t = r.network["joined"][0]["t_s"].as_f64().ok_or("network.json names no join")?;
                Ok(vec![format!("faults+={{node=3, from=0, to={t}, join=true}}")])
            },
            figures: |r, m| {
                let mut f = followers(r, m, &[1, 2, 4], &BOTH, Allowed::Rel(0.10));
                f.extend(followers(r, m, &[3], &["formation_rms_last10"], Allowed::Rel(0.10)));
                f
            },
        },
        Study {
            name: "lab-leave",
            what: "follower 2 leaves for good at 5 s of 12",
            kind: Kind::Lab,
            sets: LAB12,
            args: &["--leave", "2@5"],
            model: |_| Ok(vec!["faults+={node=2, from=5}".into()]),
            figures: |r, m| followers(r, m, &[1, 3, 4], &BOTH, Allowed::Rel(0.10)),
        },
        Study {
            name: "lab-quorum",
            what: "a quorum start without follower 3 (absent), 12 s",
            kind: Kind::Lab,
            sets: LAB12,
            args: &["--quorum", "3", "--quorum-wait", "1", "--absent", "3"],
            model: |_| Ok(vec!["faults+={node=3, from=0}".into()]),
            figures: |r, m| followers(r, m, &[1, 2, 4], &BOTH, Allowed::Rel(0.10)),
        },
        Study {
            name: "lab-handover",
            what: "the leader killed at 10 s of 30, a standby takes over",
            kind: Kind::Lab,
            sets: &["timing=realtime", "duration=30", "network.delay_steps=5"],
            args: &["--kill-leader", "10"],
            model: |r| {
                let h = &r.network["handovers"][0];
                let (heard, at) = (h["heard_step"].as_u64(), h["step"].as_u64());
                let (Some(heard), Some(at)) = (heard, at) else { return Err("network.json names no handover".into()) };
                let dt = 0.001;
                Ok(vec![format!("faults+={{node=0, from={}, to={}}}", (heard + 1) as f64 * dt, at as f64 * dt)])
            },
            figures: |r, m| followers(r, m, &[1, 2, 3, 4], &BOTH, Allowed::Rel(0.10)),
        },
    ]
}

/// Runs on this host: a launch, and the rings of 50 and 100 agents.
fn host_studies() -> Vec<Study> {
    vec![
        Study {
            name: "launch-delay",
            what: "launch on this host, 100 Hz at time scale 2, 2 steps of delay, 20 s",
            kind: Kind::Launch,
            sets: &[
                "timing=realtime",
                "dt=0.01",
                "duration=20",
                "network.silence_timeout=0.2",
                "network.delay_steps=2",
            ],
            args: &["--time-scale", "2"],
            model: none,
            figures: |r, m| {
                let all = ["formation_rms_last10", "formation_final", "estimator_error_final", "torque_tv"];
                followers(r, m, &[1, 2, 3, 4], &all, Allowed::Rel(0.10))
            },
        },
        Study {
            name: "ring-50",
            what: "50 agents on a ring with 10 chords, 100 Hz, a step of delay, k_i = 0.5, 10 s",
            kind: Kind::Ring(50),
            sets: &["timing=realtime", "dt=0.01", "duration=10", "network.delay_steps=1", "estimator.k=[0.5,0.5,0.5]"],
            args: &[],
            model: none,
            figures: |r, m| ring_figures(r, m, 0.10),
        },
        Study {
            name: "ring-100",
            what: "100 agents on a ring with 20 chords, 100 Hz, a step of delay, k_i = 0.2, 10 s",
            kind: Kind::Ring(100),
            sets: &["timing=realtime", "dt=0.01", "duration=10", "network.delay_steps=1", "estimator.k=[0.2,0.2,0.2]"],
            args: &[],
            model: none,
            figures: |r, m| ring_figures(r, m, 0.03),
        },
    ]
}

/// A ring's figures: the median of the followers' torque variation over
/// the model's, and the worst formation error over the last 10 s.
fn ring_figures(run: &Run, model: &serde_json::Value, allowed: f64) -> Vec<Figure> {
    let ids: Vec<String> = model["followers"].as_object().map(|f| f.keys().cloned().collect()).unwrap_or_default();
    let ratio = |id: &String, m: &str| num(&run.summary["followers"][id][m]) / num(&model["followers"][id][m]);
    let mut tv: Vec<f64> = ids.iter().map(|id| ratio(id, "torque_tv")).collect();
    tv.sort_by(f64::total_cmp);
    let median = tv.get(tv.len() / 2).copied().unwrap_or(f64::NAN);
    let worst = ids.iter().map(|id| ratio(id, "formation_rms_last10")).fold(f64::NAN, f64::max);
    vec![
        Figure {
            what: "median torque_tv, run over model".into(),
            run: median,
            model: 1.0,
            allowed: Allowed::Rel(allowed),
        },
        Figure {
            what: "worst formation_rms_last10, run over model".into(),
            run: worst,
            model: 1.0,
            allowed: Allowed::Rel(0.10),
        },
    ]
}

/// A study's outcome, as the table says it.
struct Outcome {
    study: &'static str,
    period: Option<Period>,
    /// Why its figures were not judged (None: judged).
    not_judged: Option<String>,
    figures: Vec<Figure>,
}

impl Outcome {
    fn failed(&self) -> bool {
        self.not_judged.is_none() && self.figures.iter().any(|f| !f.within())
    }
}

pub fn run(a: &VerifyArgs) -> Result<(), Error> {
    let all = studies();
    if a.list {
        for s in &all {
            let kind = match s.kind {
                Kind::Lab => "lab (root)".to_string(),
                Kind::Launch => "launch".to_string(),
                Kind::Ring(n) => format!("launch, {n} agents"),
            };
            println!("{:<13} {:<18} {}", s.name, kind, s.what);
        }
        return Ok(());
    }
    let words: Vec<&str> =
        a.only.as_deref().map(|w| w.split(',').filter(|w| !w.is_empty()).collect()).unwrap_or_default();
    let chosen: Vec<&Study> =
        all.iter().filter(|s| words.is_empty() || words.iter().any(|w| s.name.contains(w))).collect();
    if chosen.is_empty() {
        let names: Vec<&str> = all.iter().map(|s| s.name).collect();
        return Err(Error::Input(format!(
            "--only {}: no study by that name ({})",
            a.only.as_deref().unwrap_or(""),
            names.join(", ")
        )));
    }
    if !a.scenario.is_file() {
        return Err(Error::Input(format!("--scenario {}: no such file", a.scenario.display())));
    }
    std::fs::create_dir_all(&a.out).map_err(|e| Error::Run(format!("{}: {e}", a.out.display())))?;
    let exe = std::env::current_exe().map_err(|e| Error::Run(format!("locating this executable: {e}")))?;
    let lab = formation_launch::lab::netns::root_lab().map_err(|e| e.0);
    let mut outcomes = Vec::new();
    for (i, s) in chosen.iter().enumerate() {
        eprintln!("verify: {}/{} {}: {}", i + 1, chosen.len(), s.name, s.what);
        let outcome = match (s.kind, &lab) {
            (Kind::Lab, Err(why)) => {
                Outcome { study: s.name, period: None, not_judged: Some(format!("skipped: {why}")), figures: vec![] }
            }
            _ => study(&exe, a, s).unwrap_or_else(|why| Outcome {
                study: s.name,
                period: None,
                not_judged: Some(format!("failed: {why}")),
                figures: vec![],
            }),
        };
        eprintln!("verify: {}: {}", s.name, verdict(&outcome));
        outcomes.push(outcome);
    }
    print!("{}", table(&outcomes));
    write_files(&a.out, &outcomes)?;
    println!("written: {} and {}", a.out.join("verify.csv").display(), a.out.join("verify.json").display());
    let failed: Vec<&str> = outcomes.iter().filter(|o| o.failed()).map(|o| o.study).collect();
    let broken: Vec<&str> = outcomes
        .iter()
        .filter(|o| o.not_judged.as_deref().is_some_and(|w| w.starts_with("failed")))
        .map(|o| o.study)
        .collect();
    if !failed.is_empty() || !broken.is_empty() {
        return Err(Error::Run(format!(
            "verify: {} off the model at nominal timing{}",
            if failed.is_empty() { "no study".to_string() } else { failed.join(", ") },
            if broken.is_empty() { String::new() } else { format!("; {} did not run to the end", broken.join(", ")) }
        )));
    }
    Ok(())
}

/// One study: its run, its model, its figures.
fn study(exe: &Path, a: &VerifyArgs, s: &Study) -> Result<Outcome, String> {
    let dir = a.out.join(s.name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let scenario = match s.kind {
        Kind::Ring(n) => crate::floor::ring_file(&dir, n).map_err(|e| e.to_string())?,
        _ => a.scenario.clone(),
    };
    let run_dir = dir.join("run");
    let mut c = Command::new(exe);
    match s.kind {
        Kind::Lab => {
            c.arg("lab").arg(&scenario);
        }
        // The launch claims free ports of its own (formation_launch::ports).
        Kind::Launch | Kind::Ring(_) => {
            c.arg("launch").arg(&scenario);
        }
    }
    c.args(["-q", "--run", &format!("verify-{}", s.name), "--out"]).arg(&run_dir);
    for set in s.sets {
        c.args(["--set", set]);
    }
    c.args(s.args);
    // What the nodes say goes to the study's folder, not the table's terminal.
    let log = dir.join("run.log");
    let file = std::fs::File::create(&log).map_err(|e| format!("{}: {e}", log.display()))?;
    c.stdout(std::process::Stdio::null()).stderr(file);
    let status = c.status().map_err(|e| format!("starting {}: {e}", exe.display()))?;
    // 3: degraded, said in network.json's health; the figures say how far.
    if !(status.success() || status.code() == Some(3)) {
        return Err(format!("the run ended {status} (what it said: {})", log.display()));
    }
    let run = Run {
        summary: read_json(&run_dir.join("summary.json"))?,
        network: read_json(&run_dir.join("network.json"))?,
        lab: if s.kind == Kind::Lab { read_json(&run_dir.join("lab.json"))? } else { serde_json::Value::Null },
        dir: run_dir.clone(),
    };
    let model_dir = dir.join("model");
    let mut m = Command::new(exe);
    m.arg("sim").arg(&scenario).args(["-q", "--no-csv", "--out"]).arg(&model_dir);
    for set in s.sets.iter().map(|x| x.to_string()).chain((s.model)(&run)?) {
        m.args(["--set", &set]);
    }
    let o = m.output().map_err(|e| format!("formation sim: {e}"))?;
    if !o.status.success() {
        return Err(format!("formation sim: {}", String::from_utf8_lossy(&o.stderr).trim()));
    }
    let model = read_json(&model_dir.join("summary.json"))?;
    let period = Period::of(&run.network);
    let complete = run.network["complete"] == true;
    let not_judged = if !complete {
        Some(format!("the record is not complete ({}; {})", run.network["ending"], run.dir.display()))
    } else {
        period.why_not_judged()
    };
    Ok(Outcome { study: s.name, period: Some(period), not_judged, figures: (s.figures)(&run, &model) })
}

/// A run folder's JSON file, parsed; the error names the file.
fn read_json(p: &Path) -> Result<serde_json::Value, String> {
    let text = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("{}: {e}", p.display()))
}

fn verdict(o: &Outcome) -> String {
    match &o.not_judged {
        Some(why) => format!("not judged: {why}"),
        None if o.failed() => {
            let off: Vec<String> = o.figures.iter().filter(|f| !f.within()).map(|f| f.what.clone()).collect();
            format!("OFF THE MODEL: {}", off.join(", "))
        }
        None => format!("judged, {} figures within the model's tolerance", o.figures.len()),
    }
}

/// The table: a line per study, a line per figure under it.
fn table(outcomes: &[Outcome]) -> String {
    let mut t = format!(
        "\n{:<13} {:>10}  {:<46} {:>11} {:>11} {:>7} {:>7}  verdict\n",
        "study", "late", "figure", "run", "model", "ratio", "allowed"
    );
    for o in outcomes {
        let late = o.period.map_or("–".to_string(), |p| format!("{:.2} %", 100.0 * p.late_share()));
        t += &format!("{:<13} {late:>10}  {}\n", o.study, verdict(o));
        for f in &o.figures {
            let mark = match (&o.not_judged, f.within()) {
                (Some(_), _) => "(not judged)",
                (None, true) => "within",
                (None, false) => "OFF",
            };
            t += &format!(
                "{:<13} {:>10}  {:<46} {:>11.5} {:>11.5} {:>7.3} {:>7}  {mark}\n",
                "",
                "",
                f.what,
                f.run,
                f.model,
                f.run / f.model,
                f.allowed()
            );
        }
    }
    t += &format!(
        "\nlate: the run's source-steps that used a message older than the modelled delay; a run is judged when at \
         most {:.2} % were\n",
        100.0 * KEPT_LATE_SHARE
    );
    t
}

/// verify.csv and verify.json: one row per figure (a study without
/// figures: one row saying why).
fn write_files(out: &Path, outcomes: &[Outcome]) -> Result<(), Error> {
    let mut csv = String::from("study,late_share,judged,why_not,figure,run,model,allowed,within\n");
    let mut rows = Vec::new();
    for o in outcomes {
        let late = o.period.map(|p| p.late_share());
        let why = o.not_judged.clone().unwrap_or_default().replace(',', ";");
        let late_s = late.map_or(String::new(), |l| format!("{l:.6}"));
        if o.figures.is_empty() {
            csv += &format!("{},{late_s},false,{why},,,,,\n", o.study);
        }
        for f in &o.figures {
            let judged = o.not_judged.is_none();
            csv += &format!(
                "{},{late_s},{judged},{why},{},{},{},{},{}\n",
                o.study,
                f.what,
                f.run,
                f.model,
                f.allowed(),
                judged && f.within()
            );
        }
        rows.push(serde_json::json!({
            "study": o.study,
            "late_source_steps": o.period.map(|p| p.late),
            "source_steps": o.period.map(|p| p.used),
            "late_share": late,
            "judged": o.not_judged.is_none(),
            "why_not_judged": o.not_judged,
            "figures": o.figures.iter().map(|f| serde_json::json!({
                "figure": f.what, "run": f.run, "model": f.model, "allowed": f.allowed(), "within": f.within(),
            })).collect::<Vec<_>>(),
        }));
    }
    let json = serde_json::json!({ "kept_late_share": KEPT_LATE_SHARE, "studies": rows });
    let write = |name: &str, text: String| {
        std::fs::write(out.join(name), text).map_err(|e| Error::Run(format!("{}: {e}", out.join(name).display())))
    };
    write("verify.csv", csv)?;
    write("verify.json", serde_json::to_string_pretty(&json).unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_are_within_their_tolerance_or_not() {
        let f = |run, allowed| Figure { what: "x".into(), run, model: 2.0, allowed };
        assert!(f(2.19, Allowed::Rel(0.10)).within());
        assert!(!f(2.21, Allowed::Rel(0.10)).within());
        assert!(f(2.9, Allowed::Abs(1.0)).within());
        assert!(!f(f64::NAN, Allowed::Rel(0.10)).within(), "a figure that is not there is not within");
    }

    #[test]
    fn every_study_has_a_unique_name_and_a_bad_only_is_refused() {
        let all = studies();
        let mut names: Vec<&str> = all.iter().map(|s| s.name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), all.len());
        let a = VerifyArgs {
            scenario: "scenarios/paper.toml".into(),
            out: "/nonexistent".into(),
            only: Some("nosuch".into()),
            list: false,
        };
        let e = run(&a).expect_err("refused");
        assert!(e.to_string().contains("--only nosuch: no study by that name"), "{e}");
    }

    #[test]
    fn a_study_not_judged_does_not_fail_and_a_judged_figure_off_does() {
        let fig = Figure { what: "x".into(), run: 3.0, model: 2.0, allowed: Allowed::Rel(0.10) };
        let mut o = Outcome { study: "s", period: None, not_judged: Some("3 % late".into()), figures: vec![fig] };
        assert!(!o.failed());
        o.not_judged = None;
        assert!(o.failed());
        assert!(verdict(&o).starts_with("OFF THE MODEL"), "{}", verdict(&o));
    }
}
