//! Any run folder read back into the columns a run in memory has
//! ([`crate::memory`]): `formation sim`'s, or a networked run's with its
//! `network.json`.

use std::path::Path;

use formation_record::{read_columns, FOLLOWER_HEADER, LEADER_HEADER};

use crate::memory::Columns;

/// A run folder as read.
#[derive(Debug)]
pub struct FolderRun {
    /// (follower id, its columns), by id.
    pub followers: Vec<(u32, Columns)>,
    pub leader: Columns,
    /// summary.json's text.
    pub summary: String,
    /// network.json's text, where the run was networked.
    pub network: Option<String>,
}

/// Reads the run folder `dir`: every `follower_<id>.csv`, `leader.csv`,
/// `summary.json` and, where present, `network.json`. An error is one line
/// naming the file (and the line and column of a bad field).
pub fn read(dir: &Path) -> Result<FolderRun, String> {
    if !dir.is_dir() {
        return Err(format!("{}: there is no run folder here", dir.display()));
    }
    let text = |name: &str| std::fs::read_to_string(dir.join(name));
    let summary =
        text("summary.json").map_err(|e| format!("{}: not a run folder (summary.json: {e})", dir.display()))?;
    let network = match text("network.json") {
        Ok(t) => Some(t),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(format!("{}: {e}", dir.join("network.json").display())),
    };
    let mut ids = Vec::new();
    let entries = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let id = name.to_str().and_then(|n| n.strip_prefix("follower_")?.strip_suffix(".csv")?.parse::<u32>().ok());
        ids.extend(id);
    }
    ids.sort_unstable();
    let read = |name: String, header: &'static str| -> Result<Columns, String> {
        let mut columns = Columns::with_header(header, 0);
        columns.data = read_columns(&dir.join(name), &columns.names).map_err(|e| e.to_string())?;
        Ok(columns)
    };
    let followers = ids
        .into_iter()
        .map(|id| Ok((id, read(format!("follower_{id}.csv"), FOLLOWER_HEADER)?)))
        .collect::<Result<Vec<_>, String>>()?;
    let leader = if dir.join("leader.csv").exists() {
        read("leader.csv".into(), LEADER_HEADER)?
    } else {
        Columns::with_header(LEADER_HEADER, 0)
    };
    Ok(FolderRun { followers, leader, summary, network })
}

/// The run at `dir` re-computed from what each follower heard
/// (`hearing.bin`, as `formation replay`), or with `model` from what the
/// model says it would have heard; read back as a [`FolderRun`], with what
/// could not be re-computed, one line each.
pub fn replay(dir: &Path, model: bool) -> Result<(FolderRun, Vec<String>), String> {
    use formation_replay::replay::{load, replay_to_folder_with, HearingSource};
    let loaded = load(dir).map_err(|e| e.to_string())?;
    let tmp = tempfile::tempdir().map_err(|e| format!("a temporary folder: {e}"))?;
    let out = tmp.path().join("replay");
    let hearing = if model { HearingSource::Model } else { HearingSource::Recorded };
    let problems = replay_to_folder_with(&loaded, hearing, &out, &mut |_| {}).map_err(|e| e.to_string())?;
    let problems = problems.iter().map(|p| format!("follower {} at step {}: {}", p.follower, p.k, p.what)).collect();
    Ok((read(&out)?, problems))
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_record::RecordOptions;
    use formation_scenario::Scenario;

    #[test]
    fn a_simulated_folder_reads_back_as_the_run_in_memory() {
        let s = Scenario::load(Path::new("paper"), &["duration=0.5".into()]).expect("paper");
        let dir = tempfile::tempdir().expect("tempdir");
        let opts = RecordOptions { dir: dir.path().join("run"), every: 1, csv: true, mcap: false, rosbag2: false };
        let (summary, out) = formation_sim::run_to_folder(&s, &opts, 1, |_| {}).expect("sim");
        let f = read(&out).expect("read back");
        let m = crate::memory::run(&s, 1, Some(1)).expect("in memory");
        assert_eq!(f.followers, m.followers);
        assert_eq!(f.leader, m.leader);
        assert_eq!(f.summary.trim(), summary.to_json().trim());
        assert!(f.network.is_none());
    }

    #[test]
    fn what_is_not_a_run_folder_is_named_in_one_line() {
        let dir = tempfile::tempdir().expect("tempdir");
        let e = read(&dir.path().join("nothing")).unwrap_err();
        assert!(e.ends_with("there is no run folder here"), "{e}");
        let e = read(dir.path()).unwrap_err();
        assert!(e.contains("not a run folder (summary.json:"), "{e}");
        std::fs::write(dir.path().join("summary.json"), "{}").unwrap();
        std::fs::write(dir.path().join("follower_2.csv"), "t,x\n0,zz\n").unwrap();
        let e = read(dir.path()).unwrap_err();
        assert!(e.contains("follower_2.csv") && e.contains("no column"), "{e}");
        assert_eq!(e.lines().count(), 1, "{e}");
    }
}
