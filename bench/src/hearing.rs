//! `formation bench-net --hearing`: what the hearing record costs. The
//! scenario in real time at 1 kHz with a one-step delay, alternately with
//! and without the record (`network.hearing_record`): the real-time loop's
//! period error side by side, the record's bytes per follower and step
//! against the CSVs', and how fast `formation replay` re-computes the run.

use std::time::Instant;

use formation_exit::Error;
use formation_launch::options::LaunchArgs;

/// Runs of each kind; the medians are printed.
const RUNS: usize = 3;

/// The worst node's |period − Δt| p50, p99 and max (µs) of a real-time run's network.json.
pub(crate) fn worst_period(net: &serde_json::Value) -> (f64, f64, f64) {
    let mut p = (0.0f64, 0.0f64, 0.0f64);
    for v in net["nodes"].as_object().into_iter().flat_map(|n| n.values()) {
        let f = |k: &str| v["loop"][k].as_f64().unwrap_or(0.0);
        p = (p.0.max(f("period_error_p50_us")), p.1.max(f("period_error_p99_us")), p.2.max(f("period_error_max_us")));
    }
    p
}

pub(crate) fn network_json(dir: &std::path::Path, what: &str) -> Result<serde_json::Value, Error> {
    std::fs::read_to_string(dir.join("network.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .ok_or_else(|| Error::Run(format!("reading {what}'s network.json")))
}

/// Two kinds of run's period errors (p50, p99, max µs each), medians side by side.
pub(crate) fn periods_side_by_side(a: (&str, &[(f64, f64, f64)]), b: (&str, &[(f64, f64, f64)])) {
    let m = |v: &[(f64, f64, f64)], f: fn(&(f64, f64, f64)) -> f64| median(v.iter().map(f).collect());
    let (on, off) = (a.1, b.1);
    println!("  {:<46}{:>16}{:>16}", "", a.0, b.0);
    println!(
        "  {:<46}{:>16}{:>16}",
        "worst node's |period − 1 ms| p50 / p99 µs",
        format!("{:.1} / {:.1}", m(on, |p| p.0), m(on, |p| p.1)),
        format!("{:.1} / {:.1}", m(off, |p| p.0), m(off, |p| p.1))
    );
    println!("  {:<46}{:>16}{:>16}", "  max µs", format!("{:.1}", m(on, |p| p.2)), format!("{:.1}", m(off, |p| p.2)));
}

pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn csv_bytes(dir: &std::path::Path) -> u64 {
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.path().extension().is_some_and(|x| x == "csv"))
        .map(|e| e.metadata().map_or(0, |m| m.len()))
        .sum()
}

/// `launch(sets, port, out, run)` builds the launch of one run.
pub fn run(
    duration_s: f64,
    port: u16,
    launch: &dyn Fn(&[String], u16, std::path::PathBuf, &str) -> LaunchArgs,
) -> Result<(), Error> {
    let tmp = std::env::temp_dir().join(format!("formation-bench-hearing-{}", std::process::id()));
    let mut on = Vec::new();
    let mut off = Vec::new();
    let mut sizes = Vec::new();
    let mut replay = Vec::new();
    for r in 0..RUNS {
        for record in [true, false] {
            eprintln!("bench-net --hearing: run {} of {RUNS}, record {} …", r + 1, if record { "on" } else { "off" });
            let sets = vec![
                format!("duration={duration_s}"),
                "timing=realtime".into(),
                "dt=0.001".into(),
                "network.delay_steps=1".into(),
                format!("network.hearing_record={record}"),
            ];
            let out = tmp.join(format!("run-{r}-{record}"));
            let mut l = launch(&sets, port + 10 * (2 * r as u16 + u16::from(record)), out.clone(), "bench-hearing");
            l.opts.time_scale = Some(1.0);
            formation_launch::launch::run(&l)?;
            let p = worst_period(&network_json(&out, "the real-time run")?);
            if record {
                on.push(p);
                let loaded = formation_replay::replay::load(&out)?;
                let steps: u64 = loaded.record.followers.iter().map(|f| f.steps()).sum();
                let bytes = std::fs::metadata(out.join(formation_record::HEARING_FILE)).map_or(0, |m| m.len());
                sizes.push((bytes, steps, csv_bytes(&out)));
                let t = Instant::now();
                formation_replay::replay::replay_to_folder(&loaded, &tmp.join(format!("replay-{r}")))?;
                replay.push(steps as f64 / t.elapsed().as_secs_f64());
            } else {
                off.push(p);
            }
            let _ = std::fs::remove_dir_all(&out);
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    println!("hearing record: real time at 1 kHz, one-step delay, {duration_s} s, median of {RUNS} runs each");
    periods_side_by_side(("record on", &on), ("record off", &off));
    let per_step = median(sizes.iter().map(|&(b, s, _)| b as f64 / s.max(1) as f64).collect());
    let share = median(sizes.iter().map(|&(b, _, c)| b as f64 / c.max(1) as f64).collect());
    let bytes = median(sizes.iter().map(|&(b, _, _)| b as f64).collect());
    println!("  hearing.bin: {bytes:.0} B, {per_step:.3} B per follower and step, {:.3} % of the CSVs", 100.0 * share);
    println!("  formation replay: {:.0} follower-steps/s (median)", median(replay));
    Ok(())
}
