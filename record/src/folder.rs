//! The run folder on disk: a CSV per follower, `leader.csv`,
//! `summary.json` (and `run.mcap`), written under `<dir>.partial` and moved
//! into place when complete.

use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use formation_leader::LeaderState;

use crate::row::{Row, FOLLOWER_HEADER, LEADER_HEADER};
use crate::summary::Summary;

/// Where and how densely a run folder is written.
#[derive(Clone, Debug)]
pub struct RecordOptions {
    pub dir: PathBuf,
    /// Write every N-th sample to the CSVs (metrics use every sample).
    pub every: u64,
    /// Write CSVs at all.
    pub csv: bool,
    /// Also write run.mcap from the CSVs ([`crate::mcap`]).
    pub mcap: bool,
    /// Also write rosbag2/ from the CSVs ([`crate::rosbag2`]).
    pub rosbag2: bool,
}

/// Writes a run folder. Rows are buffered per follower and appended to the
/// follower's CSV when the buffer fills, so any number of followers works
/// with a bounded number of open files and bounded memory. The folder is
/// built under `<dir>.partial` and renamed into place by [`RunWriter::finish`].
pub struct RunWriter {
    final_dir: PathBuf,
    dir: PathBuf,
    every: u64,
    csv: bool,
    mcap: bool,
    rosbag2: bool,
    ids: Vec<u32>,
    buffers: Vec<Vec<u8>>,
    leader_buffer: Vec<u8>,
    flush_at: usize,
}

impl RunWriter {
    pub fn create(opts: &RecordOptions, ids: &[u32]) -> std::io::Result<Self> {
        refuse_foreign_folder(&opts.dir)?;
        let dir = beside(&opts.dir, ".partial");
        if dir.exists() {
            refuse_foreign_partial(&dir)?;
            fs::remove_dir_all(&dir).map_err(at_path(&dir, "cannot remove the old folder"))?;
        }
        fs::create_dir_all(&dir).map_err(at_path(&dir, "cannot create the folder"))?;
        let flush_at = (64 << 20) / ids.len().max(1);
        let flush_at = flush_at.clamp(4 << 10, 1 << 20);
        let mut w = Self {
            final_dir: opts.dir.clone(),
            dir,
            every: opts.every.max(1),
            csv: opts.csv,
            mcap: opts.mcap,
            rosbag2: opts.rosbag2,
            ids: ids.to_vec(),
            buffers: vec![FOLLOWER_HEADER.as_bytes().to_vec(); ids.len()],
            leader_buffer: LEADER_HEADER.as_bytes().to_vec(),
            flush_at,
        };
        if w.csv {
            for i in 0..ids.len() {
                let path = w.follower_path(i);
                File::create(&path).map_err(at_path(&path, "cannot create"))?;
            }
            let path = w.dir.join("leader.csv");
            File::create(&path).map_err(at_path(&path, "cannot create"))?;
        }
        w.flush_all()?;
        Ok(w)
    }

    fn follower_path(&self, index: usize) -> PathBuf {
        self.dir.join(format!("follower_{}.csv", self.ids[index]))
    }

    /// Whether the folder holds CSVs at all (`--no-csv`: none).
    pub fn csv(&self) -> bool {
        self.csv
    }

    /// Whether sample k goes into the CSVs.
    pub fn wants(&self, k: u64, last: bool) -> bool {
        self.csv && (k % self.every == 0 || last)
    }

    pub fn follower_row(&mut self, index: usize, r: &Row) -> std::io::Result<()> {
        let b = &mut self.buffers[index];
        write_fields(b, &r.csv_fields());
        if b.len() >= self.flush_at {
            let path = self.follower_path(index);
            append(&path, &mut self.buffers[index])?;
        }
        Ok(())
    }

    pub fn leader_row(&mut self, t: f64, l: &LeaderState) -> std::io::Result<()> {
        write_fields(&mut self.leader_buffer, &crate::row::leader_csv_fields(t, l));
        if self.leader_buffer.len() >= self.flush_at {
            append(&self.dir.join("leader.csv"), &mut self.leader_buffer)?;
        }
        Ok(())
    }

    fn flush_all(&mut self) -> std::io::Result<()> {
        if !self.csv {
            return Ok(());
        }
        for i in 0..self.ids.len() {
            let path = self.follower_path(i);
            append(&path, &mut self.buffers[i])?;
        }
        append(&self.dir.join("leader.csv"), &mut self.leader_buffer)
    }

    /// Writes an extra file into the run folder.
    pub fn write_file(&self, name: &str, contents: &str) -> std::io::Result<()> {
        let path = self.dir.join(name);
        fs::write(&path, contents).map_err(at_path(&path, "cannot write"))
    }

    /// Writes an extra binary file into the run folder.
    pub fn write_bytes(&self, name: &str, contents: &[u8]) -> std::io::Result<()> {
        let path = self.dir.join(name);
        fs::write(&path, contents).map_err(at_path(&path, "cannot write"))
    }

    /// Flushes the CSVs and writes what has been recorded so far, without
    /// finishing (for a partial run that stops with an error).
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.flush_all()
    }

    /// Flushes everything, writes `summary.json` and moves the folder into place.
    pub fn finish(mut self, summary: &Summary) -> std::io::Result<PathBuf> {
        self.flush_all()?;
        self.write_file("summary.json", &summary.to_json())?;
        if self.csv && self.mcap {
            crate::mcap::write(&self.dir, &self.ids)?;
        }
        if self.csv && self.rosbag2 {
            crate::rosbag2::write(&self.dir, &self.ids)?;
        }
        refuse_foreign_folder(&self.final_dir)?;
        if self.final_dir.exists() {
            fs::remove_dir_all(&self.final_dir).map_err(at_path(&self.final_dir, "cannot replace the old run"))?;
        }
        let what = format!("cannot move {} here", self.dir.display());
        fs::rename(&self.dir, &self.final_dir).map_err(at_path(&self.final_dir, &what))?;
        Ok(self.final_dir.clone())
    }

    /// Removes the `<dir>.partial` folder: nothing of it is worth keeping.
    pub fn discard(self) {
        let _ = fs::remove_dir_all(&self.dir);
    }

    /// The folder being written (`<dir>.partial` until finished).
    pub fn partial_dir(&self) -> &Path {
        &self.dir
    }
}

/// A run folder is replaced by a new run only if it is one: empty, or
/// holding a `summary.json` or `network.json` and nothing but what a run
/// writes ([`is_run_entry`]). Anything else (`--out .`, `--out ~`, a folder
/// of the user's, a run folder the user added notes to, a file) is refused
/// rather than deleted.
pub fn refuse_foreign_folder(dir: &Path) -> std::io::Result<()> {
    if fs::metadata(dir).is_ok_and(|m| !m.is_dir()) {
        return Err(refused(format!("{} exists and is not a folder: refusing to replace it", dir.display())));
    }
    let Some(names) = names_in(dir) else { return Ok(()) };
    if names.is_empty() {
        return Ok(());
    }
    let is_run = dir.join("summary.json").is_file() || dir.join("network.json").is_file();
    if !is_run {
        return Err(refused(format!(
            "{} exists and is not a run folder (no summary.json): refusing to replace it",
            dir.display()
        )));
    }
    refuse_foreign_entries(dir, &names)
}

/// Whether a run may be written to `dir`: [`refuse_foreign_folder`] for
/// it, and `<dir>.partial` (which the run replaces) holds nothing but what
/// a run writes. For a command to check before it starts anything.
pub fn refuse_replacing_foreign(dir: &Path) -> std::io::Result<()> {
    refuse_foreign_folder(dir)?;
    refuse_foreign_partial(&beside(dir, ".partial"))
}

/// `<dir>.partial`, left by a run that did not finish, is removed only if
/// it holds nothing but what a run writes.
fn refuse_foreign_partial(dir: &Path) -> std::io::Result<()> {
    names_in(dir).map_or(Ok(()), |names| refuse_foreign_entries(dir, &names))
}

/// The names in folder `dir`; None if it cannot be read (it does not exist).
pub fn names_in(dir: &Path) -> Option<Vec<std::ffi::OsString>> {
    Some(fs::read_dir(dir).ok()?.flatten().map(|e| e.file_name()).collect())
}

fn refuse_foreign_entries(dir: &Path, names: &[std::ffi::OsString]) -> std::io::Result<()> {
    let mut foreign: Vec<String> = names
        .iter()
        .filter(|n| !is_run_entry(&n.to_string_lossy()))
        .map(|n| n.to_string_lossy().into_owned())
        .collect();
    if foreign.is_empty() {
        return Ok(());
    }
    foreign.sort();
    let more = if foreign.len() > 1 { format!(" (and {} more)", foreign.len() - 1) } else { String::new() };
    Err(refused(format!(
        "{} holds {}{more}, which no run writes: refusing to replace it (move that out, or choose another --out)",
        dir.display(),
        foreign[0]
    )))
}

/// Whether a run writes an entry of this name in its folder: the CSVs,
/// `summary.json`, `network.json`, `hearing.bin`, `run.mcap`, `rosbag2/`,
/// `zenoh-log/` and the lab's `lab.json`.
pub fn is_run_entry(name: &str) -> bool {
    let follower_csv = name
        .strip_prefix("follower_")
        .and_then(|r| r.strip_suffix(".csv"))
        .is_some_and(|id| !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit()));
    follower_csv
        || matches!(
            name,
            "leader.csv"
                | "summary.json"
                | "network.json"
                | crate::hearing::HEARING_FILE
                | crate::mcap::FILE
                | "rosbag2"
                | "zenoh-log"
                | "lab.json"
        )
}

/// The sibling of folder `dir` named `<its name><suffix>`: `runs/a/` and
/// `runs/a` give `runs/a.partial` (appending to the path put it inside the
/// folder, `runs/a/.partial`, for an --out typed with a trailing slash).
pub fn beside(dir: &Path, suffix: &str) -> PathBuf {
    match dir.file_name() {
        Some(name) => {
            let mut name = name.to_owned();
            name.push(suffix);
            dir.with_file_name(name)
        }
        // `.`, `..`, `/`: refused by the commands before they write.
        None => {
            let mut path = dir.as_os_str().to_owned();
            path.push(suffix);
            PathBuf::from(path)
        }
    }
}

fn refused(message: String) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::AlreadyExists, message)
}

fn write_fields(b: &mut Vec<u8>, fields: &[f64]) {
    let mut buf = ryu::Buffer::new();
    for (i, f) in fields.iter().enumerate() {
        if i > 0 {
            b.push(b',');
        }
        b.extend_from_slice(buf.format(*f).as_bytes());
    }
    b.push(b'\n');
}

fn append(path: &Path, buffer: &mut Vec<u8>) -> std::io::Result<()> {
    if buffer.is_empty() {
        return Ok(());
    }
    let mut f = OpenOptions::new().append(true).create(true).open(path).map_err(at_path(path, "cannot open"))?;
    f.write_all(buffer).map_err(at_path(path, "cannot write"))?;
    buffer.clear();
    Ok(())
}

/// An IO error that names the path it is about (the OS message alone does
/// not: "File name too long (os error 36)"), of the same kind.
pub fn at_path<'a>(path: &'a Path, what: &'a str) -> impl FnOnce(std::io::Error) -> std::io::Error + 'a {
    move |e| std::io::Error::new(e.kind(), format!("{}: {what}: {e}", path.display()))
}

#[cfg(test)]
mod beside_tests {
    use super::beside;
    use std::path::Path;

    #[test]
    fn a_trailing_slash_still_names_a_sibling() {
        for dir in ["runs/a", "runs/a/", "runs/a/.", "./runs/a//"] {
            assert_eq!(beside(Path::new(dir), ".partial").file_name().unwrap(), "a.partial", "{dir}");
            assert!(beside(Path::new(dir), ".partial").ends_with("runs/a.partial"), "{dir}");
        }
    }
}

#[cfg(test)]
mod header_tests {
    /// What a run writes as its leader record is what `leader.source =
    /// "recorded"` reads back (formation_scenario::recorded).
    #[test]
    fn the_leader_csv_header_is_the_one_a_recorded_leader_reads() {
        assert_eq!(crate::row::LEADER_HEADER.trim_end(), formation_scenario::recorded::HEADER);
    }
}
