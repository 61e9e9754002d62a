//! Reading a run folder's CSVs back: the named columns of a file with a
//! header row, and the error that says which file and line is wrong.

use std::path::{Path, PathBuf};

/// Why a run folder's file could not be read back.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The file is there but is not what a run folder holds (a missing
    /// column, a field that is not a number): bad input.
    #[error("{}: {what}", path.display())]
    Malformed { path: PathBuf, what: String },
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
}

/// A run folder that cannot be read or written as one is the user's input
/// (a folder that is not a run folder, or one from another version).
impl From<RecordError> for formation_exit::Error {
    fn from(e: RecordError) -> Self {
        formation_exit::Error::Input(e.to_string())
    }
}

/// Reads the named columns of a CSV file with a header row. Every field of
/// the file must be a number: an error names the file, the line and the
/// column of the first that is not.
pub fn read_columns(path: &Path, names: &[&str]) -> Result<Vec<Vec<f64>>, RecordError> {
    read_columns_checked(path, names, false)
}

/// [`read_columns`], and with `finite` every field must be a finite number:
/// a complete run writes nothing else (a diverged run's last rows may hold
/// inf or NaN).
pub fn read_columns_checked(path: &Path, names: &[&str], finite: bool) -> Result<Vec<Vec<f64>>, RecordError> {
    let bad = |what: String| RecordError::Malformed { path: path.to_path_buf(), what };
    let mut reader = csv::ReaderBuilder::new().has_headers(true).from_path(path).map_err(|e| match e.into_kind() {
        csv::ErrorKind::Io(source) => RecordError::Io { path: path.to_path_buf(), source },
        other => bad(format!("{other:?}")),
    })?;
    let headers = reader.headers().map_err(|e| bad(e.to_string()))?.clone();
    let idx: Vec<usize> = names
        .iter()
        .map(|n| headers.iter().position(|h| h.trim() == *n).ok_or_else(|| bad(format!("no column `{n}`"))))
        .collect::<Result<_, _>>()?;
    // Field index → the named column it fills.
    let mut slot = vec![None; headers.len()];
    for (k, &i) in idx.iter().enumerate() {
        slot[i] = Some(k);
    }
    let mut cols = vec![Vec::new(); names.len()];
    for (n, rec) in reader.records().enumerate() {
        let rec = rec.map_err(|e| match e.kind() {
            csv::ErrorKind::UnequalLengths { pos: Some(pos), expected_len, len } => {
                bad(format!("line {}: {len} fields, where the header has {expected_len}", pos.line()))
            }
            _ => bad(e.to_string()),
        })?;
        let line = rec.position().map_or(n as u64 + 2, |p| p.line());
        for (i, field) in rec.iter().enumerate() {
            let name = headers.get(i).unwrap_or("?").trim();
            let v: f64 = field.trim().parse().map_err(|_| {
                let shown: String = field.chars().take(20).collect();
                let more = if shown.len() < field.len() { "…" } else { "" };
                bad(format!("line {line}: `{name}` is not a number: {shown:?}{more}"))
            })?;
            if finite && !v.is_finite() {
                return Err(bad(format!("line {line}: `{name}` is {v}, not a finite number")));
            }
            if let Some(k) = slot[i] {
                cols[k].push(v);
            }
        }
    }
    Ok(cols)
}
