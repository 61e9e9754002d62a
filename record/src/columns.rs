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

/// Reads the named columns of a CSV file with a header row.
pub fn read_columns(path: &Path, names: &[&str]) -> Result<Vec<Vec<f64>>, RecordError> {
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
    let mut cols = vec![Vec::new(); names.len()];
    for (line, rec) in reader.records().enumerate() {
        let rec = rec.map_err(|e| bad(e.to_string()))?;
        for ((col, &i), name) in cols.iter_mut().zip(&idx).zip(names) {
            let v: f64 = rec
                .get(i)
                .and_then(|s| s.trim().parse().ok())
                .ok_or_else(|| bad(format!("line {}: `{name}` is not a number", line + 2)))?;
            col.push(v);
        }
    }
    Ok(cols)
}
