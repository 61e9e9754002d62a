//! The error every command and node ends with: one line, and the exit
//! status that says whose fault it was (2: bad input, 1: the run failed).
//! The one place where the libraries' errors become exit statuses.

use std::process::ExitCode;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Bad input: a malformed scenario, a bad option, a folder that is not a run folder.
    #[error("{0}")]
    Input(String),
    /// The run failed: a node stopped answering, a file could not be written.
    #[error("{0}")]
    Run(String),
    /// The run was recorded to its end, but degraded (exit status 3).
    #[error("{0}")]
    Degraded(String),
    /// Stopped by a signal: exit status 128 + its number (130 for Ctrl-C,
    /// 143 for SIGTERM), as a shell reports an interrupted command.
    #[error("{0}")]
    Interrupted(String, u8),
}

/// The exit status of a run recorded to its end whose health is degraded.
use formation_launch::error::DEGRADED;

/// The name the command modules use.
pub use self::Error as CliError;

impl Error {
    pub fn exit_code(&self) -> ExitCode {
        match self {
            Error::Input(_) => ExitCode::from(2),
            Error::Run(_) => ExitCode::from(1),
            Error::Degraded(_) => ExitCode::from(DEGRADED),
            Error::Interrupted(_, signal) => ExitCode::from(128u8.saturating_add(*signal)),
        }
    }
}

impl From<formation_report::error::Error> for Error {
    fn from(e: formation_report::error::Error) -> Self {
        match e {
            formation_report::error::Error::Input(m) => Error::Input(m),
            formation_report::error::Error::Run(m) => Error::Run(m),
        }
    }
}

impl From<formation_launch::error::Error> for Error {
    fn from(e: formation_launch::error::Error) -> Self {
        use formation_launch::error::Error as E;
        match e {
            E::Input(m) => Error::Input(m),
            E::Run(m) => Error::Run(m),
            E::Degraded(m) => Error::Degraded(m),
            E::Interrupted(m, signal) => Error::Interrupted(m, signal),
        }
    }
}

/// The libraries' errors the commands meet directly, through the crate
/// that already says what each of them means.
macro_rules! through {
    ($via:ty: $($from:ty),*) => {$(
        impl From<$from> for Error {
            fn from(e: $from) -> Self {
                <$via>::from(e).into()
            }
        }
    )*};
}

through!(formation_report::error::Error: formation_sim::SimError, formation_record::RecordError, formation_topology::ScenarioError);
through!(formation_launch::error::Error: formation_certs::generate::GenerateError, formation_view::ViewError, formation_protocol::error::Error, formation_net::session::SessionError, std::io::Error);

/// Refuses 0 for a count option that must be at least 1.
pub fn at_least_one(flag: &str, value: u64) -> Result<(), Error> {
    match value {
        0 => Err(Error::Input(format!("{flag} must be at least 1, not 0"))),
        _ => Ok(()),
    }
}
