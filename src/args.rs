//! Command-line arguments several commands share.

use std::path::PathBuf;

use clap::Args;
use formation_topology::Scenario;

use crate::error::CliError;

/// Scenario selection shared by every command that runs one.
#[derive(Args, Debug, Clone)]
pub struct ScenarioArgs {
    /// Scenario file (TOML). See scenarios/paper.toml for every key.
    pub scenario: PathBuf,
    /// Override a scenario value without editing the file, e.g.
    /// `--set filter=kf --set fault.time=10 --set duration=5`. Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
}

impl ScenarioArgs {
    pub fn load(&self) -> Result<Scenario, CliError> {
        Scenario::load(&self.scenario, &self.overrides).map_err(|e| CliError::Input(e.to_string()))
    }
}
