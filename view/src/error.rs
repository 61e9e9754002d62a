//! What a viewer fails with: one line, and whose fault it was.

#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum ViewError {
    /// Bad input: an address that cannot be used.
    #[error("{0}")]
    Input(String),
    /// The server could not be started.
    #[error("{0}")]
    Run(String),
}
