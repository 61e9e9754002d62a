//! A replay set against its run (`formation replay RUN_DIR`): the run
//! re-computed from its hearing record into a folder of its own, compared
//! byte for byte with the run's CSVs and `summary.json`, and what the
//! comparison found, with its report.

use formation_exit::Error;

use crate::replay::{self, Loaded};

/// What the comparison of a replay with its run found.
#[derive(Debug, PartialEq)]
pub enum Comparison {
    /// The CSVs and summary.json byte for byte.
    Identical,
    /// Whole files that differ (and which of the run's files are damaged
    /// besides).
    Differs(Vec<String>),
    /// The run's files missing, cut short or not JSON (which).
    Damaged(Vec<String>),
}

/// Replays a run and compares: the verdict, and the report. `progress`
/// is told each step replayed.
pub fn check(
    loaded: &Loaded,
    out: Option<&std::path::Path>,
    progress: &mut dyn FnMut(u64),
) -> Result<(Comparison, String), Error> {
    let tmp;
    let dir = match out {
        Some(d) => {
            refuse_out_over_the_run(&loaded.dir, d)?;
            d.to_path_buf()
        }
        None => {
            tmp = tempfile::tempdir().map_err(|e| Error::Run(format!("a temporary folder: {e}")))?;
            tmp.path().join("replay")
        }
    };
    let began = std::time::Instant::now();
    let s = &loaded.scenario;
    let problems = replay::replay_to_folder_with(loaded, replay::HearingSource::Recorded, &dir, progress)?;
    let secs = began.elapsed().as_secs_f64();
    let diffs = replay::compare(&loaded.dir, &dir, &loaded.scenario);
    let rows: u64 = loaded.record.followers.iter().map(|f| f.steps()).sum();
    let mut text = format!(
        "replayed {} ({} followers, {rows} follower-steps of {}) in {secs:.2} s\n",
        loaded.dir.display(),
        s.followers.len(),
        (s.steps() + 1) * s.followers.len() as u64
    );
    for f in &loaded.record.followers {
        for r in &f.resumes {
            text +=
                &format!("  follower {}: a new process from step {} (t = {:.3} s)\n", f.id, r.k, r.k as f64 * s.dt_s);
        }
    }
    for p in &problems {
        text += &format!("  follower {}, step {}: {}\n", p.follower, p.k, p.what);
    }
    if diffs.is_empty() {
        text += "the CSVs and summary.json are byte-identical to the run's\n";
    } else {
        text += "first differences:\n";
        for d in &diffs {
            text += &format!("  {d}\n");
        }
    }
    if let Some(o) = out {
        text += &format!("replay written to {}\n", o.display());
    }
    let damaged: Vec<String> = diffs.iter().filter_map(|d| d.damage.clone()).collect();
    // Damage explains only the files it is in: a whole file that differs
    // besides still blames the program.
    let verdict = match (diffs.is_empty(), damaged.len() == diffs.len()) {
        (true, _) => Comparison::Identical,
        (false, true) => Comparison::Damaged(damaged),
        (false, false) => Comparison::Differs(damaged),
    };
    Ok((verdict, text))
}

/// `--out` may not be the run's folder, in it, or hold it: the replay
/// would replace the record it is compared with.
fn refuse_out_over_the_run(run: &std::path::Path, out: &std::path::Path) -> Result<(), Error> {
    let resolved = |p: &std::path::Path| -> std::path::PathBuf {
        // The deepest part that exists, resolved (links, `..`), and the rest.
        let abs = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
        let mut head = abs.clone();
        let mut tail = Vec::new();
        while !head.exists() {
            match (head.file_name().map(ToOwned::to_owned), head.parent()) {
                (Some(name), Some(parent)) => {
                    tail.push(name);
                    head = parent.to_path_buf();
                }
                _ => return abs,
            }
        }
        let mut full = head.canonicalize().unwrap_or(head);
        full.extend(tail.iter().rev());
        full
    };
    let (r, o) = (resolved(run), resolved(out));
    if o.starts_with(&r) || r.starts_with(&o) {
        return Err(Error::Input(format!(
            "--out {}: the replay would replace the run {} it is compared with; choose a folder outside it",
            out.display(),
            run.display()
        )));
    }
    Ok(())
}
