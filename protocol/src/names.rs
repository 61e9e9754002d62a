//! The names of a run's nodes (in certificates, key expressions and
//! messages) and the key expressions of a run: the one place they are spelt.
//!
//! | key | who publishes | payload |
//! | --- | --- | --- |
//! | `estimate/<id>` | leader (id 0), follower id | `crate::wire::EstimateMsg` (docs/model.md §13) |
//! | `pose/<id>` | follower id, only with the safety filter on | `crate::wire::PoseMsg` (docs/model.md §16) |
//! | `telemetry/<id>` | leader (id 0), follower id | `telemetry::Telemetry` |
//! | `control/hello/<node>` | every node, until the start | empty |
//! | `control/ready/<node>` | agents and monitor, until the start | `barrier::Ready` |
//! | `control/start` | leader, every 100 ms during the run | `barrier::Start` |
//! | `control/ack` | monitor, every 100 ms during the run | `telemetry::Ack` |
//! | `control/time` | leader's queryable, asked by every agent every 250 ms | `clock_sync::TimeReply` |
//! | `alive/<id>` | each agent's liveliness token (lock-step), while its process lives | (a token) |
//! | `control/holds/<id>` | agents, lock-step, once a follower's token is lost | `died::Holding` |
//! | `control/died` | monitor, lock-step, once every running follower said what it holds | `died::Died` |
//!
//! `<node>` is `0` for the leader, the follower id, or `monitor`.

use formation_scenario::Scenario;

/// The router's node name (its certificate's common name).
pub const ROUTER: &str = "router";
/// The leader's node name.
pub const LEADER: &str = "leader";
/// The monitor's node name, in certificates and in control keys.
pub const MONITOR: &str = "monitor";
/// The leader's name in control keys (its wire id).
pub const LEADER_NODE: &str = "0";

/// A follower's node name (its certificate's common name).
pub fn agent_name(id: u32) -> String {
    format!("agent-{id}")
}

/// Every node of a scenario, in the lab's host order (router, monitor,
/// leader, agents in id order).
pub fn node_names(scenario: &Scenario) -> Vec<String> {
    let mut names = vec![ROUTER.to_string(), MONITOR.to_string(), LEADER.to_string()];
    names.extend(scenario.graph.ids().iter().map(|&id| agent_name(id)));
    names
}

/// Key expression of this project: `formation/<run>/<rest>`.
pub fn key(run: &str, rest: &str) -> String {
    format!("formation/{run}/{rest}")
}

/// A run name that is not one chunk of a key expression.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct BadRunName(String);

/// Check a run name: non-empty, only `[A-Za-z0-9_-]` (so that it is one
/// chunk of a key expression with no wildcard or separator in it).
pub fn validate_run_name(run: &str) -> Result<(), BadRunName> {
    if run.is_empty() {
        return Err(BadRunName("run name is empty (allowed: letters, digits, '_' and '-')".into()));
    }
    let (chars, most) = (run.chars().count(), formation_scenario::scenario::MAX_NAME_CHARS);
    if chars > most {
        let start: String = run.chars().take(20).collect();
        return Err(BadRunName(format!("run name `{start}…` is {chars} characters long, at most {most}")));
    }
    if let Some(c) = run.chars().find(|c| !(c.is_ascii_alphanumeric() || *c == '_' || *c == '-')) {
        return Err(BadRunName(format!(
            "run name {run:?} contains {c:?}: only letters, digits, '_' and '-' are allowed"
        )));
    }
    Ok(())
}

/// The key expressions of one run.
#[derive(Clone, Debug)]
pub struct Keys {
    pub run: String,
}

impl Keys {
    pub fn new(run: &str) -> Self {
        Self { run: run.to_string() }
    }
    pub fn estimate(&self, id: u32) -> String {
        key(&self.run, &format!("estimate/{id}"))
    }
    /// A follower's robot's pose (safety filter on).
    pub fn pose(&self, id: u32) -> String {
        key(&self.run, &format!("pose/{id}"))
    }
    pub fn pose_all(&self) -> String {
        key(&self.run, "pose/*")
    }
    pub fn telemetry(&self, id: u32) -> String {
        key(&self.run, &format!("telemetry/{id}"))
    }
    pub fn telemetry_all(&self) -> String {
        key(&self.run, "telemetry/*")
    }
    pub fn hello(&self, node: &str) -> String {
        key(&self.run, &format!("control/hello/{node}"))
    }
    pub fn ready(&self, node: &str) -> String {
        key(&self.run, &format!("control/ready/{node}"))
    }
    pub fn ready_all(&self) -> String {
        key(&self.run, "control/ready/*")
    }
    pub fn ack(&self) -> String {
        key(&self.run, "control/ack")
    }
    pub fn start(&self) -> String {
        key(&self.run, "control/start")
    }
    /// The leader's timebase, asked for by the others (a queryable).
    pub fn time(&self) -> String {
        key(&self.run, "control/time")
    }
    /// What a node's access control refused (crate::denials), every node's.
    pub fn denied_all(&self) -> String {
        key(&self.run, "control/denied/*")
    }
    /// A process's claim to node `id`'s identity (0: the leader; crate::claim).
    pub fn claim(&self, id: u32) -> String {
        key(&self.run, &format!("control/claim/{id}"))
    }
    /// `formation leave --id ID`: follower ID is asked to leave the run.
    pub fn leave(&self, id: u32) -> String {
        key(&self.run, &format!("control/leave/{id}"))
    }
    /// The leader refuses the run before its start (the reason, UTF-8).
    pub fn abort(&self) -> String {
        key(&self.run, "control/abort")
    }
    /// Follower `id`'s liveliness token, held while its process lives
    /// (`died`).
    pub fn alive(&self, id: u32) -> String {
        key(&self.run, &format!("alive/{id}"))
    }
    pub fn alive_all(&self) -> String {
        key(&self.run, "alive/*")
    }
    /// What follower `id` holds of one that died (`died::Holding`).
    pub fn holds(&self, id: u32) -> String {
        key(&self.run, &format!("control/holds/{id}"))
    }
    pub fn holds_all(&self) -> String {
        key(&self.run, "control/holds/*")
    }
    /// The monitor names the step a killed follower is cut off from (`died::Died`).
    pub fn died(&self) -> String {
        key(&self.run, "control/died")
    }
}

/// The last chunk of a key expression (`…/estimate/3` → `3`).
pub fn last_chunk(key: &str) -> &str {
    key.rsplit('/').next().unwrap_or("")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_and_run_names() {
        assert_eq!(key("run-1", "agent/3/state"), "formation/run-1/agent/3/state");
        for ok in ["a", "run_1", "A-b-C_9"] {
            validate_run_name(ok).unwrap();
        }
        for bad in ["", "a/b", "a*", "a b", "$x", "é", "a?"] {
            let e = validate_run_name(bad).unwrap_err().to_string();
            assert!(e.contains("run name"), "{e}");
        }
    }
}
