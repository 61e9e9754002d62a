//! The error every command and node ends with: one line, and the exit
//! status that says whose fault it was (2: bad input, 1: the run failed).

use std::process::ExitCode;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Bad input: a malformed scenario, a bad option, a folder that is not a run folder.
    #[error("{0}")]
    Input(String),
    /// The run failed: a node stopped answering, a file could not be written.
    #[error("{0}")]
    Run(String),
}

impl Error {
    pub fn exit_code(&self) -> ExitCode {
        match self {
            Error::Input(_) => ExitCode::from(2),
            Error::Run(_) => ExitCode::from(1),
        }
    }
}

impl From<crate::sim::SimError> for Error {
    fn from(e: crate::sim::SimError) -> Self {
        Error::Run(e.to_string())
    }
}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        use std::io::ErrorKind;
        match e.kind() {
            // An --out that names a file or a folder which is not a run
            // folder, or a path through a file. (An over-long name,
            // `InvalidFilename`, needs Rust 1.87, past the MSRV.)
            ErrorKind::AlreadyExists | ErrorKind::NotADirectory => Error::Input(e.to_string()),
            _ => Error::Run(e.to_string()),
        }
    }
}
