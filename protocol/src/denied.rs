//! What a node's access control refused, as reported on
//! `formation/<run>/control/denied/<node>` ([`Report`], JSON) and filed by
//! the monitor ([`Table`]). Counting zenoh's denials is the node's
//! (`formation_net::denials`).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// One kind of refused message and how often.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Denial {
    /// Who sent it (its certificate's name) or, on egress, whom it was for.
    pub subject: String,
    /// zenoh's words: "Put (ingress)", "Declare Subscriber (egress)", …
    pub action: String,
    pub key: String,
    pub count: u64,
}

/// What one node reports.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Report {
    /// The reporting node (`router`, `leader`, `monitor`, `agent-<id>`).
    pub node: String,
    pub rows: Vec<Denial>,
}

/// The monitor's view: the latest report of every node.
#[derive(Debug, Default)]
pub struct Table {
    by_node: BTreeMap<String, Vec<Denial>>,
}

/// A report's largest size, bytes (a node's rows are few: one per subject,
/// action and key).
pub const MAX_REPORT_BYTES: usize = 64 * 1024;

/// Most rows of one report.
pub const MAX_REPORT_ROWS: usize = 1000;

impl Table {
    /// Files a report (JSON, from `formation/<run>/control/denied/<node>`);
    /// whether it was one.
    pub fn file(&mut self, key_node: &str, bytes: &[u8]) -> bool {
        if bytes.len() > MAX_REPORT_BYTES {
            return false;
        }
        match serde_json::from_slice::<Report>(bytes) {
            Ok(r) if r.node == key_node && r.rows.len() <= MAX_REPORT_ROWS => {
                self.by_node.insert(r.node, r.rows);
                true
            }
            _ => false,
        }
    }

    /// Every row, with the node that refused it.
    pub fn rows(&self) -> Vec<serde_json::Value> {
        self.by_node
            .iter()
            .flat_map(|(node, rows)| {
                rows.iter().map(move |d| {
                    serde_json::json!({ "by": node, "subject": d.subject, "action": d.action, "key": d.key,
                                        "count": d.count })
                })
            })
            .collect()
    }

    /// Lines for the live page: per node that refused anything, the total
    /// and the most frequent.
    pub fn summary(&self) -> Vec<String> {
        self.by_node
            .iter()
            .filter(|(_, rows)| !rows.is_empty())
            .map(|(node, rows)| {
                let total: u64 = rows.iter().map(|d| d.count).sum();
                let top = &rows[0];
                format!(
                    "access control at {node} refused {total} messages (most: {} {} on {}, {})",
                    top.subject, top.action, top.key, top.count
                )
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_monitor_files_only_well_formed_reports_under_their_own_name() {
        let mut table = Table::default();
        let r = Report {
            node: "router".into(),
            rows: vec![Denial { subject: "agent-2".into(), action: "Put (ingress)".into(), key: "k".into(), count: 5 }],
        };
        let bytes = serde_json::to_vec(&r).unwrap();
        assert!(!table.file("leader", &bytes), "a report under another node's key");
        assert!(!table.file("router", b"garbage"));
        assert!(table.file("router", &bytes));
        assert_eq!(table.rows()[0]["count"], 5);
        assert!(table.summary()[0].contains("refused 5 messages"), "{:?}", table.summary());
    }
}
