//! The simulator on several threads equals the single-thread run byte for
//! byte: 1,000 generated followers, every CSV and the summary, with a fault
//! table so that the lossy-link path runs too, without and with a
//! communication delay (`network.delay_steps`).

use std::path::Path;
use std::process::Command;

fn formation(args: &[&str]) -> std::process::Output {
    let o = Command::new(env!("CARGO_BIN_EXE_formation")).args(args).output().expect("formation");
    assert!(o.status.success(), "formation {args:?}: {}", String::from_utf8_lossy(&o.stderr));
    o
}

#[test]
fn a_thousand_followers_on_two_threads_equal_one_thread_byte_for_byte() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let file = tmp.path().join("ring1000.toml");
    let f = file.display().to_string();
    formation(&["generate", "--followers", "1000", "--graph", "ring", "--chords", "200", "--seed", "3", "--out", &f]);
    let run = |threads: &str, delay: &str| {
        let out = tmp.path().join(format!("t{threads}-d{delay}"));
        formation(&[
            "sim",
            &f,
            "-q",
            "--threads",
            threads,
            "--set",
            "duration=0.3",
            "--set",
            "faults+={node=3, from=0.1, to=0.2}",
            "--set",
            "faults+={link=[1, 2], from=0, to=0.3, loss=0.3}",
            "--set",
            &format!("network.delay_steps={delay}"),
            "--out",
            &out.display().to_string(),
        ]);
        out
    };
    for delay in ["0", "2"] {
        same(&run("1", delay), &run("2", delay), delay);
    }
}

fn same(one: &Path, two: &Path, delay: &str) {
    let mut files: Vec<String> = std::fs::read_dir(one)
        .expect("run folder")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(files.len(), 1002, "1,000 follower CSVs, the leader's and summary.json: {}", files.len());
    let read = |dir: &Path, f: &str| std::fs::read(dir.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
    let differ: Vec<&String> = files.iter().filter(|f| read(one, f) != read(two, f)).collect();
    assert!(
        differ.is_empty(),
        "delay {delay} steps: {} of {} files differ between 1 and 2 threads, e.g. {:?}",
        differ.len(),
        files.len(),
        differ.first()
    );
}

/// Counts rows: an observer that wants them, so the simulator builds every row.
struct Rows(u64);
impl formation_sim::Observer for Rows {
    fn follower(&mut self, _: usize, _: u64, _: &formation_record::Row, _: bool) -> std::io::Result<()> {
        self.0 += 1;
        Ok(())
    }
}

/// Without an observer the simulator builds no rows (metrics only), on one
/// thread or on two: the metrics are those of the run that builds every row,
/// bit for bit, with and without faults and delay.
#[test]
fn metrics_without_rows_equal_metrics_from_rows_on_one_and_two_threads() {
    use formation_sim::{NoRecord, Simulation};
    let paper = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    // The paper's 4 followers for 12 s: the last 10 s start after step 0.
    let mut cases = vec![formation_scenario::Scenario::load(&paper, &["duration=12".to_string()]).expect("paper")];
    for delay in ["0", "2"] {
        let mut s = formation_scenario::generate::ring_with_chords(1000, 200, 3).expect("ring");
        s.duration_s = 0.3;
        cases.push(s);
        let sets = ["duration=12", "faults+={node=3, from=1, to=2}", "faults+={link=[1, 2], from=0, to=3, loss=0.3}"];
        let mut sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        sets.push(format!("network.delay_steps={delay}"));
        cases.push(formation_scenario::Scenario::load(&paper, &sets).expect("paper"));
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().expect("pool");
    for s in &cases {
        let bits = |m: Vec<formation_record::FollowerMetrics>| format!("{m:?}");
        let mut rows = Rows(0);
        let with_rows = bits(Simulation::new(s).run(&mut rows, |_| {}).expect("run"));
        assert_eq!(rows.0, s.followers.len() as u64 * (s.steps() + 1));
        let one = bits(Simulation::new(s).run(&mut NoRecord, |_| {}).expect("run"));
        let mut sim = Simulation::new(s);
        sim.set_parallel(true);
        let two = bits(pool.install(|| sim.run(&mut NoRecord, |_| {})).expect("run"));
        assert_eq!(one, with_rows, "{}: metrics without rows", s.name);
        assert_eq!(two, with_rows, "{}: metrics without rows on two threads", s.name);
    }
}
