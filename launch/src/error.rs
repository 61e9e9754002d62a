//! How a launch, a lab run or a node's supervision ends when it does not
//! succeed, with the exit status each case has on the command line.

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Bad input: a malformed scenario, a bad option, a folder that is not a run folder.
    #[error("{0}")]
    Input(String),
    /// The run failed: a node stopped answering, a file could not be written.
    #[error("{0}")]
    Run(String),
    /// The run was recorded to its end, but degraded (exit status [`DEGRADED`]).
    #[error("{0}")]
    Degraded(String),
    /// Stopped by a signal: exit status 128 + its number (130 for Ctrl-C,
    /// 143 for SIGTERM), as a shell reports an interrupted command.
    #[error("{0}")]
    Interrupted(String, u8),
}

/// The exit status of a run recorded to its end whose health is degraded:
/// the formation did far worse than its model (network.json's `health`
/// says which follower, and what else happened).
pub const DEGRADED: u8 = 3;

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

impl From<formation_certs::generate::GenerateError> for Error {
    fn from(e: formation_certs::generate::GenerateError) -> Self {
        match e {
            formation_certs::generate::GenerateError::Input(m) => Error::Input(m),
            formation_certs::generate::GenerateError::Run(m) => Error::Run(m),
        }
    }
}

impl From<formation_view::ViewError> for Error {
    fn from(e: formation_view::ViewError) -> Self {
        match e {
            formation_view::ViewError::Input(m) => Error::Input(m),
            formation_view::ViewError::Run(m) => Error::Run(m),
        }
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

impl From<formation_net::session::SessionError> for Error {
    fn from(e: formation_net::session::SessionError) -> Self {
        formation_protocol::error::Error::from(e).into()
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
