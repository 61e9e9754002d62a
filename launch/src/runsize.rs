//! How much a run will write, said before it starts when it is a lot.

use std::path::Path;

use formation_scenario::Scenario;

use formation_exit::Error;

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

/// Bytes free to an unprivileged writer on the file system that would hold
/// `dir` (its nearest existing ancestor); None if that cannot be read.
pub fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let abs = std::path::absolute(dir).ok()?;
    let existing = abs.ancestors().find(|p| p.exists())?;
    let path = std::ffi::CString::new(existing.as_os_str().as_bytes()).ok()?;
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: a NUL-terminated path and a zeroed struct statvfs to fill.
    if unsafe { libc::statvfs(path.as_ptr(), &mut st) } != 0 {
        return None;
    }
    Some((st.f_bavail as u64).saturating_mul(st.f_frsize as u64))
}

/// Refuses a run that would write more than its disk has free (it started,
/// filled the disk and failed, leaving a large `<out>.partial`); one line
/// before a run that would write more than [`LARGE_RUN_BYTES`].
/// `less`: what writes less with this command (sim: "--every N or
/// --no-csv"; launch: "a shorter duration").
pub fn check(scenario: &Scenario, every: u64, csv: bool, mcap: bool, dir: &Path, less: &str) -> Result<(), Error> {
    let bytes = projected_bytes(scenario, every, csv, mcap);
    if let Some(free) = free_bytes(dir).filter(|&free| bytes > free) {
        return Err(Error::Input(format!(
            "this run would write about {:.1} GB to {}, which has {:.1} GB free ({} samples of {} followers): {less} \
             writes less",
            bytes as f64 / 1e9,
            dir.display(),
            free as f64 / 1e9,
            scenario.steps() + 1,
            scenario.followers.len()
        )));
    }
    warn_if_large(scenario, bytes, dir, less);
    Ok(())
}

/// One line before a run that would write more than [`LARGE_RUN_BYTES`].
fn warn_if_large(scenario: &Scenario, bytes: u64, dir: &Path, less: &str) {
    if bytes > LARGE_RUN_BYTES {
        eprintln!(
            "warning: this run will write about {:.1} GB to {} ({} samples of {} followers); {less} writes less",
            bytes as f64 / 1e9,
            dir.display(),
            scenario.steps() + 1,
            scenario.followers.len()
        );
    }
}
