//! `formation replay --explain`.
use formation_net::replay::Loaded;

use crate::error::Error as CliError;
use crate::replay::ReplayArgs;

pub fn run(_a: &ReplayArgs, _loaded: &Loaded) -> Result<(), CliError> {
    Err(CliError::Input("--explain is not built yet (issue 25)".into()))
}
