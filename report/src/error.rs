//! How a report, `formation paper` or `formation calibrate` fails: bad
//! input (exit status 2 on the command line) or a run that failed (1).

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Bad input: a malformed scenario, a bad option, a folder that is not a run folder.
    #[error("{0}")]
    Input(String),
    /// The work failed: a simulation, a file that could not be written.
    #[error("{0}")]
    Run(String),
}

impl From<formation_sim::SimError> for Error {
    fn from(e: formation_sim::SimError) -> Self {
        match e {
            formation_sim::SimError::Io(e) => e.into(),
            e => Error::Run(e.to_string()),
        }
    }
}

impl From<formation_record::RecordError> for Error {
    fn from(e: formation_record::RecordError) -> Self {
        Error::Input(e.to_string())
    }
}

impl From<formation_topology::ScenarioError> for Error {
    fn from(e: formation_topology::ScenarioError) -> Self {
        Error::Input(e.to_string())
    }
}

impl From<formation_protocol::error::Error> for Error {
    fn from(e: formation_protocol::error::Error) -> Self {
        match e {
            formation_protocol::error::Error::Input(m) => Error::Input(m),
            formation_protocol::error::Error::Run(m) => Error::Run(m),
        }
    }
}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        use std::io::ErrorKind;
        match e.kind() {
            // An --out that names a file or a folder which is not a run
            // folder, or a path through a file.
            ErrorKind::AlreadyExists | ErrorKind::NotADirectory => Error::Input(e.to_string()),
            _ => Error::Run(e.to_string()),
        }
    }
}

/// Refuses 0 for a count option that must be at least 1.
pub fn at_least_one(flag: &str, value: u64) -> Result<(), Error> {
    match value {
        0 => Err(Error::Input(format!("{flag} must be at least 1, not 0"))),
        _ => Ok(()),
    }
}

/// Refuses, before anything runs, an `--out` the file system would refuse
/// ([`formation_record::out_path::check_out_path`]).
pub fn check_out(flag: &str, path: &std::path::Path) -> Result<(), Error> {
    use formation_record::out_path::{check_out_path, MAX_OUT_NAME_BYTES};
    check_out_path(flag, path, MAX_OUT_NAME_BYTES).map_err(Error::Input)
}
