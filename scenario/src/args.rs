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
    /// Where the leader's motion comes from (docs/model.md §18):
    /// `trajectory` (the scenario's), `cmd_vel` (/leader/cmd_vel), `path`
    /// (/leader/path), `robot` (/leader/odom), or a run folder or
    /// leader.csv to play that run's leader again; the same as
    /// `--set leader.source=…` (and `leader.recorded=…`).
    #[cfg_attr(feature = "clap", arg(long, value_name = "SOURCE|RUN"))]
    pub leader: Option<String>,
}

/// The sources `--leader` takes by name; anything else is a record's path.
pub const LEADER_SOURCES: [&str; 4] = ["trajectory", "cmd_vel", "path", "robot"];

impl ScenarioArgs {
    /// The scenario `scenario` names, `--set` and `--leader` applied.
    pub fn load(&self) -> Result<Scenario, ScenarioError> {
        Scenario::load(&self.scenario, &self.all_overrides())
    }

    /// `--set`'s assignments, then what `--leader` stands for.
    pub fn all_overrides(&self) -> Vec<String> {
        let mut o = self.overrides.clone();
        match self.leader.as_deref() {
            None => {}
            Some(s) if LEADER_SOURCES.contains(&s) => o.push(format!("leader.source=\"{s}\"")),
            Some(run) => {
                o.push("leader.source=\"recorded\"".into());
                // A TOML basic string: backslashes and quotes escaped.
                o.push(format!("leader.recorded=\"{}\"", run.replace('\\', "\\\\").replace('"', "\\\"")));
            }
        }
        o
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn leader_stands_for_the_source_or_a_record_to_play() {
        let args = |leader: Option<&str>| ScenarioArgs {
            scenario: "teleop".into(),
            overrides: vec!["duration=5".into()],
            leader: leader.map(str::to_string),
        };
        assert_eq!(args(None).all_overrides(), ["duration=5"]);
        assert_eq!(args(Some("path")).all_overrides(), ["duration=5", "leader.source=\"path\""]);
        assert_eq!(
            args(Some("runs/a \"b\"")).all_overrides(),
            ["duration=5", "leader.source=\"recorded\"", "leader.recorded=\"runs/a \\\"b\\\"\""]
        );
    }
}
