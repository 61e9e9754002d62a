//! Domain errors of scenario loading and validation.

use thiserror::Error;

/// Why a scenario was rejected. Each names the field at fault and, where it
/// is known, the line of the file.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum ScenarioError {
    /// The TOML did not parse or did not match the schema.
    #[error("{}{message}", location(.file, *.line))]
    Syntax { file: String, line: Option<usize>, message: String },
    /// A value is out of its domain.
    #[error("{}{field}: {message}", location(.file, *.line))]
    Invalid { file: String, line: Option<usize>, field: String, message: String },
    /// A `--set KEY=VALUE` override that could not be applied.
    #[error("--set {assignment}: {message}")]
    Override { assignment: String, message: String },
    /// Lemma 1 does not hold: some followers cannot be reached from the leader.
    #[error(
        "{}graph: H is not positive definite (Lemma 1): followers {} are not connected to any follower that hears the leader",
        location(.file, None),
        list(.unreachable)
    )]
    GraphNotConnected { file: String, unreachable: Vec<u32> },
    /// The file could not be read.
    #[error("{file}: {message}")]
    Io { file: String, message: String },
}

fn location(file: &str, line: Option<usize>) -> String {
    match line {
        Some(l) => format!("{file}:{l}: "),
        None if file.is_empty() => String::new(),
        None => format!("{file}: "),
    }
}

use crate::graph::id_list as list;

/// A scenario that cannot be used is the user's input, whichever command
/// read it.
impl From<ScenarioError> for formation_exit::Error {
    fn from(e: ScenarioError) -> Self {
        formation_exit::Error::Input(e.to_string())
    }
}
