//! The error every command and node ends with: one line, and whose fault
//! it was, which is its exit status.

/// How a command or a node failed, in one line.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Error {
    /// Bad input: a malformed scenario, a bad option, a folder that is not
    /// a run folder, a mismatched node (exit status 2).
    #[error("{0}")]
    Input(String),
    /// The run failed: a node stopped answering, a file could not be
    /// written (exit status 1).
    #[error("{0}")]
    Run(String),
    /// The run was recorded to its end, but degraded: the formation did far
    /// worse than its model (network.json's `health` says which follower,
    /// and what else happened; exit status [`DEGRADED`]).
    #[error("{0}")]
    Degraded(String),
    /// Stopped by a signal (its number): exit status 128 + it, 130 for
    /// Ctrl-C and 143 for SIGTERM, as a shell reports an interrupted command.
    #[error("{0}")]
    Interrupted(String, u8),
}

/// The exit status of a run recorded to its end whose health is degraded.
pub const DEGRADED: u8 = 3;

impl Error {
    /// The exit status this error ends a process with: the one place where
    /// a failure becomes a number (a supervisor reading a child's status
    /// compares with the same numbers).
    ///
    /// ```
    /// use formation_exit::Error;
    /// let statuses: Vec<u8> = [
    ///     Error::Input("bad".into()),
    ///     Error::Run("failed".into()),
    ///     Error::Degraded("far off".into()),
    ///     Error::Interrupted("Ctrl-C".into(), 2),
    /// ]
    /// .iter()
    /// .map(Error::status)
    /// .collect();
    /// assert_eq!(statuses, [2, 1, 3, 130]);
    /// ```
    pub fn status(&self) -> u8 {
        match self {
            Error::Input(_) => 2,
            Error::Run(_) => 1,
            Error::Degraded(_) => DEGRADED,
            Error::Interrupted(_, signal) => 128u8.saturating_add(*signal),
        }
    }

    /// The line it says, without its kind.
    pub fn message(&self) -> &str {
        match self {
            Error::Input(m) | Error::Run(m) | Error::Degraded(m) | Error::Interrupted(m, _) => m,
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

/// A call into the network (zenoh) that failed: what was being done, and
/// the library's words.
pub fn zerr(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Run(format!("{what}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_in_the_way_is_bad_input_and_other_io_a_failed_run() {
        let in_the_way = std::io::Error::new(std::io::ErrorKind::AlreadyExists, "runs/paper is a file");
        assert_eq!(Error::from(in_the_way).status(), 2);
        let full = std::io::Error::other("no space left on device");
        assert_eq!(Error::from(full), Error::Run("no space left on device".into()));
        assert_eq!(zerr("declaring a publisher", "closed").message(), "declaring a publisher: closed");
        assert_eq!(Error::Interrupted("x".into(), 255).status(), 255, "saturates, never wraps");
    }
}
