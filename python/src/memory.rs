//! A scenario run in process into columns in memory: per follower the 22
//! columns of its CSV, the leader's 6, and the summary — the numbers
//! `formation sim` writes, bit for bit, without a file between.

use formation_leader::LeaderState;
use formation_record::{leader_csv_fields, Row, Summary, FOLLOWER_HEADER, LEADER_HEADER};
use formation_scenario::Scenario;
use formation_sim::{Observer, Simulation};

/// One CSV's columns: `names[i]` holds `data[i]`, every column as long.
#[derive(Clone, Debug, PartialEq)]
pub struct Columns {
    pub names: Vec<&'static str>,
    pub data: Vec<Vec<f64>>,
}

impl Columns {
    /// Empty columns named by a CSV header line, room for `rows`.
    pub fn with_header(header: &'static str, rows: usize) -> Self {
        let names: Vec<&'static str> = header.trim_end().split(',').collect();
        let data = names.iter().map(|_| Vec::with_capacity(rows)).collect();
        Self { names, data }
    }

    pub fn rows(&self) -> usize {
        self.data.first().map_or(0, Vec::len)
    }

    fn push(&mut self, fields: &[f64]) {
        for (column, &v) in self.data.iter_mut().zip(fields) {
            column.push(v);
        }
    }
}

/// A run held in memory.
#[derive(Debug)]
pub struct MemoryRun {
    /// (follower id, its columns), in the scenario's order.
    pub followers: Vec<(u32, Columns)>,
    pub leader: Columns,
    pub summary: Summary,
    /// Why the run stopped early (a diverged step); its columns then hold
    /// every step before, and the summary says `complete: false`.
    pub error: Option<String>,
}

/// At most this many numbers in memory for one run (8 GB of float64):
/// beyond, [`run`] refuses and names `every`.
pub const MAX_VALUES: u64 = 1 << 30;

/// Whether a run of `scenario` sampled every `every` steps fits in memory:
/// the numbers it would hold, or the one-line reason it does not.
pub fn check_size(scenario: &Scenario, every: u64) -> Result<u64, String> {
    if every == 0 {
        return Err("every must be at least 1".into());
    }
    let rows = scenario.steps() / every + 2;
    let values = rows.saturating_mul(22 * scenario.followers.len() as u64 + 6);
    if values > MAX_VALUES {
        return Err(format!(
            "this run would hold {:.1} GB of samples in memory ({} followers, {} rows each); sample every N-th step \
             (every=N) or run a shorter duration",
            values as f64 * 8e-9,
            scenario.followers.len(),
            rows
        ));
    }
    Ok(values)
}

struct MemoryObserver {
    followers: Vec<Columns>,
    leader: Columns,
    steps: u64,
    dt_s: f64,
    every: u64,
    /// Keep columns at all (false: the summary only, as `--no-csv`).
    keep: bool,
}

impl MemoryObserver {
    fn wants(&self, k: u64, last: bool) -> bool {
        self.keep && (k % self.every == 0 || last)
    }
}

impl Observer for MemoryObserver {
    fn leader(&mut self, k: u64, l: &LeaderState) -> std::io::Result<()> {
        if self.wants(k, k == self.steps) {
            self.leader.push(&leader_csv_fields(k as f64 * self.dt_s, l));
        }
        Ok(())
    }
    fn follower(&mut self, index: usize, k: u64, row: &Row, last: bool) -> std::io::Result<()> {
        if self.wants(k, last) {
            self.followers[index].push(&row.csv_fields());
        }
        Ok(())
    }
    fn wants_rows(&self) -> bool {
        self.keep
    }
}

/// Runs `scenario` in process with each step's followers on `threads`
/// threads (the numbers are the same for any count), keeping every
/// `every`-th sample and the last, as `formation sim --every` writes them;
/// with `every` None the summary only (empty columns), as `--no-csv`.
pub fn run(scenario: &Scenario, threads: usize, every: Option<u64>) -> Result<MemoryRun, String> {
    scenario.simulable()?;
    let keep = every.is_some();
    let every = every.unwrap_or(1);
    check_size(scenario, every)?;
    let threads = threads.max(1);
    if threads > 1 {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| format!("cannot start {threads} threads: {e}"))?;
        return Ok(pool.install(|| run_on(scenario, true, every, keep)));
    }
    Ok(run_on(scenario, false, every, keep))
}

fn run_on(scenario: &Scenario, parallel: bool, every: u64, keep: bool) -> MemoryRun {
    let rows = if keep { (scenario.steps() / every + 2) as usize } else { 0 };
    let mut observer = MemoryObserver {
        followers: scenario.followers.iter().map(|_| Columns::with_header(FOLLOWER_HEADER, rows)).collect(),
        leader: Columns::with_header(LEADER_HEADER, rows),
        steps: scenario.steps(),
        dt_s: scenario.dt_s,
        every,
        keep,
    };
    let mut sim = Simulation::new(scenario);
    sim.set_parallel(parallel);
    let ids: Vec<u32> = scenario.followers.iter().map(|f| f.id).collect();
    let (metrics, error) = match sim.run(&mut observer, |_| {}) {
        Ok(metrics) => (metrics, None),
        Err(e) => (sim.metrics(), Some(e.to_string())),
    };
    let mut summary = Summary::new(scenario, ids.iter().copied().zip(metrics).collect());
    if error.is_none() {
        summary = summary.with_outages(scenario, &sim.outages());
    }
    summary.safety = sim.proximity().cloned();
    MemoryRun { followers: ids.into_iter().zip(observer.followers).collect(), leader: observer.leader, summary, error }
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_record::{read_columns, RecordOptions};

    fn paper(sets: &[&str]) -> Scenario {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        Scenario::load(std::path::Path::new("paper"), &sets).expect("the paper scenario")
    }

    /// The columns in memory are the CSVs `formation sim` writes, bit for
    /// bit, and so is the summary (every 1 and every 7, on 1 and 2 threads).
    #[test]
    fn a_run_in_memory_is_the_run_folder_bit_for_bit() {
        let s = paper(&["duration=1.5"]);
        for (every, threads) in [(1, 1), (7, 2)] {
            let dir = tempfile::tempdir().expect("tempdir");
            let opts = RecordOptions { dir: dir.path().join("run"), every, csv: true, mcap: false, rosbag2: false };
            let (summary, out) = formation_sim::run_to_folder(&s, &opts, threads, |_| {}).expect("sim");
            let m = run(&s, threads, Some(every)).expect("run in memory");
            let bare = run(&s, threads, None).expect("summary only");
            assert_eq!(bare.summary.to_json(), summary.to_json(), "the summary alone differs");
            assert_eq!(bare.followers[0].1.rows(), 0);
            assert_eq!(m.error, None);
            assert_eq!(m.summary.to_json(), summary.to_json(), "every {every}: summaries differ");
            for (id, cols) in &m.followers {
                let file = read_columns(&out.join(format!("follower_{id}.csv")), &cols.names).expect("csv");
                let (bits_a, bits_b): (Vec<Vec<u64>>, Vec<Vec<u64>>) = (
                    cols.data.iter().map(|c| c.iter().map(|v| v.to_bits()).collect()).collect(),
                    file.iter().map(|c| c.iter().map(|v| v.to_bits()).collect()).collect(),
                );
                assert!(bits_a == bits_b, "every {every}: follower {id}'s columns differ from its CSV");
            }
            let leader = read_columns(&out.join("leader.csv"), &m.leader.names).expect("leader csv");
            assert_eq!(leader, m.leader.data, "every {every}: the leader's columns differ from leader.csv");
            assert_eq!(m.leader.rows(), m.followers[0].1.rows());
        }
    }

    #[test]
    fn a_run_too_large_for_memory_is_refused_naming_every() {
        let s = paper(&["duration=2000", "dt=0.0001"]);
        let e = run(&s, 1, Some(1)).expect_err("20 M rows of 4 followers");
        assert!(e.contains("GB of samples") && e.contains("every=N"), "{e}");
        assert!(check_size(&s, 1000).is_ok());
        assert_eq!(check_size(&s, 0).unwrap_err(), "every must be at least 1");
    }
}
