//! How much a run will write, said before it starts when it is a lot.

use std::path::Path;

use formation_topology::Scenario;

/// Bytes a run folder's time series take, measured on the paper scenario:
/// a follower's CSV row, the leader's, and a follower's MCAP messages.
const CSV_FOLLOWER_ROW: u64 = 420;
const CSV_LEADER_ROW: u64 = 105;
const MCAP_FOLLOWER_ROW: u64 = 1_600;
/// Above this a run says, before it starts, how much it will write.
pub const LARGE_RUN_BYTES: u64 = 4_000_000_000;

/// About how many bytes a run of `scenario` writes with these options.
pub fn projected_bytes(scenario: &Scenario, every: u64, csv: bool, mcap: bool) -> u64 {
    let rows = scenario.steps() / every.max(1) + 1;
    let n = scenario.followers.len() as u64;
    let per_row =
        if csv { n * CSV_FOLLOWER_ROW + CSV_LEADER_ROW } else { 0 } + if mcap { n * MCAP_FOLLOWER_ROW } else { 0 };
    rows.saturating_mul(per_row)
}

/// One line before a run that would write more than [`LARGE_RUN_BYTES`].
pub fn warn_if_large(scenario: &Scenario, every: u64, csv: bool, mcap: bool, dir: &Path) {
    let bytes = projected_bytes(scenario, every, csv, mcap);
    if bytes > LARGE_RUN_BYTES {
        eprintln!(
            "warning: this run will write about {:.1} GB to {} ({} samples of {} followers); --every N or --no-csv write less",
            bytes as f64 / 1e9,
            dir.display(),
            scenario.steps() + 1,
            scenario.followers.len()
        );
    }
}
