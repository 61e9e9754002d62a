//! The command-line arguments that choose a scenario, for every command
//! that runs one (the `clap` feature).

use std::path::PathBuf;

use crate::{Scenario, ScenarioError};

/// Scenario selection shared by every command that runs one.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct ScenarioArgs {
    /// Scenario file (TOML), or a built-in one by name (paper, paper-velocity, paper-tables, turtlebot, swap, rotation, doorway, teleop). Every key: docs/scenarios.md.
    pub scenario: PathBuf,
    /// Override a scenario value without editing the file, e.g.
    /// `--set filter=kf --set fault.time=10 --set duration=5`. Repeatable.
    #[cfg_attr(feature = "clap", arg(long = "set", value_name = "KEY=VALUE"))]
    pub overrides: Vec<String>,
}

impl ScenarioArgs {
    pub fn load(&self) -> Result<Scenario, ScenarioError> {
        Scenario::load(&self.scenario, &self.overrides)
    }
}
