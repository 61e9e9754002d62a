//! The error a node ends with: one line, and whose fault it was. The
//! binaries map the kind to an exit status; nothing here knows one.

#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum Error {
    /// Bad input: a malformed scenario, a bad option, a mismatched node.
    #[error("{0}")]
    Input(String),
    /// The run failed: a node stopped answering, a file could not be written.
    #[error("{0}")]
    Run(String),
}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        use std::io::ErrorKind;
        match e.kind() {
            // An --out that names a file or a folder which is not a run folder.
            ErrorKind::AlreadyExists | ErrorKind::NotADirectory => Error::Input(e.to_string()),
            _ => Error::Run(e.to_string()),
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

/// A zenoh call that failed: what was being done, and zenoh's words.
pub fn zerr(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Run(format!("{what}: {e}"))
}
