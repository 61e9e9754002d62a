//! The folder `report`, `paper` and `calibrate` write (`--out`): built
//! under `<out>.partial` and moved into place when complete, replacing only
//! an earlier output of the same command. A folder of the user's, or one
//! holding anything the command does not write, is refused before any work
//! starts; an earlier output's files never mix with the new one's; a
//! command that fails leaves the earlier output as it was.

use std::ffi::OsString;
use std::fs;
use std::path::{Path, PathBuf};

use formation_record::at_path;
use formation_record::folder::names_in;

use formation_exit::Error;

/// File, in a case folder, with every seed's record (written by
/// `formation paper`, read by `formation report`).
pub const SEEDS_FILE: &str = "seeds.json";

/// Which command's output a folder is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind {
    /// `formation report`: report.md, its figures and tables.
    Report,
    /// `formation paper`: a report and the run folder of every case.
    Paper,
    /// `formation calibrate`: calibration.md and its tables.
    Calibration,
}

impl Kind {
    /// The file only this command's output holds.
    fn marker(self) -> &'static str {
        match self {
            Kind::Report | Kind::Paper => "report.md",
            Kind::Calibration => "calibration.md",
        }
    }

    /// Whether `dir` says it is this command's output: its marker, or (a
    /// paper whose report was not written) a case's run folder with its
    /// seeds.json.
    fn marks(self, dir: &Path, names: &[OsString]) -> bool {
        dir.join(self.marker()).is_file()
            || (self == Kind::Paper
                && names.iter().any(|n| {
                    let case = dir.join(n);
                    case.join(SEEDS_FILE).is_file() && run_folder(&case)
                }))
    }

    /// Whether the command writes an entry of this name in its folder (a
    /// notes.md or data.csv of the user's is not one of them). `whole`: a
    /// paper's case folders have their seeds.json (a finished output; an
    /// unfinished `<out>.partial` may hold cases without it).
    fn writes(self, dir: &Path, name: &str, whole: bool) -> bool {
        let path = dir.join(name);
        if path.is_dir() {
            // Paper: a case's run folder, with its seeds.json.
            return self == Kind::Paper && run_folder(&path) && (!whole || path.join(SEEDS_FILE).is_file());
        }
        let (stem, ext) = name.rsplit_once('.').unwrap_or((name, ""));
        let report = name == "report.md"
            || name == "claims.csv"
            || (stem.starts_with("fig") && matches!(ext, "svg" | "png" | "csv"))
            || (stem.starts_with("table") && ext == "csv");
        let calibration =
            matches!(name, "calibration.md" | "calibration.csv" | "sensitivity.csv" | "sensitivity.svg" | "fitted.txt");
        path.is_file()
            && match self {
                Kind::Report | Kind::Paper => report,
                Kind::Calibration => calibration,
            }
    }
}

/// A case's run folder: nothing in it but what a run and `paper` write.
fn run_folder(dir: &Path) -> bool {
    names_in(dir).is_some_and(|names| {
        names.iter().all(|n| {
            let n = n.to_string_lossy();
            formation_record::folder::is_run_entry(&n) || n == SEEDS_FILE
        })
    })
}

/// An output folder being written; removed unless [`Output::finish`]ed.
pub struct Output {
    kind: Kind,
    out: PathBuf,
    partial: PathBuf,
    finished: bool,
}

fn partial_of(out: &Path) -> PathBuf {
    formation_record::folder::beside(out, ".partial")
}

/// Whether the command may write `out`: it is absent, empty, or an
/// earlier output of `kind`, and `<out>.partial` is absent or an
/// unfinished output of `kind`. For a command to call before its work.
pub fn check(out: &Path, kind: Kind) -> Result<(), Error> {
    refuse_foreign(out, kind, true)?;
    refuse_foreign(&partial_of(out), kind, false)
}

impl Output {
    /// [`check`], then makes `<out>.partial` afresh.
    pub fn begin(out: &Path, kind: Kind) -> Result<Self, Error> {
        check(out, kind)?;
        let partial = partial_of(out);
        if partial.exists() {
            fs::remove_dir_all(&partial).map_err(at_path(&partial, "cannot remove the unfinished folder"))?;
        }
        fs::create_dir_all(&partial).map_err(at_path(&partial, "cannot create the folder"))?;
        Ok(Self { kind, out: out.to_path_buf(), partial, finished: false })
    }

    /// Where the command writes until [`Output::finish`].
    pub fn dir(&self) -> &Path {
        &self.partial
    }

    /// Where the output will be.
    pub fn out(&self) -> &Path {
        &self.out
    }

    /// Replaces an earlier output of the command with the new one.
    pub fn finish(mut self) -> Result<PathBuf, Error> {
        // Checked again: the folder may have changed while the command ran.
        refuse_foreign(&self.out, self.kind, true)?;
        if self.out.exists() {
            fs::remove_dir_all(&self.out).map_err(at_path(&self.out, "cannot remove the earlier output"))?;
        }
        fs::rename(&self.partial, &self.out).map_err(at_path(&self.out, "cannot move the output into place"))?;
        self.finished = true;
        Ok(self.out.clone())
    }
}

impl Drop for Output {
    /// A command that failed leaves no half-written folder.
    fn drop(&mut self) {
        if !self.finished {
            let _ = fs::remove_dir_all(&self.partial);
        }
    }
}

/// Refuses a path the command may not replace: a file, or a folder that
/// is not empty and holds something else than `kind` writes (or, with
/// `marker`, lacks the file that says it is `kind`'s output).
fn refuse_foreign(dir: &Path, kind: Kind, marker: bool) -> Result<(), Error> {
    let Ok(meta) = fs::symlink_metadata(dir) else { return Ok(()) };
    if !meta.is_dir() {
        return Err(Error::Input(format!("--out {}: a file is there, not a folder", dir.display())));
    }
    let names = names_in(dir).ok_or_else(|| Error::Input(format!("--out {}: cannot be read", dir.display())))?;
    if names.is_empty() {
        return Ok(());
    }
    if marker && !kind.marks(dir, &names) {
        return Err(Error::Input(format!(
            "--out {} holds files and no {}: not an earlier output of this command, so it is not replaced (choose \
             another --out, or an empty folder)",
            dir.display(),
            kind.marker()
        )));
    }
    let mut foreign: Vec<String> =
        names.iter().map(|n| n.to_string_lossy().into_owned()).filter(|n| !kind.writes(dir, n, marker)).collect();
    foreign.sort();
    match foreign.first() {
        None => Ok(()),
        Some(first) => Err(Error::Input(format!(
            "--out {} holds {first}{}, which this command does not write: refusing to replace it (move that out, \
             or choose another --out)",
            dir.display(),
            if foreign.len() > 1 { format!(" (and {} more)", foreign.len() - 1) } else { String::new() }
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_an_earlier_output_of_the_same_command_is_replaced() {
        let t = tempfile::tempdir().expect("tempdir");
        let out = t.path().join("r");
        // Absent, then empty: fine.
        Output::begin(&out, Kind::Report).expect("absent").finish().expect("finish");
        let o = Output::begin(&out, Kind::Report).expect("empty");
        fs::write(o.dir().join("report.md"), "# new\n").expect("write");
        fs::write(o.dir().join("fig3.svg"), "<svg/>").expect("write");
        o.finish().expect("finish");
        // An earlier report: replaced, its files gone.
        let o = Output::begin(&out, Kind::Report).expect("an earlier report");
        fs::write(o.dir().join("report.md"), "# newer\n").expect("write");
        o.finish().expect("finish");
        assert!(!out.join("fig3.svg").exists(), "a stale figure stayed");
        // Not a calibration's, nor a paper's with a foreign folder.
        let e = Output::begin(&out, Kind::Calibration).err().expect("a report is not a calibration");
        assert!(e.to_string().contains("no calibration.md"), "{e}");
        fs::create_dir(out.join("notes")).expect("mkdir");
        fs::write(out.join("notes").join("mine.txt"), "x").expect("write");
        let e = Output::begin(&out, Kind::Paper).err().expect("a folder of the user's");
        assert!(e.to_string().contains("holds notes"), "{e}");
        fs::remove_dir_all(out.join("notes")).expect("rm");
        // A user's file among the report's, even one named like a report's.
        fs::write(out.join("notes.md"), "mine").expect("write");
        let e = Output::begin(&out, Kind::Report).err().expect("a user's notes.md");
        assert!(e.to_string().contains("holds notes.md"), "{e}");
        fs::remove_file(out.join("notes.md")).expect("rm");
        // `--out r/`: staged beside it, not inside it.
        let slash = t.path().join("slash").join("");
        let o = Output::begin(&slash, Kind::Report).expect("a trailing slash");
        assert!(o.dir().ends_with("slash.partial"), "{}", o.dir().display());
        fs::write(o.dir().join("report.md"), "#\n").expect("write");
        o.finish().expect("finish");
        assert!(t.path().join("slash").join("report.md").is_file());
        fs::write(out.join("thesis.tex"), "precious").expect("write");
        let e = Output::begin(&out, Kind::Report).err().expect("a user's file");
        assert!(e.to_string().contains("holds thesis.tex"), "{e}");
        assert_eq!(fs::read_to_string(out.join("thesis.tex")).expect("kept"), "precious");
        // A user's folder without the marker, and a file.
        let mine = t.path().join("mine");
        fs::create_dir(&mine).expect("mkdir");
        fs::write(mine.join("data.csv"), "1").expect("write");
        let e = Output::begin(&mine, Kind::Report).err().expect("no report.md");
        assert!(e.to_string().contains("no report.md"), "{e}");
        let file = t.path().join("file");
        fs::write(&file, "x").expect("write");
        let e = Output::begin(&file, Kind::Report).err().expect("a file");
        assert!(e.to_string().contains("a file is there"), "{e}");
        // A failed command leaves the earlier output as it was.
        fs::remove_file(out.join("thesis.tex")).expect("rm");
        let o = Output::begin(&out, Kind::Report).expect("report");
        fs::write(o.dir().join("report.md"), "# half\n").expect("write");
        drop(o);
        assert_eq!(fs::read_to_string(out.join("report.md")).expect("kept"), "# newer\n");
        assert!(!partial_of(&out).exists(), "a half-written folder stayed");
        // A paper's case folders are its own; a folder with a user's file is not.
        let paper = t.path().join("p");
        let o = Output::begin(&paper, Kind::Paper).expect("paper");
        fs::write(o.dir().join("report.md"), "#\n").expect("write");
        fs::create_dir(o.dir().join("paper-asif")).expect("mkdir");
        fs::write(o.dir().join("paper-asif").join("summary.json"), "{}").expect("write");
        fs::write(o.dir().join("paper-asif").join(SEEDS_FILE), "[]").expect("write");
        o.finish().expect("finish");
        Output::begin(&paper, Kind::Paper).expect("an earlier paper");
        fs::write(paper.join("paper-asif").join("thesis.tex"), "x").expect("write");
        let e = Output::begin(&paper, Kind::Paper).err().expect("a user's file in a case");
        assert!(e.to_string().contains("holds paper-asif"), "{e}");
    }
}
